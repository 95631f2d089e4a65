"""The edges of the safety code that the mutation run (tools/mutation.py) found untested:
MAVLink signing's length, stream and time-window boundaries, the signing key's forms, and the
limits of operator command acceptance, each tried exactly at its boundary."""

from __future__ import annotations

import logging
import math
import struct
from pathlib import Path

import pytest

from drivers.mavlink.signing import (
    NEW_STREAM_WINDOW,
    SIGNING_EPOCH_UNIX_S,
    SignatureVerifier,
    Verdict,
    frame_signature,
    load_signing_key,
    signing_timestamp_now,
)
from groundstation.operator import (
    MAX_TAKEOFF_ALT_M,
    CommandResult,
    FlightPhase,
    SetTilt,
    Takeoff,
    decide,
)

KEY = bytes(range(32))
#: our clock, in signing-timestamp units: one day after the signing epoch
NOW_TS = 86_400 * 100_000


def signed_frame(ts: int, *, payload: bytes = b"", link_id: int = 0, sysid: int = 255,
                 compid: int = 190, msgid: int = 76, crc: bytes = b"\x00\x00",
                 key: bytes = KEY) -> bytes:
    """A MAVLink2 frame with the signed flag, signed with ``key``: header (10 bytes), payload,
    CRC (not checked by the verifier), link id, 48-bit timestamp and the 6-byte signature."""
    header = bytes([0xFD, len(payload), 0x01, 0x00, 0x00, sysid, compid]) + \
        msgid.to_bytes(3, "little")
    body = header + payload + crc + bytes([link_id]) + struct.pack("<IH", ts & 0xFFFFFFFF,
                                                                 ts >> 32)
    return body + frame_signature(key, body)


def verifier() -> SignatureVerifier:
    return SignatureVerifier(KEY, unix_time=lambda: SIGNING_EPOCH_UNIX_S + NOW_TS / 100_000)


def test_that_the_signing_timestamp_counts_10_us_from_2015() -> None:
    assert signing_timestamp_now(SIGNING_EPOCH_UNIX_S) == 0
    assert signing_timestamp_now(SIGNING_EPOCH_UNIX_S + 1.0) == 100_000
    assert signing_timestamp_now(SIGNING_EPOCH_UNIX_S - 5.0) == 0
    assert SignatureVerifier(KEY).newest_timestamp == 0


def test_that_the_shortest_signed_frame_is_checked_and_a_shorter_one_is_unsigned() -> None:
    v = verifier()
    shortest = signed_frame(NOW_TS)  # no payload: 10 + 2 + 13 bytes
    assert len(shortest) == 25 and v.classify(shortest) is Verdict.GOOD
    assert v.classify(shortest[:24]) is Verdict.UNSIGNED
    assert v.classify(signed_frame(NOW_TS, key=bytes(32))) is Verdict.BAD_SIGNATURE


def test_that_a_frame_at_the_window_edge_is_good_and_one_tick_older_is_stale() -> None:
    v = verifier()
    assert v.classify(signed_frame(NOW_TS - NEW_STREAM_WINDOW)) is Verdict.GOOD
    assert v.classify(signed_frame(NOW_TS - NEW_STREAM_WINDOW - 1)) is Verdict.STALE


def test_that_each_link_system_and_component_is_a_stream_of_its_own() -> None:
    v = verifier()
    assert v.accept(signed_frame(NOW_TS + 100, crc=b"\x01\x02"), 76)
    # the same stream, an older timestamp: a replay (whatever the CRC bytes)
    assert v.classify(signed_frame(NOW_TS + 50, crc=b"\x03\x04")) is Verdict.REPLAY
    assert v.classify(signed_frame(NOW_TS + 100)) is Verdict.REPLAY
    # other streams have their own last timestamp
    assert v.classify(signed_frame(NOW_TS + 50, link_id=1)) is Verdict.GOOD
    assert v.classify(signed_frame(NOW_TS + 50, sysid=1)) is Verdict.GOOD
    assert v.classify(signed_frame(NOW_TS + 50, compid=1)) is Verdict.GOOD
    assert v.classify(signed_frame(NOW_TS + 50, msgid=77)) is Verdict.REPLAY  # not a stream key
    assert v.newest_timestamp == NOW_TS + 100
    assert v.stats().replayed == 0  # classify counts nothing


def test_that_a_key_file_of_32_raw_bytes_is_the_key_and_a_shared_one_warns(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    raw = bytes(range(200, 232))  # not ASCII
    path = tmp_path / "key.bin"
    path.write_bytes(raw)
    path.chmod(0o600)
    with caplog.at_level(logging.WARNING):
        assert load_signing_key(path, environ={}) == raw
    assert "readable by others" not in caplog.text
    path.chmod(0o644)
    with caplog.at_level(logging.WARNING):
        assert load_signing_key(path, environ={}) == raw
    assert "readable by others" in caplog.text
    assert load_signing_key(None, environ={}) is None


def test_that_takeoff_and_tilt_are_accepted_up_to_their_limits_included() -> None:
    armed, mission = FlightPhase.ARMED, FlightPhase.MISSION
    assert decide(Takeoff(MAX_TAKEOFF_ALT_M), armed) is CommandResult.ACCEPTED
    assert decide(Takeoff(math.nextafter(MAX_TAKEOFF_ALT_M, 9.0)), armed) is \
        CommandResult.DENIED
    assert decide(Takeoff(0.0), armed) is CommandResult.DENIED
    limit = math.radians(30.0)
    assert decide(SetTilt(0.0), mission, max_tilt_rad=limit) is CommandResult.ACCEPTED
    assert decide(SetTilt(limit), mission, max_tilt_rad=limit) is CommandResult.ACCEPTED
    assert decide(SetTilt(math.nextafter(limit, 1.0)), mission, max_tilt_rad=limit) is \
        CommandResult.DENIED
    assert decide(SetTilt(-1e-9), mission, max_tilt_rad=limit) is CommandResult.DENIED


def test_that_an_unknown_command_is_unsupported() -> None:
    class Dance:
        pass

    assert decide(Dance(), FlightPhase.MISSION) is CommandResult.UNSUPPORTED  # type: ignore[arg-type]


# -- the flight record: what a crash can leave behind is read, anything else refused --------
def test_that_a_record_killed_before_its_first_rows_reads_as_empty(tmp_path: Path) -> None:
    from groundstation.record import RecordWriter, read_record

    path = tmp_path / "empty.fhr"
    written = RecordWriter(path, {"session": "s"}).close()
    assert len(written.rows) == 0
    rec = read_record(path)  # exactly the header: no row yet
    assert len(rec.rows) == 0 and rec.metadata == {"session": "s"}
    assert len(RecordWriter(None).close().rows) == 0  # in memory only, nothing recorded


def test_that_a_cut_or_foreign_header_is_refused_with_its_reason(tmp_path: Path) -> None:
    from groundstation.record import MAGIC, RecordFormatError, RecordWriter, parse_record

    path = tmp_path / "r.fhr"
    RecordWriter(path, {}).close()
    data = path.read_bytes()
    (n,) = struct.unpack("<I", data[8:12])
    longer = data[:8] + struct.pack("<I", n + 5) + data[12:]  # says more header than there is
    with pytest.raises(RecordFormatError, match="no rows described"):
        parse_record(longer)
    with pytest.raises(RecordFormatError, match="corrupt record header"):
        parse_record(MAGIC + struct.pack("<I", 0))  # the magic and a length, nothing else
    with pytest.raises(RecordFormatError, match="bad magic"):
        parse_record(MAGIC[:7])


def test_that_the_signing_constants_are_mavlinks() -> None:
    from datetime import UTC, datetime

    assert datetime(2015, 1, 1, tzinfo=UTC).timestamp() == SIGNING_EPOCH_UNIX_S
    assert NEW_STREAM_WINDOW == 60 * 100_000  # one minute in 10 us units


def test_that_a_foreign_format_is_named_and_a_one_byte_row_type_reads() -> None:
    import json

    from groundstation.record import FORMAT, MAGIC, VERSION, RecordFormatError, parse_record

    def record(header: dict[str, object], body: bytes = b"") -> bytes:
        text = json.dumps(header).encode()
        return MAGIC + struct.pack("<I", len(text)) + text + body

    with pytest.raises(RecordFormatError, match="unsupported record format"):
        parse_record(record({"format": "other", "version": VERSION, "dtype": [["a", "u1"]]}))
    rec = parse_record(record({"format": FORMAT, "version": VERSION, "dtype": [["a", "u1"]]},
                              b"\x07\x08"))
    assert rec.rows["a"].tolist() == [7, 8]

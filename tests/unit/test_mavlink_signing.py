"""MAVLink2 signing: key sources, signature/replay verdicts, the codec under random bytes."""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pymavlink.dialects.v20 import common as mavlink2

from drivers.mavlink.link import MavlinkCodec
from drivers.mavlink.signing import (
    SignatureVerifier,
    SigningKeyError,
    Verdict,
    key_from_text,
    load_signing_key,
    signing_timestamp_now,
)

KEY = hashlib.sha256(b"labpass").digest()
OTHER_KEY = hashlib.sha256(b"not the lab").digest()
NOW_UNIX_S = 1_800_000_000.0
NOW_TS = signing_timestamp_now(NOW_UNIX_S)


class _Sink:
    def __init__(self) -> None:
        self.frames: list[bytes] = []

    def write(self, data: bytes) -> None:
        self.frames.append(bytes(data))


def _encoder(key: bytes | None, timestamp: int = NOW_TS, sysid: int = 255, compid: int = 190,
             link_id: int = 0) -> tuple[Any, _Sink]:
    sink = _Sink()
    mav = mavlink2.MAVLink(sink, srcSystem=sysid, srcComponent=compid)
    if key is not None:
        mav.signing.secret_key = key
        mav.signing.sign_outgoing = True
        mav.signing.link_id = link_id
        mav.signing.timestamp = timestamp
    return mav, sink


def _arm_frame(mav: Any, sink: _Sink) -> bytes:
    mav.command_long_send(1, 1, mavlink2.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
    return sink.frames[-1]


def _verifier(allow: frozenset[int] = frozenset()) -> SignatureVerifier:
    return SignatureVerifier(KEY, allow, unix_time=lambda: NOW_UNIX_S)


def test_that_a_key_is_read_as_hex_or_as_a_passphrase_like_mavproxy(tmp_path: Path) -> None:
    assert key_from_text("labpass\n") == KEY
    assert key_from_text(KEY.hex().upper()) == KEY
    f = tmp_path / "key"
    f.write_text(KEY.hex() + "\n")
    f.chmod(0o600)
    assert load_signing_key(f, environ={}) == KEY
    raw = tmp_path / "raw"
    raw.write_bytes(bytes(range(32)))
    assert load_signing_key(raw, environ={}) == bytes(range(32))
    assert load_signing_key(None, environ={"FASTHEX_MAVLINK_KEY": "labpass"}) == KEY
    assert load_signing_key(None, environ={}) is None


def test_that_a_missing_or_empty_key_names_its_source(tmp_path: Path) -> None:
    with pytest.raises(SigningKeyError, match="nokey"):
        load_signing_key(tmp_path / "nokey", environ={})
    empty = tmp_path / "empty"
    empty.write_text("  \n")
    with pytest.raises(SigningKeyError, match="empty"):
        load_signing_key(empty, environ={})
    with pytest.raises(SigningKeyError, match=r"\$K"):
        load_signing_key(None, env_var="K", environ={"K": ""})


def test_that_good_unsigned_wrong_key_and_replayed_frames_get_their_own_verdicts() -> None:
    # Fixture
    sut = _verifier(allow=frozenset({mavlink2.MAVLINK_MSG_ID_RADIO_STATUS}))
    good = _arm_frame(*_encoder(KEY))
    unsigned = _arm_frame(*_encoder(None))
    wrong = _arm_frame(*_encoder(OTHER_KEY))
    mav, sink = _encoder(None)
    mav.radio_status_send(200, 190, 100, 10, 8, 0, 0)
    radio = sink.frames[-1]
    arm = mavlink2.MAVLINK_MSG_ID_COMMAND_LONG
    # Test / Assert
    assert sut.accept(good, arm)
    assert not sut.accept(good, arm)  # byte-exact replay
    assert not sut.accept(unsigned, arm)
    assert not sut.accept(wrong, arm)
    assert sut.accept(radio, mavlink2.MAVLINK_MSG_ID_RADIO_STATUS)
    st_ = sut.stats()
    assert (st_.good, st_.replayed, st_.unsigned_rejected, st_.bad_signature,
            st_.unsigned_allowed) == (1, 1, 1, 1, 1)
    assert st_.rejected == 3


def test_that_a_badly_signed_frame_is_rejected_even_when_its_id_is_allow_listed() -> None:
    sut = _verifier(allow=frozenset({mavlink2.MAVLINK_MSG_ID_COMMAND_LONG}))
    wrong = _arm_frame(*_encoder(OTHER_KEY))
    assert sut.classify(wrong) is Verdict.BAD_SIGNATURE
    assert not sut.accept(wrong, mavlink2.MAVLINK_MSG_ID_COMMAND_LONG)


def test_that_a_forged_far_future_frame_does_not_lock_out_the_genuine_stream() -> None:
    # pymavlink 2.4.50 stores the timestamp before checking the MAC; we must not.
    sut = _verifier()
    forged = _arm_frame(*_encoder(OTHER_KEY, timestamp=NOW_TS + 10**9))
    assert not sut.accept(forged, 76)
    assert sut.accept(_arm_frame(*_encoder(KEY)), 76)


def test_that_a_frame_more_than_a_minute_old_is_stale_and_counted_apart() -> None:
    sut = _verifier()
    stale = _arm_frame(*_encoder(KEY, timestamp=NOW_TS - 61 * 100_000))
    fresh_enough = _arm_frame(*_encoder(KEY, timestamp=NOW_TS - 59 * 100_000, link_id=3))
    assert sut.classify(stale) is Verdict.STALE
    assert sut.classify(fresh_enough) is Verdict.GOOD
    assert not sut.accept(stale, 76)
    assert sut.accept(fresh_enough, 76)
    assert not sut.accept(fresh_enough, 76)  # the same frame again: a replay, not stale
    st_ = sut.stats()
    assert (st_.stale, st_.replayed, st_.good, st_.rejected) == (1, 1, 1, 2)


def test_that_the_codec_signs_what_it_sends_and_keeps_timestamps_increasing() -> None:
    codec = MavlinkCodec(1, 1, KEY)
    peer = MavlinkCodec(255, 190, KEY)
    frames = [codec.encode(mavlink2.MAVLink_heartbeat_message(13, 0, 1, 0, 3, 3))
              for _ in range(3)]
    assert all(f[2] & 0x01 for f in frames)
    assert [len(peer.decode(f)) for f in frames] == [1, 1, 1]
    assert peer.decode(frames[0]) == []  # replay
    assert peer.verifier is not None and peer.verifier.stats().replayed == 1


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=600))
def test_that_random_bytes_never_raise_from_the_codec(data: bytes) -> None:
    for key in (None, KEY):
        codec = MavlinkCodec(1, 1, key)
        codec.decode(data)
        codec.decode(b"\xfd" + data)
        assert codec.corrupted >= 0


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=300))
def test_that_random_bytes_never_raise_from_the_verifier(data: bytes) -> None:
    sut = _verifier()
    sut.accept(data, 0)
    sut.accept(b"\xfd\x00\x01" + data, 0)
    assert sut.stats().good == 0


def test_that_corrupted_bytes_between_frames_are_counted_and_dropped() -> None:
    codec = MavlinkCodec(1, 1, None)
    mav, sink = _encoder(None)
    good = _arm_frame(mav, sink)
    bad = bytearray(good)
    bad[12] ^= 0xFF  # payload byte: CRC fails
    msgs = codec.decode(b"noise" + bytes(bad) + good)
    assert [m.get_type() for m in msgs] == ["COMMAND_LONG"]
    assert codec.corrupted >= 2

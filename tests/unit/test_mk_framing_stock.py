"""Stock MikroKopter framing: the reference's byte vectors, receiver rules and properties."""

from __future__ import annotations

from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.mikrokopter import framing_stock as mk
from drivers.mikrokopter import messages as m

FC, ANY, NC = mk.Address.FLIGHT_CTRL, mk.Address.ANY, mk.Address.NAVI_CTRL

# (address, cmd, payload, exact frame) from protocol-mikrokopter.md §2.6
VECTORS: list[tuple[int, bytes, bytes, str]] = [
    (FC, b"v", b"", "23 62 76 40 78 0d"),
    (ANY, b"v", b"", "23 61 76 40 77 0d"),
    (ANY, b"d", b"\x0a", "23 61 64 3f 5d 3d 3d 44 7b 0d"),
    (ANY, b"d", b"\x00", "23 61 64 3d 3d 3d 3d 44 59 0d"),
    (FC, b"c", b"\x05", "23 62 63 3e 4d 3d 3d 44 6a 0d"),
    (FC, b"a", b"\x09", "23 62 61 3f 4d 3d 3d 44 69 0d"),
    (FC, b"t", bytes([20] * 6 + [0] * 10),
     "23 62 74 42 3e 4d 51 42 3e 4d 51" + " 3d" * 16 + " 59 42 0d"),
    (FC, b"t", b"\x01\x02\x03\x04", "23 62 74 3d 4d 45 40 3e 3d 3d 3d 48 7a 0d"),
    (FC, b"b", bytes.fromhex("00000064010100"),
     "23 62 62 3d 3d 3d 3d 56 3d 41 3e 3d 3d 3d 3d 4c 5e 0d"),
    (NC, b"u", b"\x00", "23 63 75 3d 3d 3d 3d 44 6c 0d"),
    (ANY, b"k", b"\x05", "23 61 6b 3e 4d 3d 3d 44 71 0d"),
    (FC, b"X", b"abc", "23 62 58 55 53 46 60 45 68 0d"),
    (FC, b"X", b"\x00\x01\x02\x03", "23 62 58 3d 3d 41 3f 3d 6d 3d 3d 48 78 0d"),
    (FC, b"X", b"\xff\xff", "23 62 58 7c 7c 79 3d 47 48 0d"),
    (FC, b"T", b"", "23 62 54 40 56 0d"),
    (FC, b"B", b"\x01", "23 62 42 3d 4d 3d 3d 44 48 0d"),
    (FC, b"V", bytes.fromhex("020c0ba50000001 9ff00".replace(" ", "")),
     "23 62 56 3d 5d 6d 48 66 4d 3d 3d 3d 3e 64 7c 3d 3d 3d 3d 53 63 0d"),
    (FC, b"C", bytes.fromhex("f1ff1e0008070000000002000000"),
     "23 62 43 79 5c 79 5b 3d 3d 5d 44 3d 3d 3d 3d 3d 3d 45 3d 3d 3d 3d 3d 56 6d 0d"),
]

DEBUG_FRAME = bytes.fromhex(
    "23 62 44 3d 3d 3d 3d 3d 3d 41 3d 3d 5d 3d 40 3d 3d 4d 3d 3e 4d 3d 43 3d 3d 59 3d 3f 3d 3d"
    " 46 3d 3d 65 3d 3f 6d 3d 49 3d 3d 71 3d 40 5d 3d 4c 3d 3e 3d 3d 41 4d 3d 4f 3d 3e 49 3d 42"
    " 3d 3d 52 3d 3e 55 3d 42 6d 3d 55 3d 3e 61 3d 43 5d 3d 58 3d 3e 6d 3d 44 4d 3d 5b 3d 3e 79"
    " 3d 5f 7c 0d")


def _padded(payload: bytes) -> bytes:
    return payload + bytes(-len(payload) % 3)


def test_that_every_reference_vector_is_encoded_byte_for_byte() -> None:
    for address, cmd, payload, wire in VECTORS:
        assert mk.encode_frame(address, cmd, payload) == bytes.fromhex(wire), wire


def test_that_every_reference_vector_decodes_to_its_padded_payload() -> None:
    for address, cmd, payload, wire in VECTORS:
        sut = mk.StockParser()
        assert sut.feed(bytes.fromhex(wire)) == [mk.StockFrame(address, cmd, _padded(payload))]


def test_that_the_debug_frame_vector_matches_both_ways() -> None:
    debug = m.DebugOut((0, 0), tuple(range(32)))
    assert mk.encode_frame(FC, b"D", debug.payload()) == DEBUG_FRAME
    (frame,) = mk.StockParser().feed(DEBUG_FRAME)
    assert m.decode_stock_message(frame.cmd, frame.data) == debug


def test_that_struct_replies_decode_with_units() -> None:
    (v,) = mk.StockParser().feed(bytes.fromhex(VECTORS[16][3]))
    version = m.decode_stock_message(v.cmd, v.data)
    assert isinstance(version, m.VersionInfo)
    assert (version.version, version.proto_major, version.hw_major) == ("2.12a", 11, 25)
    (c,) = mk.StockParser().feed(bytes.fromhex(VECTORS[17][3]))
    data3d = m.decode_stock_message(c.cmd, c.data)
    assert isinstance(data3d, m.Data3D)
    assert data3d.angles_deg == (-1.5, 3.0, 180.0)
    assert data3d.acc_z_raw == 512


def test_that_a_one_byte_payload_decodes_with_its_padding() -> None:
    (frame,) = mk.StockParser().feed(bytes.fromhex("23 61 64 3f 5d 3d 3d 44 7b 0d"))
    assert frame.data == b"\x0a\x00\x00"
    assert m.decode_stock_message(frame.cmd, frame.data) == m.DebugRequest(100)


def test_that_an_over_decoded_payload_is_truncated_to_the_struct_size() -> None:
    version = m.VersionInfo(2, 12, 11, 0xA5, 0, (0, 0), 25, 255, 0)
    assert m.VersionInfo.decode(version.payload() + b"\x00\x00\x07\x41") == version


def test_that_changing_any_byte_before_the_checksum_fails_the_frame() -> None:
    wire = bytes.fromhex(VECTORS[8][3])
    for i in range(1, len(wire) - 3):
        for delta in (1, 2, 7):
            bad = bytearray(wire)
            bad[i] = mk.BASE + (bad[i] - mk.BASE + delta) % 64
            sut = mk.StockParser()
            assert sut.feed(bytes(bad)) == []
            assert sut.stats.bad_checksum + sut.stats.bad_format == 1


def test_that_a_frame_over_220_chars_is_dropped() -> None:
    sut = mk.StockParser()
    wire = mk.encode_frame(FC, b"X", bytes(159))
    assert len(wire) == 218
    too_long = b"#bX" + b"=" * 216 + b"==\r"
    assert sut.feed(too_long + wire) == [mk.StockFrame(FC, b"X", bytes(159))]
    assert sut.stats.oversize == 1


def test_that_a_new_start_byte_restarts_a_frame() -> None:
    sut = mk.StockParser()
    assert sut.feed(b"#bX==" + bytes.fromhex(VECTORS[0][3])) == [mk.StockFrame(FC, b"v", b"")]
    assert sut.stats.truncated == 1


@given(st.binary(max_size=600))
def test_that_random_bytes_never_raise(data: bytes) -> None:
    sut = mk.StockParser()
    for frame in sut.feed(data):
        assert len(frame.data) % 3 == 0


@settings(max_examples=300)
@given(address=st.sampled_from(list(mk.Address)),
       cmd=st.sampled_from([bytes((c,)) for c in b"abcdtvVDCBTX"]),
       payload=st.binary(max_size=159), garbage=st.binary(max_size=80),
       trailing=st.binary(max_size=80),
       cuts=st.lists(st.integers(min_value=0, max_value=600), max_size=6))
def test_that_a_valid_frame_is_recovered_from_any_chunking_and_garbage(
        address: int, cmd: bytes, payload: bytes, garbage: bytes, trailing: bytes,
        cuts: list[int]) -> None:
    wire = garbage + mk.encode_frame(address, cmd, payload) + trailing
    points = sorted({min(c, len(wire)) for c in cuts})
    sut = mk.StockParser()
    out: list[mk.StockFrame] = []
    for a, b in zip([0, *points], [*points, len(wire)], strict=True):
        out += sut.feed(wire[a:b])
    assert mk.StockFrame(address, cmd, _padded(payload)) in out


@given(st.binary(max_size=300))
def test_that_encode64_and_decode64_are_inverse(payload: bytes) -> None:
    assert mk.decode64(mk.encode64(payload)) == _padded(payload)

"""Protocol 1.0 codec: the e-Manual's byte vectors, resync, and random bytes."""

from __future__ import annotations

from hypothesis import given
from hypothesis import strategies as st

from drivers.dynamixel import protocol1 as p1
from drivers.dynamixel.control_table import ErrorBit, Instruction, Reg


def hx(text: str) -> bytes:
    return bytes.fromhex(text)


def test_that_the_emanual_instruction_vectors_are_encoded_byte_for_byte() -> None:
    assert p1.encode_instruction(1, Instruction.PING) == hx("FF FF 01 02 01 FB")
    assert p1.encode_instruction(1, Instruction.READ, bytes((43, 1))) == hx(
        "FF FF 01 04 02 2B 01 CC")
    assert p1.encode_instruction(1, Instruction.WRITE, hx("0C 64 AA")) == hx(
        "FF FF 01 05 03 0C 64 AA DC")


def test_that_the_tilt_servo_vectors_derived_in_the_reference_are_encoded() -> None:
    assert p1.encode_instruction(1, Instruction.READ, bytes((0, 2))) == hx(
        "FF FF 01 04 02 00 02 F6")
    assert p1.encode_instruction(1, Instruction.WRITE, hx("06 FF 0F FF 0F")) == hx(
        "FF FF 01 07 03 06 FF 0F FF 0F D2")
    assert p1.encode_instruction(1, Instruction.WRITE, bytes((Reg.TORQUE_ENABLE, 1))) == hx(
        "FF FF 01 04 03 18 01 DE")
    assert p1.encode_instruction(1, Instruction.WRITE, (30).to_bytes(1, "little")
                                 + (7964).to_bytes(2, "little")) == hx("FF FF 01 05 03 1E 1C 1F 9D")
    assert p1.encode_instruction(1, Instruction.WRITE, bytes((30,))
                                 + (-7964 & 0xFFFF).to_bytes(2, "little")) == hx(
        "FF FF 01 05 03 1E E4 E0 14")
    assert p1.encode_instruction(1, Instruction.READ, bytes((36, 11))) == hx(
        "FF FF 01 04 02 24 0B C9")


def test_that_the_emanual_status_vectors_are_encoded_and_decoded() -> None:
    # Fixture
    vectors = {
        hx("FF FF 01 02 00 FC"): (0, b""),
        hx("FF FF 01 03 00 20 DB"): (0, bytes((32,))),
        hx("FF FF 01 02 24 D8"): (int(ErrorBit.OVERLOAD | ErrorBit.OVERHEATING), b""),
        hx("FF FF 01 04 00 1D 00 DD"): (0, hx("1D 00")),
        hx("FF FF 01 04 00 E4 E0 36"): (0, hx("E4 E0")),
    }
    for wire, (error, params) in vectors.items():
        # Test
        encoded = p1.encode_status(1, error, params)
        decoded = p1.Parser().feed(wire)
        # Assert
        assert encoded == wire
        assert decoded == [p1.Packet(1, error, params, True)]


def test_that_a_packet_split_at_any_offset_is_decoded_once() -> None:
    wire = b"\x00\xff\x13" + p1.encode_status(1, 0, hx("E4 E0")) + p1.encode_instruction(2, 1)
    for cut in range(len(wire) + 1):
        sut = p1.Parser()
        packets = sut.feed(wire[:cut]) + sut.feed(wire[cut:])
        assert packets == [p1.Packet(1, 0, hx("E4 E0")), p1.Packet(2, 1, b"")]


def test_that_a_bad_checksum_is_reported_and_counted_and_the_next_packet_survives() -> None:
    bad = bytearray(p1.encode_instruction(1, Instruction.PING))
    bad[-1] ^= 0xFF
    sut = p1.Parser()
    packets = sut.feed(bytes(bad) + p1.encode_instruction(1, Instruction.PING))
    assert [p.checksum_ok for p in packets] == [False, True]
    assert sut.checksum_errors == 1


def test_that_noise_and_impossible_lengths_are_dropped_and_counted() -> None:
    sut = p1.Parser()
    packets = sut.feed(b"abc\xff\xff\x01\x01\xff\xff\xff" + p1.encode_status(1, 0))
    assert packets == [p1.Packet(1, 0, b"")]
    assert sut.dropped_bytes >= 3


@given(st.binary(max_size=600))
def test_that_random_bytes_never_raise(data: bytes) -> None:
    sut = p1.Parser()
    for i in range(0, len(data), 7):
        for packet in sut.feed(data[i : i + 7]):
            assert 0 <= packet.dxl_id <= 0xFE
            assert len(packet.params) <= p1.MAX_LENGTH - 2


@given(st.integers(0, 0xFE), st.integers(0, 0x7F), st.binary(max_size=60), st.binary(max_size=20))
def test_that_any_status_round_trips_after_noise(dxl_id: int, error: int, params: bytes,
                                                 noise: bytes) -> None:
    noise = noise.replace(b"\xff", b"")
    packets = p1.Parser().feed(noise + p1.encode_status(dxl_id, error, params))
    assert packets[-1] == p1.Packet(dxl_id, error, params, True)

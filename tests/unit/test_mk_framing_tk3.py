"""tk3 framing: the reference's byte vectors, parser edge cases and properties."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.mikrokopter import framing_tk3 as tk3
from drivers.mikrokopter import messages as m

# (message = cmd + payload, exact frame on the wire) from protocol-mikrokopter.md §4.7
VECTORS: list[tuple[bytes, str]] = [
    (m.Identify().encode(), "5e 3f 24"),
    (m.IdentityMessage("mkfl1.8").encode(), "5e 3f 6d 6b 66 6c 31 2e 38 24"),
    (m.SetStreamPeriod.from_rate_hz(m.Stream.IMU, 500).encode(), "5e 69 00 00 07 d0 24"),
    (m.SetStreamPeriod.from_rate_hz(m.Stream.IMU, 1000).encode(), "5e 69 00 00 03 e8 24"),
    (m.SetStreamPeriod.from_rate_hz(m.Stream.MOTOR, 20).encode(), "5e 6d 00 00 c3 50 24"),
    (m.SetStreamPeriod.from_rate_hz(m.Stream.BATTERY, 1).encode(), "5e 62 00 0f 42 40 24"),
    (m.SetStreamPeriod.from_rate_hz(m.Stream.MAG, 0).encode(), "5e 63 00 00 00 00 24"),
    (m.StartMotors(1).encode(), "5e 67 01 24"),
    (m.StartMotors().encode(), "5e 67 24"),
    (m.StopMotors().encode(), "5e 78 24"),
    (m.StopMotors(3).encode(), "5e 78 03 24"),
    (m.Beep(440).encode(), "5e 7e 01 b8 24"),
    (m.SpinRates.from_hz([100, -100, 80, -80, 60, -60]).encode(),
     "5e 77 13 88 ec 78 18 6a e7 96 20 8d df 73 24"),
    (m.SpinRates.from_hz([0.0] * 6).encode(), "5e 77 7f ff 7f ff 7f ff 7f ff 7f ff 7f ff 24"),
    (m.Throttles.from_pct([50.0] * 6).encode(), "5e 71 01 ff 01 ff 01 ff 01 ff 01 ff 01 ff 24"),
    (m.ImuMessage(7, (0.0, 0.0, 9.81), (0.01, -0.02, 0.03)).encode(),
     "5e 49 07 00 00 00 00 26 52 00 0a ff ec 00 1e 24"),
    (m.MotorMessage(9, 2, False, True, False, 5000, 400, 1.5).encode(),
     "5e 4d 09 22 13 88 01 90 05 dc 24"),
    (m.BatteryMessage(1, 16.8).encode(), "5e 42 01 41 a0 24"),
    (m.MagMessage(3, (2000e-8, -1000e-8, 4000e-8)).encode(), "5e 43 03 07 d0 fc 18 0f a0 24"),
    (m.TextMessage(b"N", "hello").encode(), "5e 4e 68 65 6c 6c 6f 24"),
    (m.SetStreamPeriod(m.Stream.IMU, 0x24).encode(), "5e 69 00 00 00 5c db 24"),
    (b"X\x5e\x24\x5c\x21", "5e 58 5c a1 5c db 5c a3 5c de 24"),
]


def test_that_every_reference_vector_is_encoded_byte_for_byte() -> None:
    for message, wire in VECTORS:
        assert tk3.encode_frame(message) == bytes.fromhex(wire), wire


def test_that_every_reference_vector_decodes_back_to_its_message() -> None:
    for message, wire in VECTORS:
        sut = tk3.Tk3Parser()
        assert sut.feed(bytes.fromhex(wire)) == [message]
        assert sut.stats.frame_errors == 0 and sut.stats.garbage_bytes == 0


def test_that_a_second_start_byte_restarts_the_message() -> None:
    sut = tk3.Tk3Parser()
    assert sut.feed(b"^ab^cd$") == [b"cd"]
    assert sut.stats.truncated == 1


def test_that_an_abort_byte_drops_the_message() -> None:
    sut = tk3.Tk3Parser()
    assert sut.feed(b"^abc!def$") == []
    assert sut.stats.aborted == 1
    assert sut.stats.garbage_bytes == 4


def test_that_an_escaped_end_byte_is_part_of_the_payload() -> None:
    sut = tk3.Tk3Parser()
    assert sut.feed(bytes.fromhex("5e 69 5c db 00 24")) == [b"\x69\x24\x00"]


def test_that_a_message_over_64_bytes_is_dropped_and_counted() -> None:
    sut = tk3.Tk3Parser()
    out = sut.feed(b"^" + b"a" * 65 + b"$^ok$")
    assert out == [b"ok"]
    assert sut.stats.oversize == 1


def test_that_a_64_byte_message_is_accepted() -> None:
    assert tk3.Tk3Parser().feed(tk3.encode_frame(b"a" * 64)) == [b"a" * 64]


def test_that_an_escape_of_a_plain_byte_is_counted_as_a_bad_frame() -> None:
    sut = tk3.Tk3Parser()
    assert sut.feed(b"^I\\\x00$") == []
    assert sut.stats.bad_escape == 1


def test_that_an_empty_frame_is_counted() -> None:
    sut = tk3.Tk3Parser()
    assert sut.feed(b"^$") == []
    assert sut.stats.empty == 1


def test_that_a_frame_split_at_any_offset_is_decoded_once() -> None:
    # Fixture
    payload = b"I\x07^$!\\"
    wire = b"\x00noise" + tk3.encode_frame(payload)
    for cut in range(len(wire) + 1):
        sut = tk3.Tk3Parser()
        # Test
        frames = sut.feed(wire[:cut]) + sut.feed(wire[cut:])
        # Assert
        assert frames == [payload]


@given(st.binary(max_size=600))
def test_that_random_bytes_never_raise(data: bytes) -> None:
    sut = tk3.Tk3Parser()
    for msg in sut.feed(data):
        assert 1 <= len(msg) <= tk3.MAX_MESSAGE_BYTES


@settings(max_examples=300)
@given(
    message=st.binary(min_size=1, max_size=64),
    garbage=st.binary(max_size=80),
    trailing=st.binary(max_size=80),
    cuts=st.lists(st.integers(min_value=0, max_value=400), max_size=6),
)
def test_that_a_valid_frame_is_recovered_from_any_chunking_and_garbage(
        message: bytes, garbage: bytes, trailing: bytes, cuts: list[int]) -> None:
    # Garbage may itself hold frames; ours must come out, whatever the chunk boundaries.
    wire = garbage + tk3.encode_frame(message) + trailing
    points = sorted({min(c, len(wire)) for c in cuts})
    chunks = [wire[a:b] for a, b in zip([0, *points], [*points, len(wire)], strict=True)]
    sut = tk3.Tk3Parser()
    out: list[bytes] = []
    for chunk in chunks:
        out += sut.feed(chunk)
    assert message in out


@given(st.binary(max_size=200), st.binary(min_size=1, max_size=64))
def test_that_a_frame_after_any_garbage_including_start_bytes_is_recovered(
        garbage: bytes, message: bytes) -> None:
    # A '^' in the garbage opens a frame that our '^' restarts: our message still comes out.
    sut = tk3.Tk3Parser()
    out = sut.feed(garbage + tk3.encode_frame(message))
    assert out[-1] == message


# ---- fixed message lengths per command (the board's messages: the driver's configuration)

IMU_FRAME = tk3.encode_frame(m.ImuMessage(7, (0.0, 0.0, 9.81), (0.01, -0.02, 0.03)).encode())


def test_that_a_fixed_length_frame_whose_end_byte_was_corrupted_is_dropped_at_once() -> None:
    # Fixture: an IMU frame whose '$' arrived as 'A'; nothing follows yet (lockstep: the next
    # frame comes only after the next command)
    wire = IMU_FRAME[:-1] + b"A"
    plain = tk3.Tk3Parser()
    sut = tk3.Tk3Parser(message_bytes_by_cmd=m.BOARD_MESSAGE_BYTES)
    # Test
    assert plain.feed(wire) == [] and sut.feed(wire) == []
    # Assert: the plain parser still waits for the frame's end; ours has counted it
    assert plain.stats.frame_errors == 0
    assert sut.stats.oversize == 1 and sut.stats.frame_errors == 1
    # and the next frame comes out whole
    assert sut.feed(IMU_FRAME) == [IMU_FRAME[1:-1]]


def test_that_a_frame_of_its_commands_exact_length_is_accepted_escaped_or_not() -> None:
    sut = tk3.Tk3Parser(message_bytes_by_cmd={b"I": 4})
    assert sut.feed(tk3.encode_frame(b"I^$!") + tk3.encode_frame(b"Iabc")) == [b"I^$!", b"Iabc"]
    assert sut.feed(tk3.encode_frame(b"Iabcd") + tk3.encode_frame(b"J" * 64)) == [b"J" * 64]
    assert sut.stats.oversize == 1


def test_that_an_impossible_message_length_is_refused() -> None:
    for lengths in ({b"I": 0}, {b"I": 65}, {b"IM": 4}):
        with pytest.raises(ValueError, match="message length"):
            tk3.Tk3Parser(message_bytes_by_cmd=lengths)


@given(st.binary(max_size=600))
def test_that_random_bytes_never_raise_with_fixed_lengths(data: bytes) -> None:
    sut = tk3.Tk3Parser(message_bytes_by_cmd=m.BOARD_MESSAGE_BYTES)
    for msg in sut.feed(data):
        assert 1 <= len(msg) <= m.BOARD_MESSAGE_BYTES.get(msg[:1], tk3.MAX_MESSAGE_BYTES)


@settings(max_examples=300)
@given(
    seq=st.integers(0, 255),
    accel=st.tuples(*[st.floats(-150.0, 150.0)] * 3),
    gyro=st.tuples(*[st.floats(-30.0, 30.0)] * 3),
    cuts=st.lists(st.integers(min_value=0, max_value=60), max_size=6),
)
def test_that_any_imu_frame_comes_out_whole_from_any_chunking_with_fixed_lengths(
        seq: int, accel: tuple[float, float, float], gyro: tuple[float, float, float],
        cuts: list[int]) -> None:
    # escaped payload bytes count once each: the length is checked on the unescaped message
    message = m.ImuMessage(seq, accel, gyro).encode()
    wire = tk3.encode_frame(message) * 2
    points = sorted({min(c, len(wire)) for c in cuts})
    sut = tk3.Tk3Parser(message_bytes_by_cmd=m.BOARD_MESSAGE_BYTES)
    out: list[bytes] = []
    for a, b in zip([0, *points], [*points, len(wire)], strict=True):
        out += sut.feed(wire[a:b])
    assert out == [message, message] and sut.stats.frame_errors == 0

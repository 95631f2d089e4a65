"""The pipe format between the libmotioncapture child process and the adapter: what the child
encodes the adapter decodes as it was; anything else is a :class:`PipeFormatError`."""

from __future__ import annotations

import io
import math
import struct

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.mocap.motioncapture_child import (
    MAX_PAYLOAD_BYTES,
    STAGE_CONNECT,
    STAGE_FRAMES,
    BodyPose,
    ChildError,
    Frame,
    PipeFormatError,
    encode_connected,
    encode_error,
    encode_frame,
    read_message,
)

NAN7 = (math.nan,) * 7


def test_that_a_stream_of_messages_decodes_as_it_was_encoded() -> None:
    # Fixture: connect, a frame of two bodies (one the library gave no numbers for), an error
    pose = (1.25, -0.5, 0.8, 0.5, 0.5, -0.5, 0.5)
    stream = io.BytesIO(encode_connected()
                        + encode_frame(123_456_789, math.nan, [("fasthex", True, pose),
                                                               ("pad é", False, NAN7)])
                        + encode_frame(123_456_999, 2.5, [])
                        + encode_error(STAGE_FRAMES, "Connection lost ünexpectedly"))
    # Test
    messages = [read_message(stream) for _ in range(5)]
    # Assert
    assert messages[0] == b"C"
    frame = messages[1]
    assert isinstance(frame, Frame) and frame.rx_monotonic_ns == 123_456_789
    assert math.isnan(frame.library_time_s)
    assert frame.bodies[0] == BodyPose("fasthex", True, (1.25, -0.5, 0.8),
                                       (0.5, 0.5, -0.5, 0.5))
    assert frame.bodies[1].name == "pad é" and not frame.bodies[1].ok
    assert messages[2] == Frame(123_456_999, 2.5, ())
    assert messages[3] == ChildError(STAGE_FRAMES, "Connection lost ünexpectedly")
    assert messages[4] is None  # the end of the stream


@pytest.mark.parametrize("data,fragment", [
    (encode_connected()[:3], "inside a message header"),
    (encode_error(STAGE_CONNECT, "refused")[:-1], "inside a message"),
    (struct.pack("<IB", MAX_PAYLOAD_BYTES + 1, ord("F")), "byte message"),
    (struct.pack("<IB", 0, ord("Z")), "unknown kind 90"),
    (struct.pack("<IB", 1, ord("C")) + b"x", "unknown kind 67"),
    (struct.pack("<IB", 14, ord("F")) + struct.pack("<qdH", 1, 0.0, 1)[:14], "malformed"),
    (encode_frame(1, 0.0, [("a", True, NAN7)])[:-1], "inside a message"),
    (struct.pack("<IB", 19, ord("F")) + struct.pack("<qdH", 1, 0.0, 0) + b"x", "after the last"),
])
def test_that_bytes_that_are_not_the_format_are_a_pipe_format_error(
        data: bytes, fragment: str) -> None:
    with pytest.raises(PipeFormatError, match=fragment):
        read_message(io.BytesIO(data))


@settings(max_examples=400, deadline=None)
@given(st.binary(max_size=200))
def test_that_any_bytes_decode_or_are_a_pipe_format_error(data: bytes) -> None:
    stream = io.BytesIO(data)
    try:
        while (msg := read_message(stream)) is not None:
            assert isinstance(msg, (bytes, Frame, ChildError))
    except PipeFormatError:
        pass

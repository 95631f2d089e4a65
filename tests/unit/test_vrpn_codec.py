"""VRPN codec and client message handling: byte vectors, split streams, hostile bytes."""

from __future__ import annotations

import contextlib
import math
import struct

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.mocap import vrpn
from drivers.mocap.pose import TrackingStatus
from drivers.mocap.vrpn import SystemType, TrackerPose, VrpnDecodeError, VrpnStreamParser
from drivers.mocap.vrpn_client import VrpnClient, VrpnConfig


def test_that_the_cookie_is_24_bytes_with_version_two_spaces_and_log_mode() -> None:
    assert vrpn.encode_cookie() == b"vrpn: ver. 07.38  0" + b"\0" * 5
    assert vrpn.check_cookie(b"vrpn: ver. 07.35  0\0\0\0\0\0") == "vrpn: ver. 07.35"
    with pytest.raises(VrpnDecodeError):
        vrpn.check_cookie(b"vrpn: ver. 08.00  0\0\0\0\0\0")


def test_that_a_pos_quat_message_has_the_documented_big_endian_layout() -> None:
    wire = vrpn.encode_message(3, 7, vrpn.encode_pos_quat(
        TrackerPose(0, (1.0, 2.0, 3.0), (0.0, 0.0, 0.0, 1.0))), 100.25)
    # header: length = 24 + 64 unpadded, tv_sec, tv_usec, sender, type, 4 padding bytes
    assert struct.unpack_from(">5i", wire) == (88, 100, 250000, 3, 7)
    assert wire[20:24] == b"\0" * 4 and len(wire) == 88
    assert struct.unpack_from(">i4x3d4d", wire, 24) == (0, 1.0, 2.0, 3.0, 0.0, 0.0, 0.0, 1.0)


def test_that_a_description_is_padded_to_eight_bytes_and_decodes() -> None:
    wire = vrpn.encode_description(SystemType.SENDER_DESCRIPTION, 0, "Tracker0")
    # payload: uint32 9, "Tracker0\0" = 13 bytes -> padded to 16
    assert struct.unpack_from(">i", wire)[0] == 24 + 13 and len(wire) == 24 + 16
    [msg] = VrpnStreamParser(expect_cookie=False).feed(wire)
    assert (msg.sender_id, msg.type_id) == (0, -1)
    assert vrpn.decode_description(msg.payload) == "Tracker0"


def test_that_a_stream_split_at_any_offset_yields_the_same_messages() -> None:
    wire = vrpn.encode_cookie() + b"".join(
        vrpn.encode_message(0, 1, bytes(range(n)), 1.0) for n in (0, 1, 7, 8, 9, 64))
    whole = VrpnStreamParser().feed(wire)
    assert [len(m.payload) for m in whole] == [0, 1, 7, 8, 9, 64]
    for cut in range(len(wire) + 1):
        sut = VrpnStreamParser()
        assert sut.feed(wire[:cut]) + sut.feed(wire[cut:]) == whole


def test_that_an_impossible_length_raises_the_decode_error() -> None:
    with pytest.raises(VrpnDecodeError):
        VrpnStreamParser(expect_cookie=False).feed(struct.pack(">5i4x", 3, 0, 0, 0, 0))


def test_that_the_udp_connection_request_round_trips() -> None:
    assert vrpn.decode_lob(vrpn.encode_lob("127.0.0.1", 51221)) == ("127.0.0.1", 51221)
    with pytest.raises(VrpnDecodeError):
        vrpn.decode_lob(b"garbage\0")


@settings(max_examples=400)
@given(data=st.binary(max_size=400), cookie=st.booleans())
def test_that_random_stream_bytes_only_ever_raise_the_decode_error(data: bytes,
                                                                   cookie: bool) -> None:
    try:
        for m in VrpnStreamParser(expect_cookie=cookie).feed(data):
            for fn in (vrpn.decode_description, vrpn.decode_pos_quat):
                with contextlib.suppress(VrpnDecodeError):
                    fn(m.payload)
    except VrpnDecodeError:
        pass


def _client() -> VrpnClient:
    sut = VrpnClient(VrpnConfig(tracker="Hex"), clock=lambda: 1_000_000_000)
    sut._handle(VrpnStreamParser(expect_cookie=False).feed(
        vrpn.encode_description(SystemType.SENDER_DESCRIPTION, 4, "Hex")
        + vrpn.encode_description(SystemType.TYPE_DESCRIPTION, 2, vrpn.POS_QUAT_TYPE)))
    return sut


def test_that_a_report_of_the_named_tracker_becomes_a_z_up_world_pose() -> None:
    sut = _client()
    sut._handle(VrpnStreamParser(expect_cookie=False).feed(vrpn.encode_message(
        4, 2, vrpn.encode_pos_quat(TrackerPose(0, (1.0, 2.0, 3.0), (0.0, 0.0, 0.0, 1.0))), 5.0)))
    s = sut.latest()
    assert s is not None and s.valid and s.pos_w_m == (1.0, 2.0, 3.0)


def test_that_reports_of_other_senders_and_short_payloads_are_not_poses() -> None:
    sut = _client()
    feed = VrpnStreamParser(expect_cookie=False).feed
    sut._handle(feed(vrpn.encode_message(5, 2, vrpn.encode_pos_quat(
        TrackerPose(0, (1.0, 2.0, 3.0), (0.0, 0.0, 0.0, 1.0))), 5.0)))
    sut._handle(feed(vrpn.encode_message(4, 2, b"\0" * 40, 5.0)))
    assert sut.latest() is None and sut.stats().malformed_packets == 1


def test_that_a_zero_quaternion_is_reported_invalid() -> None:
    sut = _client()
    sut._handle(VrpnStreamParser(expect_cookie=False).feed(vrpn.encode_message(
        4, 2, vrpn.encode_pos_quat(TrackerPose(0, (1.0, 2.0, 3.0), (0.0, 0.0, 0.0, 0.0))), 5.0)))
    s = sut.latest()
    assert s is not None and s.status is TrackingStatus.INVALID and math.isnan(s.pos_w_m[0])


@settings(max_examples=300)
@given(payload=st.binary(max_size=100), sender=st.integers(-6, 6), kind=st.integers(-6, 6))
def test_that_random_messages_never_raise_in_the_client(payload: bytes, sender: int,
                                                        kind: int) -> None:
    sut = _client()
    sut._handle(VrpnStreamParser(expect_cookie=False).feed(
        vrpn.encode_message(sender, kind, payload, 1.0)))
    s = sut.latest()
    if s is not None and s.valid:
        assert len(payload) >= 64 and all(math.isfinite(c) for c in s.pos_w_m)

"""QTM RT codec and client packet handling: byte vectors, split streams, rotations, hostile
bytes."""

from __future__ import annotations

import contextlib
import math
import socket
import struct

import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from drivers.mocap import qtm
from drivers.mocap.frames import quat_angle_rad, quat_from_axis_angle, xyzw_to_wxyz
from drivers.mocap.pose import TrackingStatus
from drivers.mocap.qtm import (
    ComponentType,
    DataFrame,
    PacketType,
    QtmDecodeError,
    QtmStreamParser,
    SixDofBody,
    SixDofComponent,
)
from drivers.mocap.qtm_client import QtmClient, QtmConfig

_H = math.sqrt(0.5)
YAW_90_MATRIX = (0.0, 1.0, 0.0, -1.0, 0.0, 0.0, 0.0, 0.0, 1.0)  # column-major Rz(+90 deg)


def test_that_a_command_packet_is_size_type_and_nul_terminated_ascii() -> None:
    wire = qtm.encode_command("Version 1.25")
    assert wire == struct.pack("<II", 8 + 13, 1) + b"Version 1.25\0"
    [p] = QtmStreamParser().feed(wire)
    assert p.kind == PacketType.COMMAND and qtm.decode_text(p.body) == "Version 1.25"


def test_that_an_event_packet_is_one_byte() -> None:
    wire = qtm.encode_event(qtm.Event.CAPTURE_STARTED)
    assert wire == struct.pack("<II", 9, 6) + b"\x03"
    assert qtm.decode_event(wire[8:]) is qtm.Event.CAPTURE_STARTED
    with pytest.raises(QtmDecodeError):
        qtm.decode_event(b"\x63")


def test_that_a_6d_data_packet_has_the_documented_little_endian_layout() -> None:
    body = SixDofBody((1250.0, -500.0, 800.0), YAW_90_MATRIX, None)
    wire = qtm.encode_data_frame(DataFrame(123_456_789, 42, (
        SixDofComponent(ComponentType.C6D, 3, 4, (body,)),)))
    # packet header, then int64 timestamp, uint32 frame, uint32 component count
    assert struct.unpack_from("<IIqII", wire) == (len(wire), 3, 123_456_789, 42, 1)
    # component: uint32 size (incl. its 8-byte header), uint32 type 5, <ihh, 3 + 9 float32
    assert struct.unpack_from("<IIihh", wire, 24) == (8 + 8 + 48, 5, 1, 3, 4)
    assert struct.unpack_from("<12f", wire, 40) == (1250.0, -500.0, 800.0, *YAW_90_MATRIX)
    assert len(wire) == 40 + 48
    frame = qtm.decode_data(qtm.decode_packet(wire).body)
    assert frame.timestamp_us == 123_456_789 and frame.frame_number == 42
    comp = frame.six_dof()
    assert comp is not None and comp.bodies == (body,) and comp.drop_rate_2d == 3


@pytest.mark.parametrize("name", sorted(qtm.SIX_DOF_COMPONENTS))
def test_that_every_6d_variant_round_trips_and_other_components_are_skipped(name: str) -> None:
    kind, matrix, residual = qtm.SIX_DOF_COMPONENTS[name]
    body = SixDofBody((1.0, 2.0, 3.0), YAW_90_MATRIX if matrix else None,
                      None if matrix else (10.0, -20.0, 30.0), 0.5 if residual else math.nan)
    wire = qtm.encode_data_frame(DataFrame(1, 2, (SixDofComponent(kind, 0, 0, (body,)),)))
    # splice an unknown component (type 17, timecode) in front: skipped by its size
    raw = bytearray(wire)
    extra = struct.pack("<II", 12, 17) + b"\0" * 4
    raw[20:24] = struct.pack("<I", 2)  # after size, type, timestamp and frame number
    raw[24:24] = extra
    raw[0:4] = struct.pack("<I", len(raw))
    frame = qtm.decode_data(qtm.decode_packet(bytes(raw)).body)
    assert frame.other_components == (17,)
    assert frame.components[0].kind == kind
    got = frame.components[0].bodies[0]
    assert got.pos_mm == body.pos_mm and got.rot == body.rot and got.euler_deg == body.euler_deg
    assert (got.residual_mm == 0.5) if residual else math.isnan(got.residual_mm)


def test_that_a_stream_split_at_any_offset_yields_the_same_packets() -> None:
    wire = b"".join((qtm.encode_command(qtm.WELCOME), qtm.encode_event(qtm.Event.CONNECTED),
                     qtm.encode_xml("<a/>"), qtm.encode_no_more_data(), qtm.encode_data_frame(
                         DataFrame(5, 6, ()))))
    whole = QtmStreamParser().feed(wire)
    assert [p.kind for p in whole] == [1, 6, 2, 4, 3]
    for cut in range(len(wire) + 1):
        sut = QtmStreamParser()
        assert sut.feed(wire[:cut]) + sut.feed(wire[cut:]) == whole


def test_that_an_impossible_size_raises_the_decode_error() -> None:
    with pytest.raises(QtmDecodeError):
        QtmStreamParser().feed(struct.pack("<II", 4, 1))
    with pytest.raises(QtmDecodeError):
        QtmStreamParser().feed(struct.pack("<II", qtm.MAX_PACKET_BYTES + 1, 3))


def test_that_the_6d_parameters_give_the_body_names_in_index_order() -> None:
    for version in ((1, 19), (1, 25)):
        xml = qtm.encode_6d_parameters(["fasthex", "pad"], version, 100.0)
        assert qtm.decode_6d_body_names(xml) == ("fasthex", "pad")
    with pytest.raises(QtmDecodeError):
        qtm.decode_6d_body_names("<QTM_Parameters_Ver_1.25><The_6D>")
    with pytest.raises(QtmDecodeError):
        qtm.decode_6d_body_names("<QTM_Parameters_Ver_1.25/>")


def test_that_the_column_major_matrix_of_a_yaw_of_90_deg_is_that_rotation() -> None:
    q = qtm.matrix_to_quat(YAW_90_MATRIX)
    assert quat_angle_rad(xyzw_to_wxyz(q), (_H, 0.0, 0.0, _H)) < 1e-12
    # column 0 is the image of the body x axis: +90 deg about z maps x to +y
    assert qtm.quat_to_matrix((0.0, 0.0, _H, _H))[:3] == pytest.approx((0.0, 1.0, 0.0))


@settings(max_examples=200)
@given(axis=st.tuples(*[st.floats(-1.0, 1.0)] * 3).filter(lambda a: sum(c * c for c in a) > 0.01),
       angle=st.floats(-math.pi, math.pi))
@example(axis=(1.0, 2e-06, 1.0), angle=3.1415926535897927)  # 2e-6 rad from gimbal lock
def test_that_matrix_and_euler_forms_round_trip_any_rotation(
        axis: tuple[float, float, float], angle: float) -> None:
    q_wxyz = quat_from_axis_angle(axis, angle)
    q = (q_wxyz[1], q_wxyz[2], q_wxyz[3], q_wxyz[0])
    back = qtm.matrix_to_quat(qtm.quat_to_matrix(q))
    assert quat_angle_rad(xyzw_to_wxyz(back), q_wxyz) < 1e-6
    euler = qtm.quat_to_euler(q)
    assert -90.0 <= euler[1] <= 90.0
    assert quat_angle_rad(xyzw_to_wxyz(qtm.euler_to_quat(euler)), q_wxyz) < 1e-6


def test_that_euler_angles_compose_about_x_then_the_new_y_then_the_new_z() -> None:
    # R = Rx(90) Ry(90): body x -> Rx(Ry x) = Rx(-z) = +y
    r = qtm.quat_to_matrix(qtm.euler_to_quat((90.0, 90.0, 0.0)))
    assert r[:3] == pytest.approx((0.0, 1.0, 0.0), abs=1e-12)


def test_that_the_stream_command_names_rate_udp_port_and_components() -> None:
    assert qtm.parse_stream_command("AllFrames UDP:6734 3DNoLabels 6DEuler") == (
        "allframes", ["3dnolabels", "6deuler"], 6734, None)
    assert qtm.parse_stream_command("Frequency:50 udp:10.0.0.2:9000 6D")[2:] == (9000, "10.0.0.2")
    for bad in ("", "AllFrames UDP:x 6D", "AllFrames UDP:0 6D"):
        with pytest.raises(QtmDecodeError):
            qtm.parse_stream_command(bad)


@settings(max_examples=400)
@given(data=st.binary(max_size=400))
def test_that_random_stream_bytes_only_ever_raise_the_decode_error(data: bytes) -> None:
    try:
        for p in QtmStreamParser().feed(data):
            for fn in (qtm.decode_data, qtm.decode_event):
                with contextlib.suppress(QtmDecodeError):
                    fn(p.body)
            with contextlib.suppress(QtmDecodeError):
                qtm.decode_6d_body_names(qtm.decode_text(p.body))
    except QtmDecodeError:
        pass
    with contextlib.suppress(QtmDecodeError):
        qtm.decode_data(qtm.decode_packet(data).body)
    with contextlib.suppress(QtmDecodeError):
        qtm.parse_stream_command(data.decode("latin-1"))


# ---------------------------------------------------------------------------- client


def _client(body: str = "hex") -> QtmClient:
    sut = QtmClient(QtmConfig(body=body), clock=lambda: 1_000_000_000)
    sut._on_parameters(qtm.encode_6d_parameters(["pad", "hex"]))
    return sut


def _frame(*bodies: SixDofBody, kind: ComponentType = ComponentType.C6D) -> bytes:
    return qtm.encode_data_frame(DataFrame(7_000, 3, (SixDofComponent(kind, 0, 0, bodies),)))


PAD = SixDofBody((0.0, 0.0, 0.0), (1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0), None)


def test_that_a_body_in_z_up_millimetres_becomes_a_world_pose_in_metres() -> None:
    sut = _client()
    assert sut.feed_stream(_frame(PAD, SixDofBody((1250.0, -500.0, 800.0), YAW_90_MATRIX, None)))
    s = sut.latest()
    assert s is not None and s.valid and s.body_name == "hex" and s.body_id == 1
    assert s.pos_w_m == pytest.approx((1.25, -0.5, 0.8), abs=1e-9)
    assert quat_angle_rad(s.q_wb, (_H, 0.0, 0.0, _H)) < 1e-7


def test_that_euler_components_give_the_same_world_pose() -> None:
    sut = _client()
    pad = SixDofBody((0.0, 0.0, 0.0), None, (0.0, 0.0, 0.0))
    sut.feed_stream(_frame(pad, SixDofBody((1250.0, -500.0, 800.0), None, (0.0, 0.0, 90.0)),
                           kind=ComponentType.C6D_EULER))
    s = sut.latest()
    assert s is not None and s.valid and quat_angle_rad(s.q_wb, (_H, 0.0, 0.0, _H)) < 1e-7


def test_that_nan_is_invalid_a_short_frame_is_missing_and_a_non_rotation_is_dropped() -> None:
    sut = _client()
    nan = math.nan
    sut.feed_stream(_frame(PAD, SixDofBody((nan, nan, nan), (nan,) * 9, None)))
    s = sut.latest()
    assert s is not None and s.status is TrackingStatus.INVALID
    sut.feed_stream(_frame(PAD))
    s = sut.latest()
    assert s is not None and s.status is TrackingStatus.MISSING
    sut.feed_stream(_frame(PAD, SixDofBody((1.0, 2.0, 3.0), (2.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0),
                                           None)))
    assert sut.stats().implausible_samples == 1
    assert sut.latest() is s  # the dropped pose is never handed out


def test_that_udp_frames_from_another_host_are_foreign() -> None:
    sut = _client()
    sut._server_ip = "127.0.0.1"
    sut.feed_datagram(_frame(PAD, PAD), ("10.9.8.7", 22223))
    sut.feed_datagram(b"junk", ("127.0.0.1", 22223))
    assert sut.latest() is None
    assert sut.stats().foreign_packets == 1 and sut.stats().malformed_packets == 1


@settings(max_examples=300)
@given(chunks=st.lists(st.binary(max_size=200), max_size=4),
       kind=st.sampled_from(list(PacketType)))
def test_that_random_packets_never_raise_in_the_client(chunks: list[bytes],
                                                       kind: PacketType) -> None:
    sut = _client()
    for chunk in chunks:
        sut.feed_stream(qtm.encode_packet(kind, chunk))
        sut.feed_stream(chunk)
        sut.feed_datagram(chunk, ("127.0.0.1", 1))
    s = sut.latest()
    if s is not None and s.valid:
        assert all(math.isfinite(c) for c in s.pos_w_m + s.q_wb)


# ---------------------------------------------------------------------------- emulator


WORDS = ["StreamFrames", "Stop", "AllFrames", "Frequency:0", "FrequencyDivisor:7", "UDP:1",
         "udp:10.0.0.1:9", "6D", "6DEulerRes", "3D", "GetParameters", "All", "Calibration",
         "Version", "1.99", "0.5", "GetCurrentFrame", "GetState", "QTMVersion",
         "6DÉuler"]  # echoed in the error answer: not ASCII
COMMANDS = st.lists(st.sampled_from(WORDS), max_size=5).map(
    lambda words: qtm.encode_command(" ".join(words)))
PACKETS = st.builds(qtm.encode_packet, st.integers(0, 12), st.binary(max_size=80))


@settings(max_examples=200, deadline=None)
@given(chunks=st.lists(st.one_of(st.binary(max_size=120), PACKETS, COMMANDS), max_size=5))
def test_that_random_client_bytes_never_raise_in_the_emulator(chunks: list[bytes]) -> None:
    from sim_backend.emulators.qtm import QtmServer
    from sim_backend.vehicle import BenchVehicle

    server = QtmServer(BenchVehicle())
    a, b = socket.socketpair()
    with a, b:
        b.setblocking(False)
        conn = server.connection_for(a)
        conn.peer_ip = "127.0.0.1"
        for chunk in chunks:
            if not server.handle_stream(conn, chunk):
                break
            with contextlib.suppress(BlockingIOError):
                while b.recv(65536):  # answers: drained so that sends never block
                    pass
    assert server.counters.input_errors == 0

"""Our NatNet client against the emulated Motive server over real UDP sockets on loopback.

Every NatNet version (3.0, 3.1, 4.0, 4.1) in unicast and in multicast (loopback interface,
TTL 0). Frames are published in lockstep (``publish_due`` with simulated time) so that each
received frame can be matched with the vehicle's true pose at its capture; waits are
event-driven with generous deadlines, nothing depends on wall-clock timing.
"""

from __future__ import annotations

import math
import socket
import threading
from collections.abc import Iterator

import pytest

from drivers.mocap import natnet
from drivers.mocap.frames import FrameTransform, Quat, Vec3, quat_angle_rad, quat_from_axis_angle
from drivers.mocap.natnet_client import NatNetClient, NatNetConfig
from drivers.mocap.pose import MocapConnectError, PoseSample, TrackingStatus, UnknownBodyError
from sim_backend.emulators.natnet import (
    NatNetEmulatorConfig,
    NatNetServer,
    StaticBody,
    free_udp_port,
)
from sim_backend.vehicle import BenchVehicle, PoseReading

WAIT_S = 10.0  # generous: the machine is shared and loaded
POS_TOL_M = 2e-6  # float32 on the wire, |p| < 3 m
ROT_TOL_RAD = 2e-6


class CircleVehicle(BenchVehicle):
    """A bench vehicle whose true pose moves: a 1 m circle at 1.2 m, yawing and rolling."""

    def true_pose(self) -> PoseReading:
        t = self.now_s()
        q = quat_from_axis_angle((0.3, 0.2, 1.0), 0.5 + 2.0 * t)
        return PoseReading(t, (math.cos(t), math.sin(t), 1.2 + 0.1 * t), q)


def _assert_pose(sample: PoseSample, pos: Vec3, q: Quat) -> None:
    assert sample.valid, sample
    assert all(abs(a - b) < POS_TOL_M for a, b in zip(sample.pos_w_m, pos, strict=True))
    assert quat_angle_rad(sample.q_wb, q) < ROT_TOL_RAD


def _pair(version: str, mode: str, **emu: object
          ) -> tuple[NatNetServer, NatNetEmulatorConfig]:
    data_port = free_udp_port()
    cfg = NatNetEmulatorConfig(version=version, mode=mode, command_port=0,  # type: ignore[arg-type]
                               data_port=data_port, **emu)  # type: ignore[arg-type]
    return NatNetServer(CircleVehicle(), cfg, lock=threading.Lock()), cfg


@pytest.fixture
def lockstep() -> Iterator[list[NatNetServer]]:
    started: list[NatNetServer] = []
    yield started
    for s in started:
        s.close()


def _start(server: NatNetServer, cfg: NatNetEmulatorConfig, started: list[NatNetServer],
           **client: object) -> NatNetClient:
    server.start(realtime=False)
    started.append(server)
    ccfg = NatNetConfig(command_port=server.command_port, data_port=cfg.data_port,
                        mode=cfg.mode, body="fasthex", **client)  # type: ignore[arg-type]
    vehicle = server._vehicle
    # arrivals stamped on the simulated clock, as a lockstep flight stamps them: on the host's
    # clock a step that stalls longer than its simulated time makes a frame look late
    return NatNetClient(ccfg, clock=lambda: round(vehicle.now_s() * 1e9))


def _step(server: NatNetServer, client: NatNetClient, vehicle: BenchVehicle, dt_s: float,
          expect_frames: int = 1) -> None:
    before = client.frames_seen
    vehicle.advance(dt_s)
    server.publish_due(vehicle.now_s())
    assert client.wait_for_total(before + expect_frames, WAIT_S)


@pytest.mark.parametrize("mode", ["unicast", "multicast"])
@pytest.mark.parametrize("version", ["3.0", "3.1", "4.0", "4.1"])
def test_that_our_client_reads_the_true_pose_in_every_version_and_mode(
        version: str, mode: str, lockstep: list[NatNetServer]) -> None:
    # Fixture
    server, cfg = _pair(version, mode, rate_hz=200.0, latency_s=0.0035)
    vehicle = server._vehicle
    assert isinstance(vehicle, BenchVehicle)
    truth: dict[int, PoseReading] = {}
    with _start(server, cfg, lockstep) as client:
        assert client.version == natnet.parse_version(version)
        server.publish_due(vehicle.now_s())  # frame 1 captured, sent after the latency
        truth[1] = vehicle.true_pose()
        # Test: one capture per 5 ms step; each frame is sent 3.5 ms after its capture
        for n in range(2, 22):
            _step(server, client, vehicle, 0.005)
            truth[n] = vehicle.true_pose()
            # Assert: the newest frame is the previous capture, with its own true pose
            s = client.latest()
            assert s is not None and s.frame_number == n - 1
            _assert_pose(s, truth[n - 1].pos_w_m, truth[n - 1].q_wb)
            assert s.latency_s == pytest.approx(0.0035, abs=1e-6)
            assert s.t_ns == s.rx_t_ns - 3_500_000
        st = client.stats()
        assert (st.frames_dropped, st.frame_jumps, st.malformed_packets) == (0, 0, 0)
        assert st.frames_received == 20


def test_that_the_realtime_thread_streams_at_least_the_frames_waited_for() -> None:
    vehicle = BenchVehicle(pos_w_m=(0.5, -1.0, 2.0))
    cfg = NatNetEmulatorConfig(command_port=0, rate_hz=360.0,
                               static_bodies=(StaticBody("pad", 7, (1.0, 1.0, 0.0)),))
    with NatNetServer(vehicle, cfg) as server, \
            NatNetClient(NatNetConfig(command_port=server.command_port)) as client:
        assert client.wait_frames(50, WAIT_S)
        s = client.latest()
        assert s is not None and s.body_name == "fasthex"  # first defined body by default
        _assert_pose(s, (0.5, -1.0, 2.0), (1.0, 0.0, 0.0, 0.0))
        pad = client.latest_of("pad")
        assert pad is not None
        _assert_pose(pad, (1.0, 1.0, 0.0), (1.0, 0.0, 0.0, 0.0))
        assert client.bodies() == {"fasthex": 1, "pad": 7}
        assert client.wait_for_rate(WAIT_S) > 0.0  # measured once 0.25 s of frames arrived


def test_that_occluded_frames_are_invalid_samples_and_never_the_stale_pose(
        lockstep: list[NatNetServer]) -> None:
    server, cfg = _pair("4.1", "unicast", rate_hz=100.0, occlusion_probability=0.1,
                        occlusion_frames=3, seed=3)
    vehicle = server._vehicle
    assert isinstance(vehicle, BenchVehicle)
    invalid = 0
    with _start(server, cfg, lockstep) as client:
        for _ in range(120):
            _step(server, client, vehicle, 0.01)
            s = client.latest()
            assert s is not None
            if s.valid:
                truth = vehicle.true_pose()
                _assert_pose(s, truth.pos_w_m, truth.q_wb)
            else:
                invalid += 1
                assert s.status is TrackingStatus.INVALID
                assert all(math.isnan(c) for c in s.pos_w_m + s.q_wb)
        assert invalid == server.counters.occluded_frames > 0
        assert client.stats().invalid_samples == invalid


def test_that_lost_frames_count_as_dropped_and_frame_jumps_do_not(
        lockstep: list[NatNetServer]) -> None:
    server, cfg = _pair("3.1", "unicast", rate_hz=100.0, loss_probability=0.2, seed=5)
    vehicle = server._vehicle
    assert isinstance(vehicle, BenchVehicle)
    expected_dropped = 0
    lost_since_last = 0
    received_any = False
    with _start(server, cfg, lockstep) as client:
        # Test: one frame per step; the emulator's own counter says whether it was lost
        for _ in range(100):
            lost_before = server.counters.frames_lost
            n = client.frames_seen
            vehicle.advance(0.01)
            server.publish_due(vehicle.now_s())
            if server.counters.frames_lost > lost_before:
                lost_since_last += 1
                continue
            assert client.wait_for_total(n + 1, WAIT_S)
            if received_any:  # a gap is only visible between two received frames
                expected_dropped += lost_since_last
            lost_since_last, received_any = 0, True
        # Assert
        st = client.stats()
        assert server.counters.frames_lost > 0
        assert st.frames_dropped == expected_dropped
        assert st.frames_received == server.counters.frames_captured - \
            server.counters.frames_lost
        # Test: a jump of the server's numbering is a discontinuity, not 5000 lost frames
        server.inject_frame_jump(5000)
        while True:  # publish until a frame after the jump is delivered (not lost)
            lost_before, n = server.counters.frames_lost, client.frames_seen
            vehicle.advance(0.01)
            server.publish_due(vehicle.now_s())
            if server.counters.frames_lost == lost_before:
                assert client.wait_for_total(n + 1, WAIT_S)
                break
        assert client.stats().frame_jumps == 1
        assert client.stats().frames_dropped == expected_dropped


def test_that_the_client_can_request_an_older_bitstream_in_unicast(
        lockstep: list[NatNetServer]) -> None:
    server, cfg = _pair("4.1", "unicast", rate_hz=100.0)
    vehicle = server._vehicle
    assert isinstance(vehicle, BenchVehicle)
    with _start(server, cfg, lockstep, version="3.1") as client:
        assert client.version == (3, 1) and server.version == (3, 1)
        _step(server, client, vehicle, 0.01)
        s = client.latest()
        assert s is not None
        truth = vehicle.true_pose()
        _assert_pose(s, truth.pos_w_m, truth.q_wb)


def _server_ignoring_bitstream() -> tuple[NatNetServer, NatNetEmulatorConfig]:
    """A 4.1 server that answers Bitstream,x.y with success and goes on streaming 4.1."""
    return _pair("4.1", "unicast", rate_hz=100.0, honour_bitstream=False)


def test_that_a_requested_version_the_server_does_not_confirm_is_not_used_to_decode(
        lockstep: list[NatNetServer], caplog: pytest.LogCaptureFixture) -> None:
    # Fixture
    server, cfg = _server_ignoring_bitstream()
    vehicle = server._vehicle
    assert isinstance(vehicle, BenchVehicle)
    # Test: 3.1 requested; the server's SERVERINFO still states 4.1
    with _start(server, cfg, lockstep, version="3.1") as client:
        for _ in range(5):
            _step(server, client, vehicle, 0.01)
        s = client.latest()
        stats = client.stats()
        # Assert: the server's version is read, with a warning naming both
        assert client.version == (4, 1) and server.version == (4, 1)
        assert s is not None
        truth = vehicle.true_pose()
        _assert_pose(s, truth.pos_w_m, truth.q_wb)
        assert stats.malformed_packets == 0 and stats.implausible_samples == 0
    assert any("NatNet 3.1 was requested, the server speaks 4.1" in r.getMessage()
               for r in caplog.records)


def test_that_a_required_version_the_server_does_not_confirm_is_a_connect_error(
        lockstep: list[NatNetServer]) -> None:
    server, cfg = _server_ignoring_bitstream()
    client = _start(server, cfg, lockstep, version="3.1", require_version=True)
    with pytest.raises(MocapConnectError) as err:
        client.start()
    assert "NatNet 3.1 was requested, the server speaks 4.1: the server accepted the " \
        "Bitstream command but still states its own version" in str(err.value)


def test_that_a_version_request_in_multicast_is_refused_when_required(
        lockstep: list[NatNetServer]) -> None:
    server, cfg = _pair("4.1", "multicast", rate_hz=100.0)
    client = _start(server, cfg, lockstep, version="3.1", require_version=True)
    with pytest.raises(MocapConnectError, match="only be changed in unicast mode"):
        client.start()


def test_that_frames_from_another_address_are_ignored(lockstep: list[NatNetServer]) -> None:
    server, cfg = _pair("4.1", "unicast", rate_hz=100.0)
    vehicle = server._vehicle
    assert isinstance(vehicle, BenchVehicle)
    with _start(server, cfg, lockstep) as client:
        _step(server, client, vehicle, 0.01)
        good = client.latest()
        target = client.local_address
        assert target is not None
        # A forged frame with a different pose from 127.0.0.2 (another host on loopback)
        forged = natnet.encode_frame(natnet.FrameOfData(999, (natnet.RigidBodyData(
            1, (9.0, 9.0, 9.0), (0.0, 0.0, 0.0, 1.0), 0.0, True),)), (4, 1))
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as intruder:
            intruder.bind(("127.0.0.2", 0))
            intruder.sendto(forged, target)
        _step(server, client, vehicle, 0.01)  # the real frame after it, in order
        s = client.latest()
        assert s is not None and good is not None and s.frame_number == good.frame_number + 1
        assert client.stats().foreign_packets == 1


def test_that_the_emulator_pose_in_mocap_axes_is_y_up() -> None:
    # The stream itself is in Motive axes: what any NatNet client sees.
    vehicle = BenchVehicle(pos_w_m=(1.0, -2.0, 1.5))
    server = NatNetServer(vehicle, NatNetEmulatorConfig(command_port=0))
    frame_rb = server._rigid_body(1, (1.0, -2.0, 1.5), (1.0, 0.0, 0.0, 0.0), True)
    assert frame_rb.pos == pytest.approx((1.0, 1.5, 2.0))
    assert FrameTransform().to_world(frame_rb.pos, frame_rb.q_xyzw)[0] == \
        pytest.approx((1.0, -2.0, 1.5))


def test_that_no_server_is_a_typed_connect_error_naming_the_device() -> None:
    port = free_udp_port()
    with pytest.raises(MocapConnectError, match=f"natnet://127.0.0.1:{port}"):
        NatNetClient(NatNetConfig(command_port=port, connect_timeout_s=0.5)).start()


def test_that_an_unknown_body_name_lists_the_defined_ones(lockstep: list[NatNetServer]) -> None:
    server, _cfg = _pair("4.1", "unicast")
    server.start(realtime=False)
    lockstep.append(server)
    with pytest.raises(UnknownBodyError, match="fasthex"):
        NatNetClient(NatNetConfig(command_port=server.command_port, body="nope")).start()


def test_that_a_silent_unicast_client_is_dropped_after_the_keepalive_timeout() -> None:
    # Fixture: the emulator's wall clock is injected; the "client" is a raw UDP socket.
    now = [100.0]
    vehicle = BenchVehicle()
    server = NatNetServer(vehicle, NatNetEmulatorConfig(command_port=0, client_timeout_s=10.0),
                          wall_clock=lambda: now[0])
    server.start(realtime=False)
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as raw:
            raw.bind(("127.0.0.1", 0))
            raw.settimeout(WAIT_S)
            raw.sendto(natnet.encode_connect("empty"), ("127.0.0.1", server.command_port))
            info = natnet.decode_message(raw.recv(4096), None)  # CONNECT is answered first
            assert isinstance(info, natnet.ServerInfo) and info.version == (4, 1)
            server.publish_due(0.0)
            frame = natnet.decode_message(raw.recv(4096), info.version)
            assert isinstance(frame, natnet.FrameOfData) and frame.frame_number == 1
            assert server.unicast_clients == [raw.getsockname()]
            # Test: 10.5 s without KEEPALIVE
            now[0] += 10.5
            server.publish_due(0.01)
            # Assert
            assert server.unicast_clients == []
    finally:
        server.close()


def _polled_pair(started: list[NatNetServer]
                 ) -> tuple[NatNetServer, NatNetClient, BenchVehicle]:
    """A lockstep server and a started client with no receive thread (its owner polls)."""
    server, cfg = _pair("4.1", "unicast")
    client = _start(server, cfg, started)
    client.start(receive_thread=False)
    vehicle = server._vehicle
    assert isinstance(vehicle, BenchVehicle)
    return server, client, vehicle


def test_that_a_polled_client_sees_exactly_the_frames_sent_before_the_poll(
        lockstep: list[NatNetServer]) -> None:
    # Fixture: no receive thread; the owner polls, as the lockstep flight loop does.
    server, client, vehicle = _polled_pair(lockstep)
    try:
        seen = []
        for _ in range(5):
            # Test: a frame is sent, then polled at once: loopback delivery is synchronous
            vehicle.advance(0.01)
            assert server.publish_due(vehicle.now_s()) == 1
            assert client.poll() == 1
            sample = client.latest()
            assert sample is not None
            seen.append(sample.frame_number)
            pose = vehicle.true_pose()
            _assert_pose(sample, pose.pos_w_m, pose.q_wb)
        # Assert: nothing else is waiting; frames consecutive
        assert client.poll() == 0
        assert seen == list(range(seen[0], seen[0] + 5))
    finally:
        client.close()


def test_that_a_received_frame_keeps_its_arrival_time_until_it_is_handled(
        lockstep: list[NatNetServer]) -> None:
    # Fixture: a lockstep loop takes the datagrams as its IMU sample arrives (receive) and
    # decodes them after its motor command (handle_received), while its clock has moved on
    server, client, vehicle = _polled_pair(lockstep)
    try:
        vehicle.advance(0.01)
        assert server.publish_due(vehicle.now_s()) == 1
        arrival_ns = round(vehicle.now_s() * 1e9)
        pose = vehicle.true_pose()
        # Test: taken off the socket now, handled 3 ms of the client's clock later
        assert client.receive() == 1
        assert client.latest() is None          # nothing decoded yet
        vehicle.advance(0.003)
        assert client.handle_received() == 1
        # Assert: the sample is the frame's, stamped with the time it was taken
        sample = client.latest()
        assert sample is not None and sample.rx_t_ns == arrival_ns
        assert sample.t_ns <= arrival_ns
        _assert_pose(sample, pose.pos_w_m, pose.q_wb)
        assert client.handle_received() == 0 and client.receive() == 0
    finally:
        client.close()

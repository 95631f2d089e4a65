"""Our VRPN client, and the compiled VRPN 07.38 client inside PyPI ``motioncapture``, against
the emulated VRPN tracker server over real TCP/UDP sockets on loopback.

Our client connects over TCP directly; the mainline VRPN client in ``motioncapture`` lobs a UDP
connection request and the emulator connects back over TCP, so both paths are exercised."""

from __future__ import annotations

import math
import threading
from typing import Any

import pytest

from drivers.mocap.frames import quat_angle_rad, quat_from_axis_angle
from drivers.mocap.pose import MocapConnectError, TrackingStatus
from drivers.mocap.vrpn_client import VrpnClient, VrpnConfig
from sim_backend.emulators.vrpn import VrpnEmulatorConfig, VrpnServer
from sim_backend.vehicle import BenchVehicle, PoseReading

WAIT_S = 10.0
Q = quat_from_axis_angle((0.2, -0.4, 1.0), 1.1)


class PosedVehicle(BenchVehicle):
    def true_pose(self) -> PoseReading:
        return PoseReading(self.now_s(), (1.25, -0.5, 0.8), Q)


class ManualClock:
    def __init__(self) -> None:
        self.t_ns = 0
        self.lock = threading.Lock()

    def __call__(self) -> int:
        with self.lock:
            return self.t_ns


def test_that_our_client_reads_the_true_pose_from_the_vrpn_emulator() -> None:
    with VrpnServer(PosedVehicle(), VrpnEmulatorConfig(port=0, rate_hz=200.0)) as server, \
            VrpnClient(VrpnConfig(port=server.port, latency_s=0.002)) as client:
        assert client.wait_frames(20, WAIT_S)
        s = client.latest()
        assert s is not None and s.valid and s.body_name == "Tracker0"
        assert s.pos_w_m == pytest.approx((1.25, -0.5, 0.8), abs=1e-12)  # f64 on the wire
        assert quat_angle_rad(s.q_wb, Q) < 1e-9
        # the configured 2 ms plus this packet's delay above the earliest one (clock sync)
        assert s.rx_t_ns - 2_000_000 - 5_000_000 < s.t_ns <= s.rx_t_ns - 2_000_000
        assert client.trackers() == ["Tracker0"]
        assert client.stats().malformed_packets == 0


def test_that_a_silent_tracker_is_reported_missing_after_the_staleness_limit() -> None:
    clock = ManualClock()
    server = VrpnServer(PosedVehicle(), VrpnEmulatorConfig(port=0))
    server.start()
    client = VrpnClient(VrpnConfig(port=server.port, stale_after_s=0.05), clock=clock)
    client.start()
    try:
        assert client.wait_frames(3, WAIT_S)
    finally:
        server.close()
        client.close()  # joins the receive thread: no report can arrive after this
    fresh = client.latest()
    assert fresh is not None and fresh.valid
    # Test: 60 ms on the ground-station clock without a report
    with clock.lock:
        clock.t_ns += 60_000_000
    s = client.latest()
    # Assert
    assert s is not None and s.status is TrackingStatus.MISSING
    assert all(math.isnan(c) for c in s.pos_w_m + s.q_wb)
    assert client.stats().age_s == pytest.approx(0.06)


def test_that_occlusion_dropouts_stop_reports_and_are_counted_by_the_emulator() -> None:
    cfg = VrpnEmulatorConfig(port=0, rate_hz=200.0, occlusion_probability=0.2,
                             occlusion_frames=5, seed=2)
    with VrpnServer(PosedVehicle(), cfg) as server, \
            VrpnClient(VrpnConfig(port=server.port)) as client:
        assert client.wait_frames(40, WAIT_S)
        assert server.occluded_reports > 0
        s = client.latest()
        assert s is not None and (not s.valid or s.pos_w_m == pytest.approx((1.25, -0.5, 0.8)))


def test_that_no_vrpn_server_is_a_typed_connect_error_naming_the_device() -> None:
    with VrpnServer(PosedVehicle(), VrpnEmulatorConfig(port=0)) as server:
        port = server.port
    with pytest.raises(MocapConnectError, match=f"vrpn://Tracker0@127.0.0.1:{port}"):
        VrpnClient(VrpnConfig(port=port, connect_timeout_s=0.5)).start()


def test_that_the_motioncapture_vrpn_client_reads_our_tracker_server() -> None:
    import motioncapture as mc_mod  # the test extra installs it: missing is a failure
    result: dict[str, Any] = {}

    def read(port: int) -> None:
        mc = mc_mod.connect("vrpn", {"hostname": f"127.0.0.1:{port}"})
        for _ in range(200):
            mc.waitForNextFrame()
            bodies = mc.rigidBodies
            if "Tracker0" in bodies:
                rb = bodies["Tracker0"]
                r = rb.rotation
                result["pose"] = (tuple(float(c) for c in rb.position),
                                  (float(r.w), float(r.x), float(r.y), float(r.z)))
                return

    with VrpnServer(PosedVehicle(), VrpnEmulatorConfig(port=0, rate_hz=200.0)) as server:
        # The peer blocks in C++ while waiting: run it in a daemon thread with a deadline.
        t = threading.Thread(target=read, args=(server.port,), daemon=True)
        t.start()
        t.join(WAIT_S)
        assert "pose" in result, "motioncapture received no report within the deadline"
    pos, q = result["pose"]
    assert pos == pytest.approx((1.25, -0.5, 0.8), abs=1e-6)
    assert quat_angle_rad(q, Q) < 1e-6

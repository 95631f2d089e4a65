"""The libmotioncapture adapter (``motioncapture://``) against the emulated VRPN tracker server,
over real sockets on loopback: the library's compiled VRPN client does the protocol, the
adapter its thread, frame conversion and health.

NatNet is not used here: libmotioncapture's OptiTrack backend joins the multicast group on the
default-route interface, and tests send multicast on loopback only (see
``test_mocap_natnet_peer.py``). The adapter over the emulated QTM server is in
``test_mocap_qtm.py``, on one worker with the library's other use of its fixed UDP port 6734."""

from __future__ import annotations

import math

import pytest

from drivers.mocap.frames import FrameConfig, quat_angle_rad, quat_from_axis_angle
from drivers.mocap.motioncapture_client import MotionCaptureClient
from drivers.mocap.pose import MocapConnectError, PoseSource, UnknownBodyError
from drivers.mocap.uri import open_pose_source
from sim_backend.emulators.vrpn import VrpnEmulatorConfig, VrpnServer
from sim_backend.vehicle import BenchVehicle, PoseReading

WAIT_S = 10.0
TOL_M = 1e-6  # libmotioncapture hands positions over as float32
Q = quat_from_axis_angle((0.2, -0.4, 1.0), 1.1)


class PosedVehicle(BenchVehicle):
    def true_pose(self) -> PoseReading:
        return PoseReading(self.now_s(), (1.25, -0.5, 0.8), Q)


@pytest.mark.parametrize("up", ["z", "y"])
def test_that_the_adapter_reads_the_true_world_pose_through_the_library_vrpn_client(
        up: str) -> None:
    # Fixture: the server streams in its own axes (Vicon Tracker Z-up, or Motive Y-up)
    cfg = VrpnEmulatorConfig(port=0, rate_hz=200.0, frames=FrameConfig(up_axis=up),  # type: ignore[arg-type]
                             tracker_name="fasthex")
    with VrpnServer(PosedVehicle(), cfg) as server:
        uri = f"motioncapture://vrpn?host=127.0.0.1:{server.port}&body=fasthex&up={up}"
        dev = open_pose_source(uri)
        assert isinstance(dev, MotionCaptureClient) and isinstance(dev, PoseSource)
        # Test
        with dev:
            assert dev.wait_frames(10, WAIT_S)
            s = dev.latest()
            stats = dev.stats()
        # Assert: the ground-station world frame whatever the server's axes
        assert server.callbacks >= 1  # the library came in by the classic handshake
    assert s is not None and s.valid and s.body_name == "fasthex"
    assert s.pos_w_m == pytest.approx((1.25, -0.5, 0.8), abs=TOL_M)
    assert quat_angle_rad(s.q_wb, Q) < 1e-6
    assert stats.frames_received >= 10 and stats.implausible_samples == 0
    assert dev.bodies() == {"fasthex": 0}


def test_that_an_unknown_body_is_an_error_listing_the_bodies_the_server_sends() -> None:
    with VrpnServer(PosedVehicle(), VrpnEmulatorConfig(port=0, rate_hz=200.0)) as server:
        dev = open_pose_source(f"motioncapture://vrpn?host=127.0.0.1:{server.port}&body=hex",
                               connect_timeout_s=2.0)
        with pytest.raises(UnknownBodyError) as err:
            dev.start()
    assert "no rigid body named 'hex'" in str(err.value)
    assert "the server sends Tracker0" in str(err.value)


def test_that_no_server_is_a_connect_error_naming_the_device() -> None:
    with VrpnServer(PosedVehicle(), VrpnEmulatorConfig(port=0)) as server:
        port = server.port
    dev = open_pose_source(f"motioncapture://vrpn?host=127.0.0.1:{port}&body=hex",
                           connect_timeout_s=2.0)
    with pytest.raises(MocapConnectError, match=f"motioncapture://vrpn\\?host=127.0.0.1:{port}"):
        dev.start()
    assert not math.isfinite(dev.stats().age_s)


def test_that_mocap_list_and_watch_take_a_motioncapture_uri(
        capsys: pytest.CaptureFixture[str]) -> None:
    from groundstation.cli import main

    cfg = VrpnEmulatorConfig(port=0, rate_hz=200.0, tracker_name="fasthex")
    with VrpnServer(BenchVehicle(pos_w_m=(0.25, 0.5, 1.0)), cfg) as server:
        uri = f"motioncapture://vrpn?host=127.0.0.1:{server.port}&body=fasthex"
        assert main(["mocap", "list", uri]) == 0
        listed = capsys.readouterr().out
        assert main(["mocap", "watch", uri, "--frames", "5", "--interval", "0.05"]) == 0
        watched = capsys.readouterr().out
    assert "fasthex  (" in listed and "Hz on the configured body" in listed
    assert "fasthex: p [ +0.250  +0.500  +1.000] m" in watched.strip().splitlines()[-1]

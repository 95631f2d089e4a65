"""An independently written NatNet client (PyPI ``natnet``) reads our emulated Motive server.

This shows the emulator speaks the real protocol, not a private dialect shared with our own
client: the peer does its own handshake (CONNECT "Ping", SERVERINFO, MODELDEF) and frame
parsing, over real UDP sockets, unicast and multicast (loopback, TTL 0), every version.

``motioncapture`` (libmotioncapture) is not used for NatNet: its OptiTrack backend joins the
multicast group on INADDR_ANY, i.e. on the default-route interface, and our tests never send
multicast there (only on loopback). It is used as the VRPN peer instead.
"""

from __future__ import annotations

import math
import threading
from functools import partial
from typing import Any

import natnet as peer  # the test extra installs it: missing is a failure
import pytest

from drivers.mocap.frames import FrameTransform, quat_angle_rad, quat_from_axis_angle
from sim_backend.emulators.natnet import NatNetEmulatorConfig, NatNetServer, free_udp_port
from sim_backend.vehicle import BenchVehicle, PoseReading

WAIT_S = 10.0


def _has(items: list[Any], n: int) -> bool:
    return len(items) >= n


class TiltedVehicle(BenchVehicle):
    def true_pose(self) -> PoseReading:
        t = self.now_s()
        return PoseReading(t, (0.3 + t, -1.2, 1.1), quat_from_axis_angle((1.0, -0.5, 2.0),
                                                                         0.7 + t))


@pytest.mark.parametrize("mode", ["unicast", "multicast"])
@pytest.mark.parametrize("version", ["3.0", "3.1", "4.0", "4.1"])
def test_that_the_pypi_natnet_client_parses_our_stream_with_the_same_poses(
        version: str, mode: str) -> None:
    # Fixture
    data_port = free_udp_port()
    cfg = NatNetEmulatorConfig(version=version, mode=mode,  # type: ignore[arg-type]
                               command_port=0, data_port=data_port, rate_hz=100.0)
    vehicle = TiltedVehicle()
    received: list[Any] = []
    descriptions: list[Any] = []
    got_frames = threading.Condition()

    def on_frame(frame: Any) -> None:
        with got_frames:
            received.append(frame)
            got_frames.notify_all()

    server = NatNetServer(vehicle, cfg)
    server.start(realtime=False)  # lockstep: the test decides when frames are captured
    try:
        client = peer.NatNetClient(server_ip_address="127.0.0.1", local_ip_address="127.0.0.1",
                                   command_port=server.command_port, data_port=data_port,
                                   use_multicast=(mode == "multicast"))
        client.on_data_frame_received_event.handlers.append(on_frame)
        client.on_data_description_received_event.handlers.append(descriptions.append)
        client.connect(timeout=WAIT_S)
        try:
            assert str(client.protocol_version).startswith(version)
            client.request_modeldef()
            client.run_async()
            truth: dict[int, PoseReading] = {}
            # Test
            for n in range(1, 11):
                vehicle.advance(0.01)
                truth[n] = vehicle.true_pose()
                server.publish_due(vehicle.now_s())
                with got_frames:
                    assert got_frames.wait_for(partial(_has, received, n), WAIT_S)
        finally:
            client.shutdown()
    finally:
        server.close()
    # Assert: the peer's raw MoCap-frame poses are the emulator's truth in Motive axes
    transform = FrameTransform(cfg.frames)
    for frame in received:
        n = frame.prefix.frame_number
        [rb] = frame.rigid_bodies
        assert rb.id_num == cfg.body_id and rb.tracking_valid
        pos_w, q_wb = transform.to_world(tuple(rb.pos), tuple(rb.rot))
        assert all(abs(a - b) < 2e-6 for a, b in zip(pos_w, truth[n].pos_w_m, strict=True))
        assert quat_angle_rad(q_wb, truth[n].q_wb) < 2e-6
        assert frame.suffix.timestamp == pytest.approx(truth[n].t_s)
    assert [f.prefix.frame_number for f in received] == list(range(1, 11))
    assert any(d.rigid_bodies and d.rigid_bodies[0].name == cfg.body_name for d in descriptions)
    assert not math.isnan(received[-1].suffix.timestamp)

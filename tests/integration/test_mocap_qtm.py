"""Our QTM RT client, Qualisys' own ``qtm-rt`` SDK and the C++ RT SDK inside PyPI
``motioncapture`` (libmotioncapture's ``qualisys`` backend) against the emulated QTM server over
real TCP/UDP sockets on loopback.

The two peers show the emulator speaks the real protocol, not a private dialect shared with our
client: ``qtm-rt`` negotiates RT protocol 1.25 and reads the 6D and 6D Euler components;
libmotioncapture negotiates 1.19, asks ``GetState``, ``GetParameters 6D`` (the pre-1.21 XML
layout) and streams ``6DEuler`` over UDP to its own port. Our ``motioncapture://qualisys``
adapter reads the server through that library too.
"""

from __future__ import annotations

import asyncio
import json
import math
import random
import socket
import subprocess
import sys
import threading
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import qtm_rt  # the test extra installs it: missing is a failure
from flight_support import short_session

from drivers.mocap import qtm
from drivers.mocap.frames import Quat, quat_angle_rad, quat_from_axis_angle, xyzw_to_wxyz
from drivers.mocap.motioncapture_client import MotionCaptureClient
from drivers.mocap.pose import MocapConnectError, TrackingStatus, UnknownBodyError
from drivers.mocap.qtm_client import QtmClient, QtmConfig
from drivers.mocap.uri import open_pose_source
from groundstation.cli import main
from groundstation.flight import FlightState
from groundstation.record import read_record
from groundstation.session import FlightSession
from groundstation.session_config import EmulatedBackend
from sim_backend.emulators.qtm import QtmEmulatorConfig, QtmServer, QtmStaticBody
from sim_backend.vehicle import BenchVehicle, PoseReading

WAIT_S = 10.0
POS_W_M = (1.25, -0.5, 0.8)
Q_TILTED = quat_from_axis_angle((0.2, -0.4, 1.0), 1.1)
_H = math.sqrt(0.5)
Q_YAW_90: Quat = (_H, 0.0, 0.0, _H)
PAD = QtmStaticBody("pad", (3.0, 0.5, 0.0))


class PosedVehicle(BenchVehicle):
    def __init__(self, q_wb: Quat = Q_TILTED) -> None:
        super().__init__()
        self.q_wb = q_wb

    def true_pose(self) -> PoseReading:
        return PoseReading(self.now_s(), POS_W_M, self.q_wb)


def _server(q_wb: Quat = Q_TILTED, **kw: Any) -> QtmServer:
    return QtmServer(PosedVehicle(q_wb), QtmEmulatorConfig(port=0, rate_hz=200.0,
                                                           static_bodies=(PAD,), **kw))


@pytest.mark.parametrize("component", ["6d", "6dres", "6deuler", "6deulerres"])
@pytest.mark.parametrize("udp", [False, True])
def test_that_our_client_reads_the_world_pose_in_metres_from_the_qtm_emulator(
        udp: bool, component: str) -> None:
    # Fixture
    with _server() as server, QtmClient(QtmConfig(port=server.port, body="fasthex", udp=udp,
                                                  component=component)) as client:
        # Test
        assert client.wait_frames(20, WAIT_S)
        s = client.latest()
        udp_address = client.udp_address
        pad = QtmClient(QtmConfig(port=server.port, body="pad"))
        with pad:
            assert pad.wait_frames(5, WAIT_S)
            p = pad.latest()
    # Assert
    assert s is not None and s.valid and s.body_name == "fasthex" and s.body_id == 0
    assert s.pos_w_m == pytest.approx(POS_W_M, abs=1e-6)  # float32 millimetres on the wire
    assert quat_angle_rad(s.q_wb, Q_TILTED) < 1e-5
    assert (s.mean_error_m == pytest.approx(0.0004)) if component.endswith("res") \
        else math.isnan(s.mean_error_m)
    assert s.t_ns <= s.rx_t_ns and 0.0 <= s.latency_s < 0.5
    assert client.bodies() == ["fasthex", "pad"]
    assert client.stats().malformed_packets == 0 and client.stats().foreign_packets == 0
    assert (udp_address is not None) == udp
    assert p is not None and p.valid and p.body_id == 1
    assert p.pos_w_m == pytest.approx(PAD.pos_w_m, abs=1e-6)


def test_that_a_frequency_option_decimates_the_stream_and_frames_are_numbered() -> None:
    with _server() as server, QtmClient(QtmConfig(port=server.port, frequency_hz=50.0)) as c:
        assert c.wait_frames(5, WAIT_S)
        st = c.stats()
    # every 4th frame of 200 Hz: the numbers step by 4, and none is counted as dropped
    # (QTM numbers the captures, the divisor skips them deliberately)
    assert st.frames_dropped == 3 * (st.frames_received - 1)


def test_that_an_occluded_body_arrives_invalid_not_as_a_stale_pose() -> None:
    with _server() as server, QtmClient(QtmConfig(port=server.port)) as client:
        assert client.wait_frames(3, WAIT_S)
        server.occlude(1000)
        seen = client.frames_seen
        assert client.wait_for_total(seen + 5, WAIT_S)
        s = client.latest()
    assert s is not None and s.status is TrackingStatus.INVALID
    assert all(math.isnan(c) for c in s.pos_w_m + s.q_wb)


def test_that_an_unknown_body_is_a_typed_error_listing_the_defined_bodies() -> None:
    with _server() as server, pytest.raises(UnknownBodyError, match=r"'nope'.*fasthex.*pad"):
        QtmClient(QtmConfig(port=server.port, body="nope", connect_timeout_s=1.0)).start()


def test_that_a_server_that_never_answers_is_a_connect_error_after_the_timeout() -> None:
    # Fixture: greets like QTM, then says nothing more
    with socket.socket() as listener:
        listener.bind(("127.0.0.1", 0))
        listener.listen(1)

        def greet() -> None:
            conn, _ = listener.accept()
            with conn:
                conn.sendall(qtm.encode_command(qtm.WELCOME))
                conn.recv(1024)  # the Version command; no answer
                conn.recv(1024)  # until the client gives up and closes

        t = threading.Thread(target=greet, daemon=True)
        t.start()
        port = listener.getsockname()[1]
        # Test / Assert
        with pytest.raises(MocapConnectError, match=rf"qtm://127.0.0.1:{port}.*no answer to "
                           r"Version within 0.5 s"):
            QtmClient(QtmConfig(port=port, connect_timeout_s=0.5)).start()
        t.join(WAIT_S)


def test_that_no_qtm_server_is_a_typed_connect_error_naming_the_device() -> None:
    with _server() as server:
        port = server.port
    with pytest.raises(MocapConnectError, match=f"qtm://127.0.0.1:{port}"):
        QtmClient(QtmConfig(port=port, connect_timeout_s=0.5)).start()


def _sdk_frames(port: int, components: list[str]) -> tuple[Any, list[Any], str]:
    """State event, a few data packets and the 6D parameters, read with Qualisys' SDK."""

    async def run() -> tuple[Any, list[Any], str]:
        conn = await qtm_rt.connect("127.0.0.1", port=port, version="1.25", timeout=WAIT_S)
        assert conn is not None, "qtm-rt could not connect"
        try:
            state = await conn.get_state()
            xml = (await conn.get_parameters(["6d"])).decode()
            packets: list[Any] = []
            done = asyncio.get_running_loop().create_future()

            def on_packet(packet: Any) -> None:
                packets.append(packet)
                if len(packets) >= 5 and not done.done():
                    done.set_result(None)

            assert await conn.stream_frames(components=components, on_packet=on_packet) == b"Ok"
            await asyncio.wait_for(done, WAIT_S)
            await conn.stream_frames_stop()
            return state, packets, xml
        finally:
            conn.disconnect()

    return asyncio.run(run())


def test_that_the_qtm_rt_sdk_reads_a_known_pose_in_z_up_millimetres() -> None:
    # Fixture: the vehicle at POS_W_M, yawed +90 deg
    with _server(Q_YAW_90) as server:
        # Test
        state, packets, xml = _sdk_frames(server.port, ["6d", "6deuler"])
    # Assert
    assert state == qtm_rt.QRTEvent.EventCaptureStarted
    assert "<Name>fasthex</Name>" in xml and "<Name>pad</Name>" in xml
    last = packets[-1]
    # consecutive frames, nothing lost (a sixth may arrive before the stop, on a loaded host)
    assert len(packets) >= 5
    assert [p.framenumber for p in packets] == list(range(packets[0].framenumber,
                                                          packets[0].framenumber + len(packets)))
    info, bodies = last.get_6d()
    assert info.body_count == 2
    pos, rot = bodies[0]
    assert (pos.x, pos.y, pos.z) == pytest.approx((1250.0, -500.0, 800.0), abs=1e-3)
    # column-major: column 0 = body x in QTM axes = +y after a +90 deg yaw
    assert rot.matrix == pytest.approx((0.0, 1.0, 0.0, -1.0, 0.0, 0.0, 0.0, 0.0, 1.0), abs=1e-6)
    _, euler_bodies = last.get_6d_euler()
    e_pos, euler = euler_bodies[0]
    assert (e_pos.x, e_pos.y, e_pos.z) == (pos.x, pos.y, pos.z)
    assert (euler.a1, euler.a2, euler.a3) == pytest.approx((0.0, 0.0, 90.0), abs=1e-4)
    pad_pos, _ = bodies[1]
    assert (pad_pos.x, pad_pos.y, pad_pos.z) == pytest.approx((3000.0, 500.0, 0.0), abs=1e-3)


def test_that_the_qtm_rt_sdk_reads_a_tilted_pose_as_the_same_rotation() -> None:
    with _server(Q_TILTED) as server:
        _, packets, _ = _sdk_frames(server.port, ["6dres"])
    _, bodies = packets[-1].get_6d_residual()
    pos, rot, res = bodies[0]
    q = xyzw_to_wxyz(qtm.matrix_to_quat(tuple(rot.matrix)))
    assert (pos.x, pos.y, pos.z) == pytest.approx((1250.0, -500.0, 800.0), abs=1e-3)
    assert quat_angle_rad(q, Q_TILTED) < 1e-5
    assert res.residual == pytest.approx(0.4)


PEER = """
import json, sys, motioncapture
mc = motioncapture.connect("qualisys", {"hostname": "127.0.0.1", "port": sys.argv[1]})
for _ in range(5):
    mc.waitForNextFrame()
out = {}
for name, rb in mc.rigidBodies.items():
    r = rb.rotation
    out[name] = [[float(c) for c in rb.position], [float(r.w), float(r.x), float(r.y), float(r.z)]]
print(json.dumps(out))
"""


def test_that_the_motioncapture_qualisys_backend_reads_our_qtm_server() -> None:
    # libmotioncapture takes the base port and connects to base + 1 (the little-endian port);
    # it streams 6DEuler over UDP to its own fixed port 6734. It runs in a child process: its
    # C++ calls block while holding the GIL, which would stall the emulator's threads.
    with _server(Q_TILTED) as server:
        proc = subprocess.run([sys.executable, "-c", PEER, str(server.port - 1)],
                              capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr[-2000:]
    bodies = json.loads(proc.stdout.strip().splitlines()[-1])
    assert sorted(bodies) == ["fasthex", "pad"]
    pos, q = bodies["fasthex"]
    assert pos == pytest.approx(POS_W_M, abs=1e-6)
    assert quat_angle_rad(tuple(q), Q_TILTED) < 1e-5
    assert bodies["pad"][0] == pytest.approx(PAD.pos_w_m, abs=1e-6)


def test_that_the_motioncapture_adapter_reads_the_world_pose_from_our_qtm_server() -> None:
    # Fixture: the server in this process; the library runs in the adapter's child process,
    # so its connect, which holds its own process's GIL, leaves the server's threads running.
    # The URI names the RT port itself, as qtm:// does; the adapter hands the library the
    # base port below it.
    with _server(Q_TILTED) as server:
        uri = f"motioncapture://qualisys?host=127.0.0.1:{server.port}&body=fasthex"
        dev = open_pose_source(uri)
        assert isinstance(dev, MotionCaptureClient)
        # Test
        with dev:
            assert dev.wait_frames(10, WAIT_S)
            s = dev.latest()
            stats = dev.stats()
            bodies = dev.bodies()
    # Assert: metres and the Z-up world frame, as the vehicle's true pose
    assert s is not None and s.valid and s.body_name == "fasthex"
    assert s.pos_w_m == pytest.approx(POS_W_M, abs=1e-6)  # float32 mm on the wire
    assert quat_angle_rad(s.q_wb, Q_TILTED) < 1e-5  # via 6D Euler angles in float32
    assert stats.frames_received >= 10 and stats.implausible_samples == 0
    assert bodies == {"fasthex": 0, "pad": 0}


def test_that_the_emulator_serves_clients_after_garbage_commands_and_streams() -> None:
    # Fixture
    rng = random.Random(22)
    with _server() as server:
        for i in range(30):
            with socket.create_connection(("127.0.0.1", server.port), timeout=WAIT_S) as bad:
                words = ["StreamFrames", "GetParameters", "Version", "GetCurrentFrame",
                         "UDP:1", "6D", "Frequency:0", "FrequencyDivisor:-3", "1.99", "\xff"]
                text = " ".join(rng.choice(words) for _ in range(rng.randrange(0, 5)))
                junk = rng.randbytes(rng.randrange(0, 40))
                # Test: a command of random words, a packet of random type and bytes, then
                # (every third connection) a size no packet can have
                bad.sendall(qtm.encode_packet(1, text.encode("utf-8", "replace"))
                            + qtm.encode_packet(rng.randrange(0, 12), junk)
                            + (b"\x03\0\0\0\x01\0\0\0" if i % 3 == 0 else b""))
                if i % 3 == 0:
                    bad.settimeout(WAIT_S)
                    while bad.recv(4096):  # answers, then the end of the stream
                        pass
        with QtmClient(QtmConfig(port=server.port, body="fasthex")) as client:
            assert client.wait_frames(20, WAIT_S)
            s = client.latest()
        counters = server.counters
    # Assert
    assert s is not None and s.valid and s.pos_w_m == pytest.approx(POS_W_M, abs=1e-6)
    assert counters.dropped_clients == 10 and counters.refused_commands > 0
    assert counters.input_errors == 0


def test_that_fasthex_mocap_watch_and_list_read_a_qtm_server(
        capsys: pytest.CaptureFixture[str]) -> None:
    with _server(Q_YAW_90) as server:
        rc_list = main(["mocap", "list", f"qtm://127.0.0.1:{server.port}"])
        rc_watch = main(["mocap", "watch", f"qtm://127.0.0.1:{server.port}", "--body", "pad",
                         "--frames", "10", "--interval", "0.05"])
        rc_bad = main(["mocap", "watch", f"qtm://127.0.0.1:{server.port}?body=nope"])
    out, err = capsys.readouterr()
    assert (rc_list, rc_watch, rc_bad) == (0, 0, 2)
    assert "   0  fasthex" in out and "   1  pad" in out
    assert "pad: p [ +3.000  +0.500  +0.000] m" in out
    assert "no 6DOF body named 'nope'" in err and "Traceback" not in err


def test_that_a_short_lockstep_flight_is_flown_on_the_emulated_qtm_server(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # Fixture: the short emulated session, with the QTM server instead of Motive
    cfg, params, mission = short_session(tmp_path)
    assert isinstance(cfg.backend, EmulatedBackend) and cfg.backend.mocap == "natnet"
    cfg = replace(cfg, backend=replace(cfg.backend, mocap="qtm"))
    started: list[tuple[str, bool]] = []
    start = QtmClient.start

    def spy(self: QtmClient, receive_thread: bool = True) -> None:
        started.append((self.config.body, receive_thread))
        start(self, receive_thread)

    monkeypatch.setattr(QtmClient, "start", spy)
    # Test
    out = FlightSession(cfg, params, mission, record_path=tmp_path / "qtm.fhr",
                        echo_events=False, dashboard="off").run()
    # Assert
    assert started == [("fasthex", False)]  # lockstep: the loop polls the QTM client itself
    assert [t.to_state for t in out.result.transitions] == [
        FlightState.ARMED, FlightState.TAKEOFF, FlightState.MISSION, FlightState.LANDING,
        FlightState.DISARMED]
    assert out.result.faults == []
    rows = read_record(out.record_path).rows
    measured = rows[rows["measured"] > 0]
    est_err_mm = 1e3 * np.linalg.norm(measured["est_pos_w_m"] - measured["pos_w_m"], axis=1)
    assert est_err_mm.mean() < 3.0  # as on NatNet: the UKF fused the QTM poses


@pytest.mark.parametrize("udp", [False, True])
def test_that_a_received_qtm_frame_keeps_its_arrival_time_until_it_is_handled(
        udp: bool) -> None:
    # Fixture: a lockstep server and a client with no receive thread, on the simulated clock
    vehicle = PosedVehicle(Q_TILTED)
    server = QtmServer(vehicle, QtmEmulatorConfig(port=0, rate_hz=200.0))
    server.start(realtime=False)
    client = QtmClient(QtmConfig(port=server.port, body="fasthex", udp=udp),
                       clock=lambda: round(vehicle.now_s() * 1e9))
    try:
        client.start(receive_thread=False)
        got = 0
        for _ in range(200):        # the first frames may come before the stream is set up
            vehicle.advance(0.005)
            server.publish_due(vehicle.now_s())
            arrival_ns = round(vehicle.now_s() * 1e9)
            # Test: taken as they arrive, decoded 2 ms of the client's clock later
            deadline = 0
            while not client.receive() and deadline < 1000:  # TCP: the bytes may lag a little
                deadline += 1
            vehicle.advance(0.002)
            before = client.latest()
            if client.handle_received():
                sample = client.latest()
                assert sample is not None and sample is not before
                # Assert: stamped with the time it was taken, not the time it was decoded
                assert sample.rx_t_ns == arrival_ns and sample.valid
                got += 1
            if got >= 5:
                break
        assert got >= 5
    finally:
        client.close()
        server.close()

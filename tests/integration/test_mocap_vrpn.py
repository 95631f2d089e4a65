"""Our VRPN client, and the compiled VRPN 07.38 client inside PyPI ``motioncapture``, against
the emulated VRPN tracker server over real TCP/UDP sockets on loopback.

Both ways a VRPN connection starts are exercised: the classic handshake (the client lobs a UDP
connection request, the server connects back over TCP: the mainline VRPN client's way and our
default) and a direct TCP connection. A minimal classic-only server written here from the
protocol reference, sharing no code with the project, checks that our client reads a server
that knows nothing but the classic handshake; ``motioncapture`` checks the emulator's side."""

from __future__ import annotations

import errno
import math
import re
import socket
import struct
import threading
import time
from typing import Any

import pytest

from drivers.mocap.frames import quat_angle_rad, quat_from_axis_angle
from drivers.mocap.pose import MocapConnectError, TrackingStatus, UnknownBodyError
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
        # the default handshake is the classic one: the server called us back
        assert (server.callbacks, server.direct_connections) == (1, 0)


def test_that_an_ephemeral_port_taken_for_udp_is_traded_for_another(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Port 0: the TCP socket takes a free ephemeral port, whose number a UDP socket of
    another program may hold (seen in the test suite: "Address already in use"); the server
    then takes another port. The collision itself cannot be produced on demand: the first
    binding attempt is made to meet one."""
    # Fixture: the first attempt collides
    real_bind = VrpnServer._bind
    calls: list[int] = []

    def bind(self: VrpnServer, port: int) -> None:
        calls.append(port)
        real_bind(self, port)
        if len(calls) == 1:
            raise OSError(errno.EADDRINUSE, "Address already in use")

    monkeypatch.setattr(VrpnServer, "_bind", bind)
    # Test
    with VrpnServer(PosedVehicle(), VrpnEmulatorConfig(port=0, rate_hz=200.0)) as server, \
            VrpnClient(VrpnConfig(port=server.port, latency_s=0.002)) as client:
        # Assert: served on the second port, both ways
        assert calls == [0, 0]
        assert client.wait_frames(5, WAIT_S)
        assert (server.callbacks, server.direct_connections) == (1, 0)


def test_that_a_configured_port_in_use_is_an_error_not_another_port() -> None:
    # Fixture: the port's number held for UDP
    held = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    held.bind(("127.0.0.1", 0))
    port = held.getsockname()[1]
    try:
        # Test / Assert
        with pytest.raises(OSError) as exc_info, \
                VrpnServer(PosedVehicle(), VrpnEmulatorConfig(port=port, rate_hz=200.0)):
            pass
        assert exc_info.value.errno == errno.EADDRINUSE
    finally:
        held.close()


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


def test_that_a_direct_tcp_connection_is_taken_when_asked_for() -> None:
    with VrpnServer(PosedVehicle(), VrpnEmulatorConfig(port=0)) as server, \
            VrpnClient(VrpnConfig(port=server.port, handshake="tcp")) as client:
        assert client.wait_frames(3, WAIT_S)
        s = client.latest()
        assert s is not None and s.pos_w_m == pytest.approx((1.25, -0.5, 0.8), abs=1e-12)
        assert (server.callbacks, server.direct_connections) == (0, 1)


def test_that_a_server_that_never_calls_back_is_reached_by_direct_tcp_after_the_lob_timeout(
        ) -> None:
    # Fixture: a server variant that only accepts direct TCP (its UDP port is closed)
    with VrpnServer(PosedVehicle(), VrpnEmulatorConfig(port=0, accept="tcp")) as server, \
            VrpnClient(VrpnConfig(port=server.port, lob_timeout_s=0.3)) as client:
        # Test
        assert client.wait_frames(3, WAIT_S)
        # Assert
        s = client.latest()
        assert s is not None and s.pos_w_m == pytest.approx((1.25, -0.5, 0.8), abs=1e-12)
        assert (server.callbacks, server.direct_connections) == (0, 1)


def test_that_the_classic_handshake_alone_fails_against_a_tcp_only_server_by_name() -> None:
    with VrpnServer(PosedVehicle(), VrpnEmulatorConfig(port=0, accept="tcp")) as server, \
            pytest.raises(MocapConnectError, match="no call-back to the UDP connection request"):
        VrpnClient(VrpnConfig(port=server.port, handshake="classic",
                              connect_timeout_s=0.5, lob_timeout_s=0.5)).start()


def test_that_an_unknown_tracker_is_an_error_naming_it_and_the_announced_trackers() -> None:
    with VrpnServer(PosedVehicle(), VrpnEmulatorConfig(port=0, tracker_name="fasthex")
                    ) as server:
        port = server.port
        client = VrpnClient(VrpnConfig(tracker="Tracker0", port=port, connect_timeout_s=0.5))
        with pytest.raises(UnknownBodyError) as err:
            client.start()
    text = str(err.value)
    assert f"vrpn://Tracker0@127.0.0.1:{port}" in text
    assert "no tracker named 'Tracker0'" in text and "it announces fasthex" in text


# ------------------------------------------------------------------ independent classic server

def _vrpn_message(sender: int, kind: int, payload: bytes, t_s: float) -> bytes:
    """Header: int32 length (24 + unpadded payload), tv_sec, tv_usec, sender, type, 4 pad;
    the payload padded to 8 bytes (protocol reference, VRPN section)."""
    head = struct.pack(">iiiii", 24 + len(payload), int(t_s), int((t_s % 1.0) * 1e6), sender,
                       kind) + bytes(4)
    return head + payload + bytes(-len(payload) % 8)


def _vrpn_name(system_type: int, described: int, name: str) -> bytes:
    text = name.encode() + b"\0"
    return _vrpn_message(described, system_type, struct.pack(">i", len(text)) + text, 0.0)


class ClassicOnlyServer:
    """A VRPN tracker server that has no TCP listener at all: it waits for a client's UDP
    ``"<ip> <port>\\0"`` request and connects back, as a stock VRPN server does."""

    def __init__(self, tracker: str, pos: tuple[float, float, float],
                 q_xyzw: tuple[float, float, float, float]) -> None:
        self.udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.udp.bind(("127.0.0.1", 0))
        self.udp.settimeout(0.1)
        self.port = self.udp.getsockname()[1]
        self.requests: list[bytes] = []
        self._report = struct.pack(">ii3d4d", 0, 0, *pos, *q_xyzw)
        self._tracker = tracker
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, daemon=True)

    def __enter__(self) -> ClassicOnlyServer:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(5.0)
        self.udp.close()

    def _serve(self) -> None:
        while not self._stop.is_set():
            try:
                data, source = self.udp.recvfrom(256)
            except TimeoutError:
                continue
            self.requests.append(data)
            host, port = data.split(b"\0")[0].decode().split(" ")
            assert host == source[0]
            with socket.create_connection((host, int(port)), timeout=5.0) as tcp:
                tcp.sendall(b"vrpn: ver. 07.38  0".ljust(24, b"\0"))
                cookie = b""
                while len(cookie) < 24:
                    cookie += tcp.recv(24 - len(cookie))
                assert cookie.startswith(b"vrpn: ver. 07.")
                tcp.sendall(_vrpn_name(-1, 3, self._tracker)
                            + _vrpn_name(-2, 7, "vrpn_Tracker Pos_Quat"))
                while not self._stop.wait(0.005):
                    try:
                        tcp.sendall(_vrpn_message(3, 7, self._report, time.time()))
                    except OSError:
                        break  # the client hung up
            return  # one client is all the test needs


def test_that_our_client_reads_a_server_that_only_speaks_the_classic_handshake() -> None:
    # Fixture
    with ClassicOnlyServer("Hex", (0.5, -0.25, 1.5), (0.0, 0.0, math.sin(0.3), math.cos(0.3))
                           ) as server, \
            VrpnClient(VrpnConfig(tracker="Hex", port=server.port)) as client:
        # Test
        assert client.wait_frames(5, WAIT_S)
        s = client.latest()
    # Assert: one request, "<ip> <port>" NUL-terminated; the pose in the Z-up world frame
    [request] = server.requests
    assert request.endswith(b"\0") and request.count(b"\0") == 1
    ip, port = request[:-1].decode().split(" ")
    assert ip == "127.0.0.1" and 1 <= int(port) <= 65535
    assert s is not None and s.valid and s.body_name == "Hex"
    assert s.pos_w_m == pytest.approx((0.5, -0.25, 1.5), abs=1e-12)
    assert quat_angle_rad(s.q_wb, (math.cos(0.3), 0.0, 0.0, math.sin(0.3))) < 1e-9


def test_that_mocap_watch_reads_a_classic_only_server_at_its_rate(
        capsys: pytest.CaptureFixture[str]) -> None:
    # the operator's command against a server with no TCP listener: the classic request, the
    # call-back, the pose in the world frame, and the rate the server sends at (a report every
    # 5 ms of wall time plus the send: 200 Hz at most, well above half of it on any host; the
    # 1 s rate window may hold a few more when TCP delivers reports in bursts: 203.5 Hz seen)
    from groundstation.cli import main
    with ClassicOnlyServer("Hex", (0.5, -0.25, 1.5), (0.0, 0.0, 0.0, 1.0)) as server:
        rc = main(["mocap", "watch", f"vrpn://Hex@127.0.0.1:{server.port}?handshake=classic",
                   "--frames", "120", "--interval", "0.1"])
    assert rc == 0 and len(server.requests) == 1
    last = capsys.readouterr().out.strip().splitlines()[-1]
    assert "Hex: p [ +0.500  -0.250  +1.500] m" in last, last
    rate = re.search(r"([0-9.]+) Hz", last)
    assert rate is not None and 100.0 <= float(rate.group(1)) <= 220.0, last


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

    # The emulator as a classic-only server: the mainline client must come in by the lob.
    cfg = VrpnEmulatorConfig(port=0, rate_hz=200.0, accept="classic")
    with VrpnServer(PosedVehicle(), cfg) as server:
        # The peer blocks in C++ while waiting: run it in a daemon thread with a deadline.
        t = threading.Thread(target=read, args=(server.port,), daemon=True)
        t.start()
        t.join(WAIT_S)
        assert "pose" in result, "motioncapture received no report within the deadline"
        assert server.callbacks >= 1 and server.direct_connections == 0
    pos, q = result["pose"]
    assert pos == pytest.approx((1.25, -0.5, 0.8), abs=1e-6)
    assert quat_angle_rad(q, Q) < 1e-6

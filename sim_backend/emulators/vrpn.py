"""Emulated VRPN tracker server (as exported by Vicon Tracker, Motive or QTM).

Speaks VRPN 07.38 with the codec of :mod:`drivers.mocap.vrpn`. It accepts both ways a VRPN
connection starts (``accept``): the classic handshake, where a client lobs the UDP connection
request ``"<ip> <port>\\0"`` to ``port`` (3883) and the server connects back to that TCP port
(the mainline VRPN client's way; only the host that asked is called back, once per
listening port), and a direct TCP connection to ``port``. ``accept="classic"`` or ``"tcp"``
emulates a server that only knows one of them; ``callbacks`` and ``direct_connections``
count how clients came in. After the cookie exchange it describes its sender (the tracker
name, e.g. ``Tracker0``) and message types, then streams ``vrpn_Tracker Pos_Quat`` reports of
one sensor at ``rate_hz`` (server-clock timestamps, epoch seconds), answers
``vrpn_Base ping_message`` with a pong, and ignores everything else a client says.

The vehicle's true pose is converted into the server's frame (Z-up, metres by default, like
Vicon Tracker) with :class:`drivers.mocap.frames.FrameTransform`. Noise, a send latency and
occlusion dropouts (no report at all while occluded, as VRPN has no validity flag) are
configurable. Vehicle calls are made under the shared ``lock``.
"""

from __future__ import annotations

import contextlib
import errno
import functools
import logging
import selectors
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from config.schema import ConfigValueError, spec
from drivers.mocap import vrpn
from drivers.mocap.frames import FrameConfig, FrameTransform, quat_from_axis_angle, quat_mul
from sim_backend.emulators.schedule import CaptureSchedule
from sim_backend.vehicle import EmulatedVehicle

log = logging.getLogger(__name__)

_SENDER_ID = 0
_TYPE_POS_QUAT = 0
_TYPE_PONG = 1


#: port 0: how many ephemeral TCP ports to try for one whose number is free for UDP too
_PORT_ATTEMPTS = 20


@dataclass(frozen=True)
class VrpnEmulatorConfig:
    """The emulated VRPN tracker server. Loadable from YAML (``config.schema``)."""

    host: str = "127.0.0.1"
    port: int = spec(vrpn.DEFAULT_PORT, ge=0, le=65535, doc="TCP and UDP; 0 picks a free one")
    accept: Literal["both", "classic", "tcp"] = spec(
        "both", doc="connections: classic (UDP request, call-back), direct TCP, or both")
    tracker_name: str = "Tracker0"
    sensor: int = spec(0, ge=0)
    rate_hz: float = spec(100.0, ge=100.0, le=360.0)
    pos_noise_m: float = spec(0.0, ge=0.0)
    rot_noise_rad: float = spec(0.0, ge=0.0)
    latency_s: float = spec(0.0, ge=0.0, le=0.5)
    occlusion_probability: float = spec(0.0, ge=0.0, le=1.0)
    occlusion_frames: int = spec(10, ge=1)
    seed: int = 0
    frames: FrameConfig = field(default_factory=lambda: FrameConfig(up_axis="z"))
    server_clock_offset_s: float = spec(0.0, ge=-1e6, le=1e6,
                                        doc="the report stamps' clock minus the wall clock")
    server_clock_drift_ppm: float = spec(0.0, ge=-50_000.0, le=50_000.0,
                                         doc="rate error of the stamps' clock")

    def __post_init__(self) -> None:
        if self.accept not in ("both", "classic", "tcp"):
            raise ConfigValueError("accept", f"must be both, classic or tcp, not {self.accept!r}")


class _Conn:
    def __init__(self, sock: socket.socket, called_back: tuple[str, int] | None = None
                 ) -> None:
        self.sock = sock
        self.called_back = called_back  # the (ip, port) a connection request named
        self.parser = vrpn.VrpnStreamParser(expect_cookie=True)
        self.ready = False
        self.types: dict[int, str] = {}
        self.send_lock = threading.Lock()


class VrpnServer:
    """Emulated VRPN tracker: one tracker name, one sensor following the vehicle."""

    def __init__(self, vehicle: EmulatedVehicle, config: VrpnEmulatorConfig | None = None,
                 lock: threading.Lock | None = None,
                 wall_clock: Callable[[], float] = time.time) -> None:
        self.config = cfg = config or VrpnEmulatorConfig()
        self._vehicle = vehicle
        self._lock = lock or threading.Lock()
        self._wall = wall_clock
        self._clock0_s = wall_clock()  # where the stamps' clock error starts to accumulate
        self._transform = FrameTransform(cfg.frames)
        self._rng = np.random.default_rng(cfg.seed)
        self._tcp: socket.socket | None = None
        self._udp: socket.socket | None = None
        self._conns: list[_Conn] = []
        self._conns_lock = threading.Lock()
        self._sel = selectors.DefaultSelector()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._occluded_left = 0
        self.reports_sent = 0
        self.callbacks = 0  # clients connected back after their UDP connection request
        self.direct_connections = 0  # clients that connected over TCP directly
        self.occluded_reports = 0
        self.dropped_inputs = 0
        """Connection requests that do not parse or name another host, corrupt client streams
        (the connection is dropped) and inputs whose handling failed (logged)."""

    def _bind(self, port: int) -> None:
        cfg = self.config
        if cfg.accept != "classic":
            self._tcp = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            self._tcp.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            self._tcp.bind((cfg.host, port))
            self._tcp.listen(4)
            port = self.port
        if cfg.accept != "tcp":
            self._udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            self._udp.bind((cfg.host, port))

    def _close_listeners(self) -> None:
        for s in (self._tcp, self._udp):
            if s is not None:
                s.close()
        self._tcp = self._udp = None

    def __enter__(self) -> VrpnServer:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def port(self) -> int:
        """The bound port (TCP and UDP: the real one when configured as 0)."""
        sock = self._tcp or self._udp
        assert sock is not None, "server not started"
        return int(sock.getsockname()[1])

    def start(self) -> None:
        cfg = self.config
        # VRPN listens on one port number for both TCP and UDP. With port 0 the TCP socket
        # takes a free ephemeral port, which a UDP socket of another program may hold: then
        # take another one.
        for attempt in range(_PORT_ATTEMPTS):
            try:
                self._bind(cfg.port)
                break
            except OSError as exc:
                self._close_listeners()
                if cfg.port != 0 or exc.errno != errno.EADDRINUSE \
                        or attempt == _PORT_ATTEMPTS - 1:
                    raise
        for s in (self._tcp, self._udp):
            if s is not None:
                s.setblocking(False)
                self._sel.register(s, selectors.EVENT_READ)
        self._stop.clear()
        self._threads = [threading.Thread(target=self._serve, name="vrpn-emu-io", daemon=True),
                         threading.Thread(target=self._stream, name="vrpn-emu-stream",
                                          daemon=True)]
        for t in self._threads:
            t.start()

    def close(self) -> None:
        self._stop.set()
        for t in self._threads:
            t.join(timeout=5.0)
        self._threads = []
        with self._conns_lock:
            conns, self._conns = self._conns, []
        for c in conns:
            c.sock.close()
        for s in (self._tcp, self._udp):
            if s is not None:
                s.close()
        self._tcp = self._udp = None
        self._sel.close()

    @property
    def client_count(self) -> int:
        with self._conns_lock:
            return sum(1 for c in self._conns if c.ready)

    # ------------------------------------------------------------------ connections

    def _add(self, sock: socket.socket, called_back: tuple[str, int] | None = None) -> None:
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        sock.settimeout(2.0)  # bounds a blocked sendall; reads only follow select()
        conn = _Conn(sock, called_back)
        self._send(conn, vrpn.encode_cookie())
        with self._conns_lock:
            self._conns.append(conn)
        self._sel.register(sock, selectors.EVENT_READ, conn)

    def _drop(self, conn: _Conn) -> None:
        with self._conns_lock:
            if conn in self._conns:
                self._conns.remove(conn)
        with contextlib.suppress(KeyError, ValueError):
            self._sel.unregister(conn.sock)
        conn.sock.close()

    def _send(self, conn: _Conn, data: bytes) -> bool:
        try:
            with conn.send_lock:
                conn.sock.sendall(data)
            return True
        except OSError:
            return False

    def _serve(self) -> None:
        while not self._stop.is_set():
            for key, _ in self._sel.select(timeout=0.1):
                if key.fileobj is self._tcp:
                    with contextlib.suppress(BlockingIOError):
                        sock, _ = self._tcp.accept()
                        self._add(sock)
                        self.direct_connections += 1
                elif key.fileobj is self._udp:
                    self._on_lob()
                else:
                    self._on_readable(key.data)

    def _on_lob(self) -> None:
        assert self._udp is not None
        try:
            data, source = self._udp.recvfrom(512)
        except OSError:
            return
        self.handle_lob(data, source)

    def handle_lob(self, data: bytes, source: tuple[str, int]) -> None:
        """Serve one UDP connection request from ``source``. Never raises for any content."""
        try:
            self._call_back(data, source)
        except Exception:
            self.dropped_inputs += 1
            log.exception("vrpn emulator: connection request from %s failed", source)

    def _call_back(self, data: bytes, source: tuple[str, int]) -> None:
        try:
            ip, port = vrpn.decode_lob(data)
        except vrpn.VrpnDecodeError:
            self.dropped_inputs += 1
            return
        if ip != source[0]:  # only call back the host that asked, never a third address
            self.dropped_inputs += 1
            log.warning("vrpn emulator: ignoring request from %s to call %s", source[0], ip)
            return
        with self._conns_lock:
            if any(c.called_back == (ip, port) for c in self._conns):
                return  # clients repeat their request until the call-back arrives
        try:
            sock = socket.create_connection((ip, port), timeout=2.0)
        except OSError as exc:
            log.warning("vrpn emulator: cannot call back %s:%d: %s", ip, port, exc)
            return
        self._add(sock, called_back=(ip, port))
        self.callbacks += 1

    def _on_readable(self, conn: _Conn) -> None:
        try:
            chunk = conn.sock.recv(65536)
        except (BlockingIOError, TimeoutError):
            return
        except OSError:
            chunk = b""
        if not chunk:
            self._drop(conn)
            return
        try:
            ok = self.handle_stream(conn, chunk)
        except Exception:
            self.dropped_inputs += 1
            log.exception("vrpn emulator: client input failed")
            ok = False
        if not ok:
            self._drop(conn)

    def handle_stream(self, conn: _Conn, chunk: bytes) -> bool:
        """Serve bytes a client sent on its connection; False when the stream is corrupt (the
        caller drops the connection)."""
        try:
            msgs = conn.parser.feed(chunk)
        except vrpn.VrpnDecodeError as exc:
            self.dropped_inputs += 1
            log.warning("vrpn emulator: dropping client: %s", exc)
            return False
        if not conn.ready and conn.parser.peer_version:
            self._describe(conn)
        for m in msgs:
            if m.type_id == vrpn.SystemType.TYPE_DESCRIPTION:
                with contextlib.suppress(vrpn.VrpnDecodeError):
                    conn.types[m.sender_id] = vrpn.decode_description(m.payload)
            elif conn.types.get(m.type_id) == vrpn.PING_TYPE:
                self._send(conn, vrpn.encode_message(_SENDER_ID, _TYPE_PONG, b"", self._wall()))
        return True

    def connection_for(self, sock: socket.socket) -> _Conn:
        """A client connection on ``sock`` as :meth:`handle_stream` takes it (in-process
        fuzzing; it is not registered with the server)."""
        return _Conn(sock)

    def _describe(self, conn: _Conn) -> None:
        t = self._wall()
        self._send(conn, b"".join((
            vrpn.encode_description(vrpn.SystemType.SENDER_DESCRIPTION, _SENDER_ID,
                                    self.config.tracker_name, t),
            vrpn.encode_description(vrpn.SystemType.TYPE_DESCRIPTION, _TYPE_POS_QUAT,
                                    vrpn.POS_QUAT_TYPE, t),
            vrpn.encode_description(vrpn.SystemType.TYPE_DESCRIPTION, _TYPE_PONG,
                                    vrpn.PONG_TYPE, t))))
        conn.ready = True

    # ------------------------------------------------------------------ streaming

    def _report(self, t_s: float) -> bytes | None:
        cfg = self.config
        with self._lock:
            pose = self._vehicle.true_pose()
        if self._occluded_left == 0 and cfg.occlusion_probability > 0.0 \
                and self._rng.random() < cfg.occlusion_probability:
            self._occluded_left = cfg.occlusion_frames
        if self._occluded_left > 0:
            self._occluded_left -= 1
            self.occluded_reports += 1
            return None
        pos, q = pose.pos_w_m, pose.q_wb
        if cfg.pos_noise_m > 0.0:
            n = self._rng.normal(0.0, cfg.pos_noise_m, 3)
            pos = (pos[0] + float(n[0]), pos[1] + float(n[1]), pos[2] + float(n[2]))
        if cfg.rot_noise_rad > 0.0:
            r = self._rng.normal(0.0, cfg.rot_noise_rad, 3)
            q = quat_mul(q, quat_from_axis_angle((float(r[0]), float(r[1]), float(r[2])),
                                                 float(np.linalg.norm(r))))
        p_m, q_m = self._transform.to_mocap(pos, q)
        return vrpn.encode_message(_SENDER_ID, _TYPE_POS_QUAT,
                                   vrpn.encode_pos_quat(vrpn.TrackerPose(cfg.sensor, p_m, q_m)),
                                   t_s)

    def server_time_s(self, wall_s: float) -> float:
        """The stamp the server's clock puts on a report captured at ``wall_s``."""
        cfg = self.config
        return (wall_s + cfg.server_clock_offset_s
                + (wall_s - self._clock0_s) * cfg.server_clock_drift_ppm * 1e-6)

    def _stream(self) -> None:
        schedule: CaptureSchedule[bytes] = CaptureSchedule(1.0 / self.config.rate_hz)
        while not self._stop.is_set():
            now = self._wall()
            stamp_s = self.server_time_s(now)
            _, due = schedule.due(now, self.config.latency_s,
                                  functools.partial(self._report, stamp_s))
            for msg in due:
                with self._conns_lock:
                    targets = [c for c in self._conns if c.ready]
                for c in targets:
                    if self._send(c, msg):
                        self.reports_sent += 1
            wake = schedule.next_event_s()
            self._stop.wait(max(0.0, min(wake - self._wall(), 0.05)))

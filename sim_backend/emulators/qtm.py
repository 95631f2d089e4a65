"""Emulated Qualisys QTM RT server streaming an emulated vehicle's true pose as a 6DOF body.

Speaks the QTM RT protocol (little-endian, 1.0 to 1.25) over TCP with the codec of
:mod:`drivers.mocap.qtm`, so any QTM RT client can read it (``protocol-mocap-mavlink.md`` §3a):
our :class:`~drivers.mocap.qtm_client.QtmClient`, Qualisys' own ``qtm-rt`` SDK, and the C++ RT
SDK inside ``motioncapture`` (libmotioncapture's ``qualisys`` backend).

Each client is greeted with ``QTM RT Interface connected``. Commands (case-insensitive):
``Version [1.N]``, ``QTMVersion``, ``ByteOrder``, ``GetState`` (answered by an event packet:
``Capture started``, the emulator is always measuring), ``GetParameters All|General|6D ...``
(XML in the layout of the negotiated version; other known sections are left out),
``StreamFrames AllFrames|Frequency:N|FrequencyDivisor:N [UDP[:ADDR]:PORT] COMPONENTS``
(components 6D, 6DRes, 6DEuler, 6DEulerRes; other known components are left out of the data
packets; no answer on success, as QTM), ``StreamFrames Stop``, ``GetCurrentFrame COMPONENTS``,
``TakeControl`` / ``ReleaseControl``. Anything else is answered by an error packet and the
connection stays; a stream that does not frame (impossible packet size) is dropped. UDP frames
go only to the host of the TCP connection that asked for them (``ADDR``, if given, must be it).

Bodies: the vehicle (``body_name``, index 0) and optional static bodies (a landing pad, ...)
after it, in the server's frame (Z-up, mm by default) via
:class:`drivers.mocap.frames.FrameTransform`. 6D Euler angles use QTM's default convention.
Noise, a send latency and occlusion dropouts (the body's values are NaN, as QTM sends a body it
does not track) are configurable; timestamps (µs) are on the server's own clock (offset and
rate error configurable).

Two ways to run it, like :mod:`sim_backend.emulators.natnet`: realtime (``start()`` paces
captures on the wall clock) or lockstep (``start(realtime=False)``, then
:meth:`QtmServer.publish_due` with the simulated time). Vehicle calls are made under the shared
``lock``. :meth:`QtmServer.handle_stream` serves client bytes in process (fuzzing).
"""

from __future__ import annotations

import contextlib
import logging
import math
import selectors
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from config.schema import ConfigValueError, spec
from drivers.mocap import qtm
from drivers.mocap.frames import (
    IDENTITY_Q,
    FrameConfig,
    FrameTransform,
    Quat,
    Vec3,
    quat_from_axis_angle,
    quat_mul,
)
from sim_backend.emulators.schedule import CaptureSchedule
from sim_backend.vehicle import EmulatedVehicle

log = logging.getLogger(__name__)

_NAN = math.nan
#: How QTM sends a body it does not track: every value NaN.
NAN_BODY = qtm.SixDofBody((_NAN, _NAN, _NAN), (_NAN,) * 9, (_NAN, _NAN, _NAN), _NAN)
MAX_CLIENTS = 16
MAX_MINOR_VERSION = 25  # RT protocol 1.25


@dataclass(frozen=True)
class QtmStaticBody:
    """An extra 6DOF body at a fixed world pose; bodies are indexed in configuration order."""

    name: str
    pos_w_m: Vec3 = (0.0, 0.0, 0.0)
    q_wb: Quat = IDENTITY_Q


@dataclass(frozen=True)
class QtmEmulatorConfig:
    """The emulated QTM server. Loadable from YAML (``config.schema``)."""

    host: str = "127.0.0.1"
    port: int = spec(qtm.DEFAULT_PORT, ge=0, le=65535, doc="TCP; 0 picks a free one")
    rate_hz: float = spec(100.0, ge=1.0, le=1000.0, doc="capture rate")
    body_name: str = "fasthex"
    static_bodies: tuple[QtmStaticBody, ...] = ()
    pos_noise_m: float = spec(0.0, ge=0.0, doc="standard deviation per axis")
    rot_noise_rad: float = spec(0.0, ge=0.0, doc="standard deviation per axis")
    residual_mm: float = spec(0.4, ge=0.0, doc="reported in the residual components")
    latency_s: float = spec(0.0, ge=0.0, le=0.5, doc="capture -> send")
    occlusion_probability: float = spec(0.0, ge=0.0, le=1.0, doc="per frame, starts a dropout")
    occlusion_frames: int = spec(10, ge=1)
    seed: int = 0
    frames: FrameConfig = field(default_factory=lambda: FrameConfig(up_axis="z", units="mm"))
    server_clock_offset_s: float = spec(0.0, ge=0.0, le=1e6,
                                        doc="the server's clock minus the emulator's")
    server_clock_drift_ppm: float = spec(0.0, ge=-50_000.0, le=50_000.0,
                                         doc="rate error of the server's clock")
    qtm_version: str = "QTM Version is 2023.3 (build 9999, emulated)"

    def __post_init__(self) -> None:
        names = [self.body_name] + [b.name for b in self.static_bodies]
        if not all(names) or len(set(names)) != len(names):
            raise ConfigValueError("static_bodies", "body names must be non-empty and unique")


@dataclass
class _Stream:
    components: tuple[qtm.ComponentType, ...]
    divisor: int
    udp: tuple[str, int] | None  # None: frames on the TCP connection


class _Conn:
    def __init__(self, sock: socket.socket) -> None:
        self.sock = sock
        self.peer_ip = ""
        with contextlib.suppress(OSError):
            peer = sock.getpeername()
            if isinstance(peer, tuple):  # an IP socket (a socketpair in tests has no address)
                self.peer_ip = str(peer[0])
        self.parser = qtm.QtmStreamParser()
        self.version = (1, MAX_MINOR_VERSION)
        self.stream: _Stream | None = None
        self.send_lock = threading.Lock()


@dataclass
class QtmEmulatorCounters:
    frames_captured: int = 0
    frames_sent: int = 0  # data packets (per client)
    occluded_frames: int = 0
    refused_commands: int = 0  # answered by an error packet
    dropped_clients: int = 0  # stream did not frame, or beyond MAX_CLIENTS
    input_errors: int = 0  # inputs whose handling failed unexpectedly (logged)

    @property
    def dropped_inputs(self) -> int:
        return self.refused_commands + self.dropped_clients + self.input_errors


class QtmServer:
    """Emulated QTM: the vehicle's 6DOF body plus optional static bodies."""

    def __init__(self, vehicle: EmulatedVehicle, config: QtmEmulatorConfig | None = None,
                 lock: threading.Lock | None = None,
                 wall_clock: Callable[[], float] = time.monotonic) -> None:
        self.config = cfg = config or QtmEmulatorConfig()
        self._vehicle = vehicle
        self._lock = lock or threading.Lock()
        self._wall = wall_clock
        self._transform = FrameTransform(cfg.frames)
        self._rng = np.random.default_rng(cfg.seed)
        self.counters = QtmEmulatorCounters()
        self._tcp: socket.socket | None = None
        self._udp: socket.socket | None = None
        self._conns: list[_Conn] = []
        self._conns_lock = threading.Lock()
        self._sel = selectors.DefaultSelector()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._stream_lock = threading.Lock()
        self._schedule: CaptureSchedule[tuple[int, int, tuple[qtm.SixDofBody, ...]]] = \
            CaptureSchedule(1.0 / cfg.rate_hz)
        self._frame_number = 0
        self._occluded_left = 0
        self._last: tuple[int, int, tuple[qtm.SixDofBody, ...]] | None = None
        self._t0_wall = 0.0

    # ------------------------------------------------------------------ lifecycle

    def __enter__(self) -> QtmServer:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def port(self) -> int:
        """The bound TCP port (the real one when configured as 0)."""
        assert self._tcp is not None, "server not started"
        return int(self._tcp.getsockname()[1])

    @property
    def body_names(self) -> tuple[str, ...]:
        return (self.config.body_name, *(b.name for b in self.config.static_bodies))

    @property
    def client_count(self) -> int:
        with self._conns_lock:
            return len(self._conns)

    def start(self, realtime: bool = True) -> None:
        """Listen and serve commands; with ``realtime``, also capture on the wall clock."""
        cfg = self.config
        self._tcp = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._tcp.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._tcp.bind((cfg.host, cfg.port))
        self._tcp.listen(4)
        self._tcp.setblocking(False)
        self._sel.register(self._tcp, selectors.EVENT_READ)
        self._udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._udp.bind((cfg.host, 0))
        self._stop.clear()
        self._threads = [threading.Thread(target=self._serve, name="qtm-emu-io", daemon=True)]
        if realtime:
            self._t0_wall = self._wall()
            self._threads.append(threading.Thread(target=self._stream_realtime,
                                                  name="qtm-emu-stream", daemon=True))
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

    # ------------------------------------------------------------------ connections

    def _serve(self) -> None:
        while not self._stop.is_set():
            for key, _ in self._sel.select(timeout=0.1):
                if key.fileobj is self._tcp:
                    with contextlib.suppress(BlockingIOError, OSError):
                        sock, _ = self._tcp.accept()
                        self._add(sock)
                else:
                    self._on_readable(key.data)

    def _add(self, sock: socket.socket) -> None:
        with self._conns_lock:
            full = len(self._conns) >= MAX_CLIENTS
        if full:
            self.counters.dropped_clients += 1
            sock.close()
            return
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        sock.settimeout(2.0)  # bounds a blocked sendall; reads only follow select()
        conn = _Conn(sock)
        with self._conns_lock:
            self._conns.append(conn)
        self._sel.register(sock, selectors.EVENT_READ, conn)
        self._send(conn, qtm.encode_command(qtm.WELCOME))

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
            self.counters.input_errors += 1
            log.exception("qtm emulator: client input failed")
            ok = False
        if not ok:
            self._drop(conn)

    def connection_for(self, sock: socket.socket) -> _Conn:
        """A client connection on ``sock`` as :meth:`handle_stream` takes it (in-process
        fuzzing; it is not registered with the server)."""
        return _Conn(sock)

    def handle_stream(self, conn: _Conn, chunk: bytes) -> bool:
        """Serve bytes a client sent; False when the stream does not frame (the caller drops
        the connection). Never raises for any content."""
        try:
            packets = conn.parser.feed(chunk)
        except qtm.QtmDecodeError as exc:
            self.counters.dropped_clients += 1
            log.warning("qtm emulator: dropping client: %s", exc)
            return False
        for p in packets:
            if p.kind == qtm.PacketType.COMMAND:
                reply = self._command(conn, qtm.decode_text(p.body))
            else:
                reply = self._refuse(f"Packet type {p.kind} not supported by the emulator")
            if reply:
                self._send(conn, reply)
        return True

    def _refuse(self, text: str) -> bytes:
        self.counters.refused_commands += 1
        return qtm.encode_error(text)

    # ------------------------------------------------------------------ commands

    def _command(self, conn: _Conn, text: str) -> bytes | None:
        """The answer to one command (None: QTM sends none)."""
        words = text.split()
        if not words:
            return self._refuse("Parse error")
        verb, args = words[0].lower(), words[1:]
        if verb == "version":
            return self._version(conn, args)
        if verb == "qtmversion":
            return qtm.encode_command(self.config.qtm_version)
        if verb == "byteorder":
            return qtm.encode_command("Byte order is little endian")
        if verb == "getstate":
            return qtm.encode_event(qtm.Event.CAPTURE_STARTED)
        if verb == "getparameters":
            return self._parameters(conn, [a.lower() for a in args])
        if verb == "streamframes":
            return self._stream_frames(conn, " ".join(args))
        if verb == "getcurrentframe":
            comps = self._components(args)
            if isinstance(comps, bytes):
                return comps
            return self._current_frame(comps)
        if verb == "takecontrol":
            return qtm.encode_command("You are now master")
        if verb == "releasecontrol":
            return qtm.encode_command("You are now a regular client")
        return self._refuse("Parse error")

    def _version(self, conn: _Conn, args: list[str]) -> bytes:
        if not args:
            return qtm.encode_command(f"Version is {conn.version[0]}.{conn.version[1]}")
        try:
            major_text, minor_text = args[0].split(".")
            version = (int(major_text), int(minor_text))
        except ValueError:
            return self._refuse("Parse error")
        if version[0] != 1 or not 0 <= version[1] <= MAX_MINOR_VERSION:
            return self._refuse("Version NOT supported")
        conn.version = version
        return qtm.encode_command(f"Version set to {args[0]}")

    def _parameters(self, conn: _Conn, args: list[str]) -> bytes:
        known = {"all", "general", "3d", "6d", "analog", "force", "image", "gazevector",
                 "eyetracker", "skeleton", "skeleton:global", "calibration", "timecode"}
        if not args or any(a not in known for a in args):
            return self._refuse("Parse error")
        with_6d = "all" in args or "6d" in args
        with_general = "all" in args or "general" in args
        names = list(self.body_names) if with_6d else None
        return qtm.encode_xml(qtm.encode_6d_parameters(
            names, conn.version, self.config.rate_hz if with_general else None))

    def _components(self, names: list[str]) -> tuple[qtm.ComponentType, ...] | bytes:
        """Requested 6D components (others QTM knows are left out); an error packet if a
        name is unknown or none is given."""
        others = {"2d", "2dlin", "3d", "3dres", "3dnolabels", "3dnolabelsres", "analog",
                  "analogsingle", "force", "forcesingle", "image", "gazevector", "eyetracker",
                  "timecode", "skeleton", "skeleton:global", "all"}
        comps: list[qtm.ComponentType] = []
        for name in names:
            lname = name.lower()
            if lname in qtm.SIX_DOF_COMPONENTS:
                comps.append(qtm.SIX_DOF_COMPONENTS[lname][0])
            elif lname == "all":
                comps.append(qtm.ComponentType.C6D)
            elif lname not in others:
                return self._refuse(f"Parse error: unknown component {name}")
        if not names:
            return self._refuse("Parse error: no component")
        return tuple(dict.fromkeys(comps))

    def _stream_frames(self, conn: _Conn, args: str) -> bytes | None:
        if args.strip().lower() == "stop":
            conn.stream = None
            return None
        try:
            rate, names, udp_port, udp_addr = qtm.parse_stream_command(args)
        except qtm.QtmDecodeError as exc:
            return self._refuse(f"Parse error: {exc}")
        divisor = 1
        try:
            if rate.startswith("frequency:"):
                divisor = max(1, round(self.config.rate_hz / float(rate.split(":", 1)[1])))
            elif rate.startswith("frequencydivisor:"):
                divisor = int(rate.split(":", 1)[1])
            elif rate != "allframes":
                raise ValueError(rate)
        except (ValueError, ZeroDivisionError):
            return self._refuse(f"Parse error: bad rate {rate}")
        if not 1 <= divisor <= 1_000_000:
            return self._refuse(f"Parse error: bad rate {rate}")
        comps = self._components(names)
        if isinstance(comps, bytes):
            return comps
        udp = None
        if udp_port is not None:
            if udp_addr is not None and udp_addr != conn.peer_ip:
                # never send frames to a third host
                return self._refuse("UDP address must be the client's own")
            udp = (conn.peer_ip, udp_port)
        conn.stream = _Stream(comps, divisor, udp)
        return None

    # ------------------------------------------------------------------ frames

    def _noisy(self, pos: Vec3, q: Quat) -> tuple[Vec3, Quat]:
        cfg = self.config
        if cfg.pos_noise_m > 0.0:
            n = self._rng.normal(0.0, cfg.pos_noise_m, 3)
            pos = (pos[0] + float(n[0]), pos[1] + float(n[1]), pos[2] + float(n[2]))
        if cfg.rot_noise_rad > 0.0:
            r = self._rng.normal(0.0, cfg.rot_noise_rad, 3)
            q = quat_mul(q, quat_from_axis_angle((float(r[0]), float(r[1]), float(r[2])),
                                                 float(np.linalg.norm(r))))
        return pos, q

    def body_on_wire(self, pos_w_m: Vec3, q_wb: Quat) -> qtm.SixDofBody:
        """A world-frame pose as QTM sends it (server frame and units, matrix and Euler)."""
        p, q_xyzw = self._transform.to_mocap(pos_w_m, q_wb)
        return qtm.SixDofBody(p, qtm.quat_to_matrix(q_xyzw), qtm.quat_to_euler(q_xyzw),
                              self.config.residual_mm)

    def _capture(self) -> tuple[qtm.SixDofBody, ...]:
        cfg = self.config
        with self._lock:
            pose = self._vehicle.true_pose()
        self._frame_number += 1
        if self._occluded_left == 0 and cfg.occlusion_probability > 0.0 \
                and self._rng.random() < cfg.occlusion_probability:
            self._occluded_left = cfg.occlusion_frames
        if self._occluded_left > 0:
            self._occluded_left -= 1
            self.counters.occluded_frames += 1
            vehicle = NAN_BODY
        else:
            vehicle = self.body_on_wire(*self._noisy(pose.pos_w_m, pose.q_wb))
        self.counters.frames_captured += 1
        return (vehicle, *(self.body_on_wire(b.pos_w_m, b.q_wb) for b in cfg.static_bodies))

    def occlude(self, frames: int) -> None:
        """The vehicle's body is not tracked (NaN) in the next ``frames`` frames."""
        with self._stream_lock:
            self._occluded_left = max(self._occluded_left, int(frames))

    def server_timestamp_us(self, t_capture_s: float) -> int:
        cfg = self.config
        rate = 1.0 + cfg.server_clock_drift_ppm * 1e-6
        return round((cfg.server_clock_offset_s + t_capture_s * rate) * 1e6)

    @staticmethod
    def _packet(timestamp_us: int, frame_number: int, bodies: tuple[qtm.SixDofBody, ...],
                comps: tuple[qtm.ComponentType, ...]) -> bytes:
        return qtm.encode_data_frame(qtm.DataFrame(timestamp_us, frame_number, tuple(
            qtm.SixDofComponent(kind, 0, 0, bodies) for kind in comps)))

    def _current_frame(self, comps: tuple[qtm.ComponentType, ...]) -> bytes:
        with self._stream_lock:
            if self._last is None:
                now = self._wall() - self._t0_wall
                self._last = (self.server_timestamp_us(now), self._frame_number + 1,
                              self._capture())
            ts, number, bodies = self._last
        return self._packet(ts, number, bodies, comps)

    def _send_frame(self, timestamp_us: int, frame_number: int,
                    bodies: tuple[qtm.SixDofBody, ...]) -> None:
        with self._conns_lock:
            targets = [(c, c.stream) for c in self._conns if c.stream is not None]
        for conn, stream in targets:
            assert stream is not None
            if frame_number % stream.divisor:
                continue
            packet = self._packet(timestamp_us, frame_number, bodies, stream.components)
            if stream.udp is None:
                ok = self._send(conn, packet)
            else:
                ok = False
                if self._udp is not None:
                    with contextlib.suppress(OSError):
                        self._udp.sendto(packet, stream.udp)
                        ok = True
            if ok:
                self.counters.frames_sent += 1

    def publish_due(self, now_s: float, defer: bool = False) -> int:
        """Capture every frame due by ``now_s`` (emulator time, s) and send those whose send
        time (capture + latency) has come. Returns the number of frames captured. In lockstep a
        frame due between two calls carries the vehicle's pose and timestamp at ``now_s``.
        ``defer``: as :meth:`NatNetServer.publish_due`."""
        def capture() -> tuple[int, int, tuple[qtm.SixDofBody, ...]]:
            bodies = self._capture()
            self._last = (self.server_timestamp_us(now_s), self._frame_number, bodies)
            return self._last

        with self._stream_lock:
            captured, due = self._schedule.due(now_s, self.config.latency_s, capture, defer)
        for ts, number, bodies in due:
            self._send_frame(ts, number, bodies)
        return captured

    def capture_deferred(self) -> int:
        """Capture the frames ``publish_due(..., defer=True)`` left; returns how many."""
        with self._stream_lock:
            return self._schedule.capture_deferred()

    def next_event_s(self) -> float:
        with self._stream_lock:
            return self._schedule.next_event_s()

    def _stream_realtime(self) -> None:
        while not self._stop.is_set():
            try:
                self.publish_due(self._wall() - self._t0_wall)
            except Exception:  # keep the emulator alive; the failure is logged
                log.exception("qtm emulator: publishing failed")
            wait = self.next_event_s() - (self._wall() - self._t0_wall)
            if wait > 0.0:
                self._stop.wait(min(wait, 0.05))


__all__ = ["QtmEmulatorConfig", "QtmServer", "QtmStaticBody"]

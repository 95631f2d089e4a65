"""Qualisys QTM RT client device: one named 6DOF body as a PoseSource.

Wire protocol: see :mod:`drivers.mocap.qtm` (TCP port 22223, little-endian, RT protocol 1.2x).

Connection sequence (``start()``, blocking, before the thread runs; each step bounded by
``connect_timeout_s``):

1. TCP connect to ``host:port`` and wait for the greeting ``QTM RT Interface connected``;
2. ``Version 1.25`` (answered ``Version set to 1.25``; an error packet means QTM is too old);
3. ``GetParameters 6D``: body names in index order; an unknown configured body raises
   :class:`~drivers.mocap.pose.UnknownBodyError` listing the names QTM defines (an empty
   ``body`` takes the first one);
4. ``StreamFrames AllFrames`` (or ``Frequency:N``) with the configured 6D component (``6D`` by
   default: the rotation matrix does not depend on QTM's Euler-angle setting), over the TCP
   connection or, with ``udp``, to a UDP socket of this client (``UDP:PORT``; only datagrams
   from the server's address are accepted, others are counted as foreign).

The receive thread turns every data packet into a world-frame
:class:`~drivers.mocap.pose.PoseSample` of the configured body: a body QTM does not track (NaN
position) is ``INVALID``, a body index beyond the frame's body count ``MISSING``. A TCP stream
that does not decode (impossible packet size) is counted as malformed and the connection is
re-opened (the whole sequence again); a data packet that does not decode is counted and dropped.
Error packets and events are logged (``QTM shutting down`` is a warning); ``GetParameters`` is
sent again when QTM reports changed camera settings.

Time: the packet's capture timestamp (µs on QTM's clock) is mapped onto the injected clock by
:class:`drivers.clock_sync.ClockSync` (offset and drift, on the earliest arrivals; never later
than the arrival), minus the configured ``latency_s`` (the smallest latency of the MoCap chain,
which one-way stamps cannot see); ``latency_s`` of a sample is arrival minus ``t_ns``.

Plausibility (:class:`~drivers.mocap.pose.PoseLimits`): a timestamp giving a latency outside
0..1 s, a non-finite or out-of-workspace position, or a rotation matrix that is not one
(rebuilt from its quaternion it differs by more than ``max_quat_norm_error``) is dropped and
counted (``stats().implausible_samples``); the previous sample stays the latest.
:meth:`QtmClient.feed_stream` and :meth:`QtmClient.feed_datagram` run the receive path in
process (fuzzing, replay); ``start(receive_thread=False)`` with :meth:`QtmClient.poll` lets a
lockstep loop receive in its own thread.

Default axes are QTM's: Z-up, millimetres.
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

from config.schema import ConfigValueError
from drivers.clock_sync import ClockSync
from drivers.mocap import qtm
from drivers.mocap.frames import FrameConfig, FrameTransform
from drivers.mocap.pose import (
    NAN3,
    NAN4,
    FrameWaits,
    MocapConnectError,
    PoseLimits,
    PoseSample,
    StreamMonitor,
    TrackingStatus,
    UnknownBodyError,
    WaitingSockets,
)

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class QtmConfig:
    """Which QTM server and 6DOF body to read. Loadable from YAML (``config.schema``)."""

    host: str = "127.0.0.1"
    port: int = qtm.DEFAULT_PORT
    body: str = ""  # 6DOF body name; empty: the first one QTM defines
    component: str = "6d"  # 6d | 6dres | 6deuler | 6deulerres
    frequency_hz: float = 0.0  # 0: every frame (AllFrames); else StreamFrames Frequency:N
    udp: bool = False  # frames over UDP to a port of this client instead of the TCP connection
    local_ip: str = "0.0.0.0"  # where the UDP socket binds (with ``udp``)
    latency_s: float = 0.0
    connect_timeout_s: float = 3.0
    frames: FrameConfig = field(default_factory=lambda: FrameConfig(up_axis="z", units="mm"))
    limits: PoseLimits = field(default_factory=PoseLimits)

    def __post_init__(self) -> None:
        if not 1 <= self.port <= 65535:
            raise ConfigValueError("port", "must be a TCP port (1..65535)")
        if self.component.lower() not in qtm.SIX_DOF_COMPONENTS:
            raise ConfigValueError("component", f"must be one of "
                                   f"{sorted(qtm.SIX_DOF_COMPONENTS)}, not {self.component!r}")
        if not self.frequency_hz >= 0.0:
            raise ConfigValueError("frequency_hz", "must be >= 0 (0: every frame)")
        if not 0.0 <= self.latency_s <= self.limits.max_latency_s:
            raise ConfigValueError("latency_s", f"must be in [0, {self.limits.max_latency_s}] s")
        if not self.connect_timeout_s > 0.0:
            raise ConfigValueError("connect_timeout_s", "must be > 0")

    @property
    def name(self) -> str:
        return f"qtm://{self.host}:{self.port}"

    def stream_command(self, udp_port: int | None) -> str:
        rate = "AllFrames" if self.frequency_hz == 0.0 else f"Frequency:{self.frequency_hz:g}"
        udp = f" UDP:{udp_port}" if udp_port is not None else ""
        return f"StreamFrames {rate}{udp} {self.component.lower()}"


class QtmClient(FrameWaits):
    """A :class:`~drivers.mocap.pose.PoseSource` reading one 6DOF body from Qualisys QTM.

    ``with QtmClient(cfg) as c: c.latest()``. ``clock`` returns nanoseconds (the ground-station
    clock; ``time.monotonic_ns`` by default).
    """

    def __init__(self, config: QtmConfig, clock: Callable[[], int] = time.monotonic_ns
                 ) -> None:
        self.config = config
        self._clock = clock
        self._transform = FrameTransform(config.frames)
        self.monitor = StreamMonitor(clock)
        self._waiting = WaitingSockets()  # poll(): is anything there at all
        self.server_clock = ClockSync()  # QTM's capture timestamps -> ours
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._sock: socket.socket | None = None
        self._udp: socket.socket | None = None
        self._server_ip = ""
        self._parser = qtm.QtmStreamParser()
        self._backlog: list[qtm.Packet] = []  # decoded during the handshake, not yet used
        #: receive(): what was taken off the sockets, not yet handled: (UDP sender or None for
        #: the TCP stream, bytes, arrival time)
        self._received: list[tuple[tuple[str, int] | None, bytes, int]] = []
        self._names: tuple[str, ...] = ()
        self._index: int | None = None
        self._latest: PoseSample | None = None
        self._frames_seen = 0
        self.last_event: qtm.Event | None = None
        self.server_errors: list[str] = []  # error packets after the handshake (newest last)
        self.reconnects = 0

    # ------------------------------------------------------------------ lifecycle

    def __enter__(self) -> QtmClient:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def start(self, receive_thread: bool = True) -> None:
        """Connect, handshake, resolve the body and start streaming (raises MocapConnectError
        or UnknownBodyError), then start the receive thread.

        With ``receive_thread=False`` nothing receives in the background: the owner calls
        :meth:`poll` (a lockstep loop does, so that it sees exactly the frames that arrived
        before its IMU sample, whatever the thread scheduling)."""
        self._connect()
        self._stop.clear()
        if not receive_thread and self._sock is not None:
            self._sock.setblocking(False)  # poll() must never wait
        if receive_thread:
            self._thread = threading.Thread(target=self._run, name="qtm-rx", daemon=True)
            self._thread.start()

    def poll(self) -> int:
        """Receive and handle every packet already waiting, in the caller's thread; never
        blocks. Returns the number of TCP reads and datagrams handled. A broken connection is
        closed (and, without the receive thread, not re-opened). (:meth:`receive`, then
        :meth:`handle_received`.)"""
        received = self.receive()
        self.handle_received()
        return received

    def receive(self) -> int:
        """Take what is already waiting off the sockets (datagrams, TCP reads), each with its
        arrival time, without decoding it (:meth:`handle_received` does); the caller's
        thread, never blocks. Returns how many. A connection found closed is closed here. As
        :meth:`NatNetClient.receive`."""
        sock, udp = self._sock, self._udp
        if not self._waiting.any((sock, udp)):
            return 0
        received = 0
        while udp is not None:
            try:
                data, addr = udp.recvfrom(65536)
            except OSError:  # BlockingIOError: nothing waiting
                break
            self._received.append((addr, data, self._clock()))
            received += 1
        while sock is not None:
            try:
                chunk = sock.recv(65536, socket.MSG_DONTWAIT)
            except (BlockingIOError, InterruptedError, TimeoutError):
                break
            except OSError:
                chunk = b""
            received += 1
            if not chunk:
                self._reset()
                break
            self._received.append((None, chunk, self._clock()))
        return received

    def handle_received(self) -> int:
        """Decode and apply what :meth:`receive` took, in arrival order; how many. A corrupt
        stream closes the connection."""
        todo, self._received = self._received, []
        corrupt = False
        for addr, data, rx_t_ns in todo:
            if addr is not None:
                self.feed_datagram(data, addr, rx_t_ns)
            elif not corrupt and not self.feed_stream(data, rx_t_ns):
                corrupt = True      # the rest of that connection's bytes go with it
                self._reset()
        return len(todo)

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=5.0)
        self._thread = None
        self._reset()

    def _reset(self) -> None:
        for s in (self._sock, self._udp):
            if s is not None:
                with contextlib.suppress(OSError):
                    s.close()
        self._sock = self._udp = None

    # ------------------------------------------------------------------ handshake

    def _connect(self) -> None:
        cfg = self.config
        try:
            sock = socket.create_connection((cfg.host, cfg.port), timeout=cfg.connect_timeout_s)
        except OSError as exc:
            raise MocapConnectError(cfg.name, f"cannot connect: {exc} (QTM not running, wrong "
                                    "address, or not its little-endian RT port 22223?)") from exc
        udp: socket.socket | None = None
        try:
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self._parser = qtm.QtmStreamParser()
            self._backlog = []
            self._server_ip = str(sock.getpeername()[0])
            deadline = time.monotonic() + cfg.connect_timeout_s
            greeting = self._await(sock, None, deadline, "greeting")
            if greeting.kind != qtm.PacketType.COMMAND or \
                    qtm.decode_text(greeting.body) != qtm.WELCOME:
                raise MocapConnectError(cfg.name, f"not a QTM RT server (greeting "
                                        f"{greeting.body[:40]!r})")
            answer = self._await(sock, f"Version {qtm.PROTOCOL_VERSION}", deadline, "Version")
            if answer.kind != qtm.PacketType.COMMAND:
                raise MocapConnectError(cfg.name, f"QTM refused RT protocol "
                                        f"{qtm.PROTOCOL_VERSION}: {qtm.decode_text(answer.body)}")
            self._read_parameters(sock, deadline)
            if cfg.udp:
                udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
                udp.bind((cfg.local_ip, 0))
                udp.setblocking(False)
            sock.sendall(qtm.encode_command(cfg.stream_command(
                int(udp.getsockname()[1]) if udp is not None else None)))
        except qtm.QtmDecodeError as exc:
            self._close_all(sock, udp)
            raise MocapConnectError(cfg.name, f"not a QTM RT server: {exc}") from exc
        except OSError as exc:
            self._close_all(sock, udp)
            raise MocapConnectError(cfg.name, f"handshake failed: {exc}") from exc
        except BaseException:
            self._close_all(sock, udp)
            raise
        sock.settimeout(0.1)
        self._sock, self._udp = sock, udp
        rx = self._clock()
        backlog, self._backlog = self._backlog, []
        for p in backlog:  # arrived with the last answer: frames may already be among them
            self._on_packet(p, rx)

    @staticmethod
    def _close_all(*socks: socket.socket | None) -> None:
        for s in socks:
            if s is not None:
                s.close()

    def _await(self, sock: socket.socket, command: str | None, deadline: float,
               what: str) -> qtm.Packet:
        """Send ``command`` (if any) and return the next non-data packet. Raises
        MocapConnectError on timeout or a closed connection, QtmDecodeError on junk."""
        if command is not None:
            sock.sendall(qtm.encode_command(command))
        while True:
            while self._backlog:
                p = self._backlog.pop(0)
                if p.kind == qtm.PacketType.EVENT:
                    with contextlib.suppress(qtm.QtmDecodeError):
                        self.last_event = qtm.decode_event(p.body)
                elif p.kind not in (qtm.PacketType.DATA, qtm.PacketType.NO_MORE_DATA):
                    return p
            left = deadline - time.monotonic()
            if left <= 0.0:
                raise MocapConnectError(self.config.name, f"no answer to {what} within "
                                        f"{self.config.connect_timeout_s} s")
            sock.settimeout(left)
            try:
                chunk = sock.recv(65536)
            except TimeoutError:
                continue
            if not chunk:
                raise MocapConnectError(self.config.name, f"server closed the connection "
                                        f"(waiting for the answer to {what})")
            self._backlog = self._parser.feed(chunk)

    def _read_parameters(self, sock: socket.socket, deadline: float) -> None:
        cfg = self.config
        answer = self._await(sock, "GetParameters 6D", deadline, "GetParameters 6D")
        if answer.kind != qtm.PacketType.XML:
            raise MocapConnectError(cfg.name, f"GetParameters 6D refused: "
                                    f"{qtm.decode_text(answer.body)}")
        names = qtm.decode_6d_body_names(qtm.decode_text(answer.body))
        with self._cond:
            self._names = names
        if cfg.body:
            if cfg.body not in names:
                raise UnknownBodyError(cfg.name, f"no 6DOF body named {cfg.body!r}; QTM "
                                       f"defines {list(names) or 'none'}")
            self._index = names.index(cfg.body)
        elif names:
            self._index = 0
        else:
            raise UnknownBodyError(cfg.name, "QTM defines no 6DOF body")

    # ------------------------------------------------------------------ receive

    def _run(self) -> None:
        while not self._stop.is_set():
            if self._sock is None:
                try:
                    self._connect()
                    self.reconnects += 1
                except (MocapConnectError, UnknownBodyError) as exc:
                    log.debug("%s", exc)
                    self._stop.wait(0.5)
                continue
            sel = selectors.DefaultSelector()
            try:
                sel.register(self._sock, selectors.EVENT_READ)
                if self._udp is not None:
                    sel.register(self._udp, selectors.EVENT_READ)
                self._receive(sel)
            finally:
                sel.close()

    def _receive(self, sel: selectors.BaseSelector) -> None:
        """Serve the current connection until it breaks or ``close()``."""
        while not self._stop.is_set():
            for key, _ in sel.select(timeout=0.1):
                sock = key.fileobj
                assert isinstance(sock, socket.socket)
                if sock is self._udp:
                    for _ in range(64):  # drain a burst, then check stop again
                        try:
                            data, addr = sock.recvfrom(65536)
                        except (BlockingIOError, InterruptedError):
                            break
                        except OSError:
                            return
                        self.feed_datagram(data, addr)
                    continue
                try:
                    chunk = sock.recv(65536)
                except (TimeoutError, BlockingIOError):
                    continue
                except OSError:
                    chunk = b""
                if not chunk or not self.feed_stream(chunk):
                    self._reset()
                    return

    def feed_stream(self, chunk: bytes, rx_t_ns: int | None = None) -> bool:
        """Handle bytes received on the TCP connection at ``rx_t_ns`` (None: now; in process:
        fuzzing, replay, tests). False when the stream is corrupt: it is counted and the
        parser starts over (the connection must be re-opened). Never raises for any content."""
        try:
            packets = self._parser.feed(chunk)
        except qtm.QtmDecodeError as exc:
            self.monitor.count_malformed()
            log.warning("%s: stream corrupt (%s); reconnecting", self.config.name, exc)
            self._parser = qtm.QtmStreamParser()
            return False
        rx = self._clock() if rx_t_ns is None else rx_t_ns
        for p in packets:
            self._on_packet(p, rx)
        return True

    def feed_datagram(self, data: bytes, addr: tuple[str, int], rx_t_ns: int | None = None
                      ) -> None:
        """Handle one UDP datagram as if it had arrived from ``addr`` at ``rx_t_ns`` (None:
        now). Never raises."""
        if addr[0] != self._server_ip:
            self.monitor.count_foreign()
            return
        rx = self._clock() if rx_t_ns is None else rx_t_ns
        try:
            packet = qtm.decode_packet(data)
        except qtm.QtmDecodeError:
            self.monitor.count_malformed()
            return
        self._on_packet(packet, rx)

    def _on_packet(self, p: qtm.Packet, rx_t_ns: int) -> None:
        """Apply one packet. Never raises for any content."""
        if p.kind == qtm.PacketType.DATA:
            try:
                frame = qtm.decode_data(p.body)
            except qtm.QtmDecodeError as exc:
                self.monitor.count_malformed()
                log.debug("%s: dropped malformed data packet: %s", self.config.name, exc)
                return
            self._on_frame(frame, rx_t_ns)
        elif p.kind == qtm.PacketType.EVENT:
            try:
                event = qtm.decode_event(p.body)
            except qtm.QtmDecodeError:
                self.monitor.count_malformed()
                return
            self.last_event = event
            if event == qtm.Event.QTM_SHUTTING_DOWN:
                log.warning("%s: QTM is shutting down", self.config.name)
            elif event == qtm.Event.CAMERA_SETTINGS_CHANGED and self._sock is not None:
                with contextlib.suppress(OSError):
                    self._sock.sendall(qtm.encode_command("GetParameters 6D"))
        elif p.kind == qtm.PacketType.XML:
            self._on_parameters(qtm.decode_text(p.body))
        elif p.kind == qtm.PacketType.ERROR:
            text = qtm.decode_text(p.body)
            self.server_errors = [*self.server_errors, text][-10:]
            log.warning("%s: QTM error: %s", self.config.name, text)

    def _on_parameters(self, xml_text: str) -> None:
        try:
            names = qtm.decode_6d_body_names(xml_text)
        except qtm.QtmDecodeError:
            self.monitor.count_malformed()
            return
        with self._cond:
            self._names = names
            if self.config.body:
                self._index = names.index(self.config.body) if self.config.body in names \
                    else None
            else:
                self._index = 0 if names else None

    def _on_frame(self, frame: qtm.DataFrame, rx: int) -> None:
        cfg = self.config
        comp = frame.six_dof()
        if comp is None:
            self.monitor.count_malformed()  # we asked for a 6D component
            return
        sync = self.server_clock
        t_ns = sync.update(frame.timestamp_us * 1000, rx) - round(cfg.latency_s * 1e9)
        self.monitor.set_server_clock(sync.offset_ns * 1e-9, sync.drift_ppm
                                      if sync.rate_known else math.nan, sync.drift_sigma_ppm)
        lat = (rx - t_ns) * 1e-9
        if not cfg.limits.latency_ok(lat):
            self.monitor.count_implausible()
            return
        index = self._index
        name = cfg.body or (self._names[0] if self._names else "")
        status, pos, q, residual_m = TrackingStatus.MISSING, NAN3, NAN4, math.nan
        if index is not None and index < len(comp.bodies):
            body = comp.bodies[index]
            if not body.tracked:
                status = TrackingStatus.INVALID
            else:
                converted = self._to_world(body)
                if converted is None:
                    self.monitor.count_implausible()
                    return
                status, (pos, q) = TrackingStatus.OK, converted
                residual_m = body.residual_mm * 1e-3  # NaN unless a residual component
        sample = PoseSample(t_ns, rx, frame.frame_number, -1 if index is None else index, name,
                            status, pos, q, lat, residual_m)
        self.monitor.on_frame(frame.frame_number, rx, lat)
        self.monitor.on_sample(sample)
        with self._cond:
            self._latest = sample
            self._frames_seen += 1
            self._cond.notify_all()

    def _to_world(self, body: qtm.SixDofBody) -> tuple[tuple[float, float, float],
                                                       tuple[float, float, float, float]] | None:
        """World pose of a tracked body; None if it is not a pose (see module docstring)."""
        limits = self.config.limits
        if body.rot is not None:
            q = qtm.matrix_to_quat(body.rot)
            n = math.sqrt(sum(c * c for c in q))
            if not n > 0.5 or not math.isfinite(n):
                return None
            q = (q[0] / n, q[1] / n, q[2] / n, q[3] / n)
            rebuilt = qtm.quat_to_matrix(q)
            if not max(abs(a - b) for a, b in zip(rebuilt, body.rot, strict=True)) \
                    <= limits.max_quat_norm_error:
                return None  # not a rotation matrix (also catches NaN)
        elif body.euler_deg is not None:
            if not all(math.isfinite(a) for a in body.euler_deg):
                return None
            q = qtm.euler_to_quat(body.euler_deg)
        else:
            return None
        try:
            pos, q_wb = self._transform.to_world(body.pos_mm, q)
        except ValueError:
            return None
        if not limits.position_ok(pos):
            return None
        return pos, q_wb

    # ------------------------------------------------------------------ PoseSource

    def latest(self) -> PoseSample | None:
        """The configured body in the newest frame (None before the first frame)."""
        return self._latest

    # ------------------------------------------------------------------ info

    def bodies(self) -> list[str]:
        """6DOF body names QTM defines, in index order."""
        with self._cond:
            return list(self._names)

    @property
    def body_index(self) -> int | None:
        return self._index

    @property
    def udp_address(self) -> tuple[str, int] | None:
        """Where UDP frames arrive (with ``udp``), else None."""
        if self._udp is None:
            return None
        host, port = self._udp.getsockname()
        return (str(host), int(port))


__all__ = ["QtmClient", "QtmConfig"]

"""VRPN tracker client device: one sensor of one named tracker as a PoseSource.

Wire protocol: see :mod:`drivers.mocap.vrpn` (VRPN 07.x over TCP, big-endian).

Connection (``handshake``, URI option ``handshake=auto|classic|tcp``):

- ``classic``: the VRPN way. The client listens on an ephemeral TCP port of its address on
  the route to the server, and lobs the UDP datagram ``"<that ip> <that port>\\0"`` to the
  server's port (3883), again every ``LOB_PERIOD_S`` (UDP may be lost); the server connects
  back over TCP. Only a call-back from the server's address is accepted.
- ``tcp``: a direct TCP connection to ``host:port`` (servers that accept one, such as the
  mainline VRPN server; useful when a firewall blocks the call-back).
- ``auto`` (default): classic for ``lob_timeout_s`` (1 s), then direct TCP for the rest of
  ``connect_timeout_s`` (3 s). A classic server answers in milliseconds; a server that only
  accepts direct TCP costs one ``lob_timeout_s`` per connection.

On the connection both sides write their cookie (major version 07 must match); the client
describes its own message types, then waits up to ``connect_timeout_s`` for the server to
announce the configured tracker (sender) name: a tracker the server does not announce raises
:class:`~drivers.mocap.pose.UnknownBodyError` listing the names it does. The receive thread then
maps the server's sender/type descriptions to names and turns every ``vrpn_Tracker Pos_Quat``
report of the configured tracker and sensor into a world-frame
:class:`~drivers.mocap.pose.PoseSample`. The client describes no UDP channel, so the server
sends everything over the TCP connection.

A stream that does not decode (impossible length, bad cookie) is counted as malformed and the
connection is re-opened; a report with a short payload is counted and dropped.

VRPN carries no frame number, no latency and no validity flag. Hence:

- ``frame_number`` counts reports (no dropped-frame count is possible);
- ``t_ns`` = the report's server timestamp (absolute, on the server's own clock) mapped onto
  the injected clock by :class:`drivers.clock_sync.ClockSync` (offset and drift, on the
  earliest arrivals; never later than the arrival), minus the configured ``latency_s``: the
  smallest latency of the MoCap chain, measured once in the lab, which one-way stamps cannot
  see; ``latency_s`` of a sample is arrival minus ``t_ns``;
- a body the server stops reporting (occluded) becomes a ``MISSING`` sample once its newest
  report is older than ``stale_after_s``: the stale pose is never returned as current.

A report with an all-zero quaternion is a body the server lost (``INVALID``); any other report
whose stamp gives a latency outside 0..1 s, or that is non-finite, farther than
``limits.max_range_m`` (100 m) from the world origin or has a quaternion far from unit norm is
dropped and counted
(``stats().implausible_samples``; :class:`~drivers.mocap.pose.PoseLimits`), never handed out.
:meth:`VrpnClient.feed_stream` runs the receive path on bytes in process (fuzzing, replay).

Default axes are Z-up metres (Vicon Tracker, QTM); set ``frames.up_axis: y`` for Motive's
default Y-up export.
"""

from __future__ import annotations

import contextlib
import logging
import math
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal

from config.schema import ConfigValueError
from drivers.clock_sync import ClockSync
from drivers.mocap import vrpn
from drivers.mocap.frames import FrameConfig, FrameTransform
from drivers.mocap.pose import (
    NAN3,
    NAN4,
    FrameWaits,
    MocapConnectError,
    MocapError,
    PoseLimits,
    PoseSample,
    StreamMonitor,
    TrackingStatus,
    UnknownBodyError,
)

log = logging.getLogger(__name__)

Handshake = Literal["auto", "classic", "tcp"]
HANDSHAKES: tuple[Handshake, ...] = ("auto", "classic", "tcp")
#: The classic connection request is repeated this often until the server calls back.
LOB_PERIOD_S = 0.5


@dataclass(frozen=True)
class VrpnConfig:
    """Which VRPN tracker to read. Loadable from YAML (``config.schema``)."""

    tracker: str = "Tracker0"
    host: str = "127.0.0.1"
    port: int = vrpn.DEFAULT_PORT
    sensor: int = 0
    latency_s: float = 0.0
    stale_after_s: float = 0.05
    connect_timeout_s: float = 3.0
    handshake: Handshake = "auto"
    lob_timeout_s: float = 1.0  # auto: wait this long (at most connect_timeout_s) for the
    # call-back, then connect over TCP directly
    frames: FrameConfig = field(default_factory=lambda: FrameConfig(up_axis="z"))
    limits: PoseLimits = field(default_factory=PoseLimits)

    def __post_init__(self) -> None:
        if not self.latency_s <= self.limits.max_latency_s:
            raise ConfigValueError("latency_s", f"must be <= {self.limits.max_latency_s} s")
        if not self.tracker:
            raise ConfigValueError("tracker", "must name the tracker (e.g. Tracker0)")
        if not 1 <= self.port <= 65535:
            raise ConfigValueError("port", "must be a TCP port (1..65535)")
        if self.sensor < 0:
            raise ConfigValueError("sensor", "must be >= 0")
        if not self.latency_s >= 0.0 or not self.stale_after_s > 0.0:
            raise ConfigValueError("stale_after_s", "latency must be >= 0 and staleness > 0")
        if self.handshake not in HANDSHAKES:
            raise ConfigValueError("handshake", f"must be one of {', '.join(HANDSHAKES)}, not "
                                   f"{self.handshake!r}")
        if not self.lob_timeout_s > 0.0 or not self.connect_timeout_s > 0.0:
            raise ConfigValueError("lob_timeout_s", "timeouts must be > 0")

    @property
    def name(self) -> str:
        return f"vrpn://{self.tracker}@{self.host}:{self.port}"


class VrpnClient(FrameWaits):
    """A :class:`~drivers.mocap.pose.PoseSource` reading one sensor of a VRPN tracker."""

    def __init__(self, config: VrpnConfig, clock: Callable[[], int] = time.monotonic_ns
                 ) -> None:
        self.config = config
        self._clock = clock
        self._transform = FrameTransform(config.frames)
        self.monitor = StreamMonitor(clock)
        self.server_clock = ClockSync()  # the report stamps' clock -> ours
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._sock: socket.socket | None = None
        self._parser = vrpn.VrpnStreamParser()
        self._senders: dict[int, str] = {}
        self._types: dict[int, str] = {}
        self._latest: PoseSample | None = None
        self._frames_seen = 0
        self.reconnects = 0

    def __enter__(self) -> VrpnClient:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def start(self) -> None:
        """Connect and exchange cookies (raises MocapConnectError), then start receiving."""
        self._connect()
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="vrpn-rx", daemon=True)
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
        self._thread = None
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    def _connect(self) -> None:
        cfg = self.config
        deadline = time.monotonic() + cfg.connect_timeout_s
        sock = self._open_connection(deadline)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        try:
            sock.sendall(vrpn.encode_cookie() + vrpn.encode_description(
                vrpn.SystemType.TYPE_DESCRIPTION, 0, vrpn.POS_QUAT_TYPE))
            self._parser = vrpn.VrpnStreamParser()
            with self._cond:
                self._senders, self._types = {}, {}
            # The server describes its senders once it has our cookie: wait for the
            # configured tracker among them.
            deadline = time.monotonic() + cfg.connect_timeout_s
            while not self._parser.peer_version or cfg.tracker not in self._senders.values():
                left = deadline - time.monotonic()
                if left <= 0.0:
                    if not self._parser.peer_version:
                        raise MocapConnectError(cfg.name, "no VRPN cookie from the server")
                    raise UnknownBodyError(
                        cfg.name, f"the server announces no tracker named {cfg.tracker!r} "
                        f"within {cfg.connect_timeout_s:g} s; it announces "
                        f"{', '.join(self.trackers()) or 'none'}")
                sock.settimeout(left)
                try:
                    chunk = sock.recv(4096)
                except TimeoutError:
                    continue  # the deadline check above names what is missing
                if not chunk:
                    raise MocapConnectError(cfg.name, "server closed the connection")
                self._handle(self._parser.feed(chunk))
        except vrpn.VrpnDecodeError as exc:
            sock.close()
            raise MocapConnectError(cfg.name, f"not a VRPN server: {exc}") from exc
        except OSError as exc:
            sock.close()
            raise MocapConnectError(cfg.name, f"handshake failed: {exc}") from exc
        except MocapError:
            sock.close()
            raise
        sock.settimeout(0.1)
        self._sock = sock

    def _open_connection(self, deadline: float) -> socket.socket:
        """A TCP connection to the server, by the configured handshake (module docstring)."""
        cfg = self.config
        classic_error = ""
        if cfg.handshake != "tcp":
            window_s = cfg.connect_timeout_s if cfg.handshake == "classic" \
                else min(cfg.lob_timeout_s, deadline - time.monotonic())
            try:
                return self._call_me_back(time.monotonic() + window_s)
            except TimeoutError:
                classic_error = f"no call-back to the UDP connection request within " \
                    f"{window_s:.1f} s"
            except OSError as exc:
                classic_error = f"UDP connection request failed ({exc})"
            if cfg.handshake == "classic":
                raise MocapConnectError(cfg.name, f"{classic_error}; is a VRPN server "
                                        "running there?")
            log.info("%s: %s; trying direct TCP", cfg.name, classic_error)
        try:
            return socket.create_connection((cfg.host, cfg.port),
                                            timeout=max(0.1, deadline - time.monotonic()))
        except OSError as exc:
            tried = f"{classic_error}; direct TCP: " if classic_error else ""
            raise MocapConnectError(cfg.name, f"cannot connect: {tried}{exc}") from exc

    def _call_me_back(self, deadline: float) -> socket.socket:
        """The classic handshake: listen, lob ``"<ip> <port>\\0"`` to the server's UDP port,
        accept the server's call-back. Raises OSError (TimeoutError when it never calls)."""
        cfg = self.config
        server_ip = socket.gethostbyname(cfg.host)
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as udp, \
                socket.socket(socket.AF_INET, socket.SOCK_STREAM) as listener:
            udp.connect((server_ip, cfg.port))  # no packet: picks our address on the route
            local_ip = udp.getsockname()[0]
            listener.bind((local_ip, 0))
            listener.listen(1)
            lob = vrpn.encode_lob(local_ip, listener.getsockname()[1])
            next_lob = 0.0
            while True:
                now = time.monotonic()
                if now >= deadline:
                    raise TimeoutError("the server did not call back")
                if now >= next_lob:
                    with contextlib.suppress(ConnectionRefusedError):  # ICMP of an earlier lob
                        udp.send(lob)
                    next_lob = now + LOB_PERIOD_S
                listener.settimeout(max(1e-3, min(deadline, next_lob) - now))
                try:
                    conn, peer = listener.accept()
                except TimeoutError:
                    continue
                if peer[0] == server_ip:
                    conn.settimeout(None)
                    return conn
                log.warning("%s: refused a call-back from %s", cfg.name, peer[0])
                conn.close()

    def _run(self) -> None:
        while not self._stop.is_set():
            sock = self._sock
            if sock is None:
                try:
                    self._connect()
                    self.reconnects += 1
                except MocapError as exc:
                    log.debug("%s", exc)
                    self._stop.wait(0.5)
                continue
            try:
                chunk = sock.recv(65536)
            except TimeoutError:
                continue
            except OSError:
                chunk = b""
            if not chunk:
                self._reset()
                continue
            if not self.feed_stream(chunk):
                self._reset()

    def feed_stream(self, chunk: bytes) -> bool:
        """Handle bytes received on the connection (in process: fuzzing, replay, tests).
        False when the stream is corrupt: it is counted and the parser starts over (the
        connection must be re-opened). Never raises for any content."""
        try:
            msgs = self._parser.feed(chunk)
        except vrpn.VrpnDecodeError as exc:
            self.monitor.count_malformed()
            log.warning("%s: stream corrupt (%s); reconnecting", self.config.name, exc)
            self._parser = vrpn.VrpnStreamParser()
            return False
        self._handle(msgs)
        return True

    def _reset(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    def _handle(self, msgs: list[vrpn.VrpnMessage]) -> None:
        """Apply decoded messages. Never raises for any content."""
        for m in msgs:
            if m.type_id in (vrpn.SystemType.SENDER_DESCRIPTION,
                             vrpn.SystemType.TYPE_DESCRIPTION):
                try:
                    name = vrpn.decode_description(m.payload)
                except vrpn.VrpnDecodeError:
                    self.monitor.count_malformed()
                    continue
                table = self._senders if m.type_id == vrpn.SystemType.SENDER_DESCRIPTION \
                    else self._types
                with self._cond:
                    table[m.sender_id] = name
                continue
            if self._types.get(m.type_id) != vrpn.POS_QUAT_TYPE:
                continue
            if self._senders.get(m.sender_id) != self.config.tracker:
                continue
            try:
                report = vrpn.decode_pos_quat(m.payload)
            except vrpn.VrpnDecodeError:
                self.monitor.count_malformed()
                continue
            if report.sensor == self.config.sensor:
                self._on_report(report, m.tv_sec * 1_000_000_000 + m.tv_usec * 1000)

    def _on_report(self, report: vrpn.TrackerPose, server_t_ns: int | None = None) -> None:
        rx = self._clock()
        if server_t_ns is None:
            t_ns = rx - round(self.config.latency_s * 1e9)
        else:
            sync = self.server_clock
            t_ns = sync.update(server_t_ns, rx) - round(self.config.latency_s * 1e9)
            self.monitor.set_server_clock(sync.offset_ns * 1e-9, sync.drift_ppm
                                          if sync.rate_known else math.nan,
                                          sync.drift_sigma_ppm)
        lat = (rx - t_ns) * 1e-9
        limits = self.config.limits
        if not limits.latency_ok(lat):
            # A report stamp that puts the capture more than a second before its arrival (or
            # after it) is a broken stamp: so would be the sample time.
            self.monitor.count_implausible()
            return
        status = TrackingStatus.OK
        pos, q = NAN3, NAN4
        if report.q_xyzw == (0.0, 0.0, 0.0, 0.0):
            status = TrackingStatus.INVALID  # how some servers report a body they lost
        else:
            pose = limits.world_pose(self._transform, report.pos, report.q_xyzw)
            if pose is None:
                # VRPN has no validity flag: a pose no body can have is a broken report.
                self.monitor.count_implausible()
                return
            pos, q = pose
        self._frames_seen += 1
        self.monitor.on_frame(None, rx, lat)
        sample = PoseSample(t_ns, rx, self._frames_seen, report.sensor, self.config.tracker,
                            status, pos, q, lat, math.nan)
        self.monitor.on_sample(sample)
        with self._cond:
            self._latest = sample
            self._cond.notify_all()

    # ------------------------------------------------------------------ PoseSource

    def latest(self) -> PoseSample | None:
        s = self._latest
        if s is None or not s.valid:
            return s
        now = self._clock()
        if (now - s.rx_t_ns) * 1e-9 > self.config.stale_after_s:
            return s.as_missing()
        return s


    def trackers(self) -> list[str]:
        """Sender (tracker) names the server has announced."""
        with self._cond:
            return sorted(set(self._senders.values()))


__all__ = ["VrpnClient", "VrpnConfig"]

"""NatNet client device: handshake, receive thread, latest-pose mailbox, stream health.

Wire protocol: see :mod:`drivers.mocap.natnet` (UDP, little-endian, bitstream 3.0-4.1).

Connection sequence (``start()``, blocking, before the thread runs):

1. a UDP command socket bound to ``(local_ip, 0)`` sends CONNECT to ``server_ip:command_port``
   (1510) and waits for SERVERINFO (retrying every 0.25 s until ``connect_timeout_s``); the
   NatNet version and the high-resolution clock frequency come from there;
2. optionally ``Bitstream,x.y`` (unicast only) to select the bitstream version, then CONNECT
   again: the version is the one the new SERVERINFO states, never the one asked for (a server
   may answer the command with success and go on streaming its own). A request the server
   refuses or does not confirm is a warning and the server's version is read, or, with
   ``require_version``, a :class:`MocapConnectError` naming both versions. Frames that arrive
   before the version is settled are ignored;
3. REQUEST_MODELDEF: rigid-body names -> ids; an unknown configured body raises
   :class:`UnknownBodyError` listing the names the server has.

Data: in unicast mode the server sends frames to the command socket (the address that sent
CONNECT/KEEPALIVE) and the client repeats KEEPALIVE every ``keepalive_period_s``; in multicast
mode a data socket bound to ``("", data_port)`` (not to the interface address: on Linux that
receives nothing) joins ``multicast_group`` on ``local_ip``.

Only datagrams whose source address is ``server_ip`` are accepted (others are counted as
foreign); datagrams that do not decode are counted as malformed and dropped. When a frame says
the models changed, MODELDEF is requested again.

Timestamps: the server's transmit stamps (HighResClockFrequency ticks) are mapped onto the
injected clock by :class:`drivers.clock_sync.ClockSync` (offset and rate error of the server's
clock, on the earliest arrivals); a sample's ``t_ns`` is its mapped mid-exposure stamp minus the
configured network delay (the smallest delay, which one-way stamps cannot see), never later
than its arrival; ``latency_s`` is arrival minus ``t_ns``. Without stamps (a zero clock
frequency) ``t_ns`` is the arrival minus the configured network delay.

Plausibility (:class:`~drivers.mocap.pose.PoseLimits`, ``limits``): a frame whose reported
latency is outside 0..1 s is dropped whole; a tracked pose that is non-finite, farther than
``max_range_m`` (100 m) from the world origin or has a wire quaternion far from unit norm is
dropped. Both are counted (``stats().implausible_samples``) and the previous sample stays the
latest. :meth:`NatNetClient.feed_datagram` runs the receive path in process (fuzzing, replay).
"""

from __future__ import annotations

import contextlib
import errno
import logging
import math
import selectors
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal

from config.schema import ConfigValueError
from drivers.clock_sync import ClockSync
from drivers.mocap import natnet
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
class NatNetConfig:
    """Where the NatNet server is and how to read it. Loadable from YAML (``config.schema``)."""

    server_ip: str = "127.0.0.1"
    local_ip: str = "127.0.0.1"
    mode: Literal["unicast", "multicast"] = "unicast"
    command_port: int = natnet.DEFAULT_COMMAND_PORT
    data_port: int = natnet.DEFAULT_DATA_PORT
    multicast_group: str = natnet.DEFAULT_MULTICAST_GROUP
    body: str = ""  # rigid-body name; empty: the first one the server defines
    version: str = ""  # requested bitstream version ("3.1"); empty: the server's
    require_version: bool = False  # a requested version the server does not confirm: fail
    network_delay_s: float = 0.0
    keepalive_period_s: float = 1.0
    connect_timeout_s: float = 3.0
    frames: FrameConfig = field(default_factory=FrameConfig)
    limits: PoseLimits = field(default_factory=PoseLimits)

    def __post_init__(self) -> None:
        if self.mode not in ("unicast", "multicast"):
            raise ConfigValueError("mode", f"must be 'unicast' or 'multicast', not {self.mode!r}")
        for key in ("command_port", "data_port"):
            if not 0 <= getattr(self, key) <= 65535:
                raise ConfigValueError(key, "must be a UDP port (0..65535)")
        for key in ("server_ip", "local_ip", "multicast_group"):
            try:
                socket.inet_aton(getattr(self, key))
            except OSError as exc:
                raise ConfigValueError(key, "must be an IPv4 address") from exc
        if self.version:
            try:
                natnet.parse_version(self.version)
            except ValueError as exc:
                raise ConfigValueError("version", str(exc)) from exc
        if not self.network_delay_s >= 0.0:
            raise ConfigValueError("network_delay_s", "must be >= 0")
        if not self.keepalive_period_s > 0.0 or not self.connect_timeout_s > 0.0:
            raise ConfigValueError("keepalive_period_s", "periods must be > 0")

    @property
    def name(self) -> str:
        return f"natnet://{self.server_ip}:{self.command_port}"


class NatNetClient(FrameWaits):
    """A :class:`~drivers.mocap.pose.PoseSource` reading one OptiTrack NatNet server.

    ``with NatNetClient(cfg) as c: c.latest()``. ``clock`` returns nanoseconds (the
    ground-station clock; ``time.monotonic_ns`` by default).
    """

    def __init__(self, config: NatNetConfig, clock: Callable[[], int] = time.monotonic_ns
                 ) -> None:
        self.config = config
        self._clock = clock
        self._transform = FrameTransform(config.frames)
        self.monitor = StreamMonitor(clock)
        self._waiting = WaitingSockets()  # poll(): is anything there at all
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._cmd: socket.socket | None = None
        self._data: socket.socket | None = None
        self._server_info: natnet.ServerInfo | None = None
        self._unsupported: natnet.NatNetVersion | None = None
        self._version: natnet.NatNetVersion | None = None
        self._models: natnet.ModelDefinitions | None = None
        self._names_by_id: dict[int, str] = {}
        self._body_id: int | None = None
        self._latest: PoseSample | None = None
        self._last_frame_times: tuple[int, int, float] = (0, 0, math.nan)
        self._last_frame: natnet.FrameOfData | None = None
        self.server_clock = ClockSync()  # the server's high-resolution clock -> ours
        self._response: natnet.Response | natnet.UnrecognizedRequest | None = None
        self._frames_seen = 0
        self._next_keepalive = 0.0
        self._handshaking = False  # frames are ignored until the version is settled
        #: receive(): datagrams taken off the sockets, not yet handled (data, sender, arrival)
        self._received: list[tuple[bytes, tuple[str, int], int]] = []

    # ------------------------------------------------------------------ lifecycle

    def __enter__(self) -> NatNetClient:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def start(self, receive_thread: bool = True) -> None:
        """Open sockets, handshake, resolve the body, start the receive thread.

        With ``receive_thread=False`` nothing receives in the background: the owner calls
        :meth:`poll` (a lockstep loop does, so that it sees exactly the datagrams that arrived
        before its IMU sample, whatever the thread scheduling)."""
        cfg = self.config
        try:
            self._cmd = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            self._cmd.bind((cfg.local_ip, 0))
            if cfg.mode == "multicast":
                self._data = _open_multicast(cfg)
        except OSError as exc:
            self.close()
            if exc.errno == errno.EADDRNOTAVAIL:  # the usual cause: a wrong local= address
                raise MocapConnectError(cfg.name, f"local address {cfg.local_ip} is not an "
                                        "address of this host (the URI's local= option; "
                                        "`ip -br addr` lists them)") from exc
            raise MocapConnectError(cfg.name, f"cannot open sockets: {exc}") from exc
        self._handshaking = True
        try:
            self._handshake()
        except BaseException:
            self.close()
            raise
        finally:
            self._handshaking = False
        self._stop.clear()
        for sock in (self._cmd, self._data):
            if sock is not None:
                sock.setblocking(False)
        self._next_keepalive = time.monotonic()
        if receive_thread:
            self._thread = threading.Thread(target=self._run, name="natnet-rx", daemon=True)
            self._thread.start()

    def poll(self) -> int:
        """Receive and handle every datagram already waiting, in the caller's thread; never
        blocks. Returns the number of datagrams handled. Also sends the unicast keep-alive
        when due. (:meth:`receive`, then :meth:`handle_received`.)"""
        received = self.receive()
        self.handle_received()
        return received

    def receive(self) -> int:
        """Take every datagram already waiting off the sockets, each with its arrival time,
        without decoding it (:meth:`handle_received` does); the caller's thread, never blocks.
        Returns how many. Also sends the unicast keep-alive when due.

        A lockstep loop takes them as its IMU sample arrives (what came before the sample is
        what it sees, whatever the thread scheduling) and handles them once its motor command
        is out."""
        if self.config.mode == "unicast":
            now = time.monotonic()
            if now >= self._next_keepalive:
                self._send(natnet.encode_keepalive())
                self._next_keepalive = now + self.config.keepalive_period_s
        socks = (self._cmd, self._data)
        if not self._waiting.any(socks):
            return 0
        received = 0
        for sock in socks:
            while sock is not None:
                try:
                    data, addr = sock.recvfrom(65536)
                except (BlockingIOError, InterruptedError):
                    break
                except OSError:
                    return received
                self._received.append((data, addr, self._clock()))
                received += 1
        return received

    def handle_received(self) -> int:
        """Decode and file the datagrams :meth:`receive` took, in arrival order; how many."""
        todo, self._received = self._received, []
        for data, addr, rx_t_ns in todo:
            self._on_datagram(data, addr, rx_t_ns)
        return len(todo)

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=5.0)
        self._thread = None
        for s in (self._cmd, self._data):
            if s is not None:
                with contextlib.suppress(OSError):
                    if s is self._cmd and self._server_info is not None:
                        s.sendto(natnet.encode_disconnect(), self._server)
                    s.close()
        self._cmd = self._data = None

    @property
    def _server(self) -> tuple[str, int]:
        return (self.config.server_ip, self.config.command_port)

    def _send(self, data: bytes) -> None:
        if self._cmd is not None:
            with contextlib.suppress(OSError):
                self._cmd.sendto(data, self._server)

    def _pump_until(self, done: Callable[[], bool], timeout_s: float,
                    resend: bytes | None) -> bool:
        """Receive on the command socket (handshake phase) until ``done()`` or timeout."""
        assert self._cmd is not None
        deadline = time.monotonic() + timeout_s
        next_send = 0.0
        while not done():
            now = time.monotonic()
            if now >= deadline:
                return False
            if resend is not None and now >= next_send:
                self._send(resend)
                next_send = now + 0.25
            self._cmd.settimeout(max(1e-3, min(deadline, next_send) - now))
            try:
                data, addr = self._cmd.recvfrom(65536)
            except (TimeoutError, BlockingIOError):
                continue
            except OSError:
                return False
            self._on_datagram(data, addr)
        return True

    def _handshake(self) -> None:
        cfg = self.config
        if not self._pump_until(
                lambda: self._server_info is not None or self._unsupported is not None,
                cfg.connect_timeout_s, natnet.encode_connect("ping")):
            raise MocapConnectError(cfg.name, f"no SERVERINFO within {cfg.connect_timeout_s} s "
                                    "(server not running, wrong address or port?)")
        if self._server_info is None:
            raise MocapConnectError(cfg.name, f"server speaks NatNet {self._unsupported}; "
                                    f"supported: {natnet.SUPPORTED_VERSIONS}")
        if cfg.version and natnet.parse_version(cfg.version) != self._version:
            self._request_version(natnet.parse_version(cfg.version))
        self._models = None
        if not self._pump_until(lambda: self._models is not None, cfg.connect_timeout_s,
                                natnet.encode_request_modeldef()):
            raise MocapConnectError(cfg.name, "no MODELDEF answer")
        self._resolve_body()

    def _request_version(self, wanted: natnet.NatNetVersion) -> None:
        """Ask for bitstream ``wanted``; settle on the version the server then states."""
        cfg = self.config
        problem = ""
        if cfg.mode != "unicast":
            problem = "the bitstream version can only be changed in unicast mode"
        else:
            self._response = None
            command = natnet.encode_command(f"Bitstream,{wanted[0]}.{wanted[1]}")
            if not self._pump_until(lambda: self._response is not None, cfg.connect_timeout_s,
                                    command):
                problem = "no answer to the Bitstream command"
            elif not isinstance(self._response, natnet.Response) or self._response.code != 0:
                problem = "the server refused the Bitstream command"
            else:
                with self._cond:
                    self._server_info = None  # the next SERVERINFO sets the version
                if not self._pump_until(lambda: self._server_info is not None,
                                        cfg.connect_timeout_s, natnet.encode_connect("ping")):
                    raise MocapConnectError(cfg.name, "no SERVERINFO after the Bitstream "
                                            "command")
                if self._version != wanted:
                    problem = "the server accepted the Bitstream command but still states " \
                        "its own version"
        if not problem:
            return
        text = f"NatNet {_dotted(wanted)} was requested, the server speaks " \
            f"{_dotted(self._version)}: {problem}"
        if cfg.require_version:
            raise MocapConnectError(cfg.name, text)
        log.warning("%s: %s; reading NatNet %s", cfg.name, text, _dotted(self._version))

    def _resolve_body(self) -> None:
        assert self._models is not None
        ids = self._models.body_ids_by_name()
        if self.config.body:
            if self.config.body not in ids:
                raise UnknownBodyError(self.config.name, f"no rigid body named "
                                       f"{self.config.body!r}; the server defines "
                                       f"{sorted(ids) or 'none'}")
            self._body_id = ids[self.config.body]
        elif self._models.rigid_bodies:
            self._body_id = self._models.rigid_bodies[0].body_id

    # ------------------------------------------------------------------ receive

    def _run(self) -> None:
        sel = selectors.DefaultSelector()
        for s in (self._cmd, self._data):
            if s is not None:
                s.setblocking(False)
                sel.register(s, selectors.EVENT_READ)
        unicast = self.config.mode == "unicast"
        period = self.config.keepalive_period_s
        next_keepalive = time.monotonic()
        try:
            while not self._stop.is_set():
                now = time.monotonic()
                if unicast and now >= next_keepalive:
                    self._send(natnet.encode_keepalive())
                    next_keepalive = now + period
                for key, _ in sel.select(timeout=min(0.1, period)):
                    sock = key.fileobj
                    assert isinstance(sock, socket.socket)
                    for _ in range(64):  # drain a burst, then check stop/keepalive again
                        try:
                            data, addr = sock.recvfrom(65536)
                        except (BlockingIOError, InterruptedError):
                            break
                        except OSError:
                            return
                        self._on_datagram(data, addr)
        finally:
            sel.close()

    def feed_datagram(self, data: bytes, addr: tuple[str, int]) -> None:
        """Handle one datagram as if it had arrived from ``addr`` (in process: fuzzing, replay,
        tests). Never raises for any content."""
        self._on_datagram(data, addr)

    def _on_datagram(self, data: bytes, addr: tuple[str, int], rx_t_ns: int | None = None
                     ) -> None:
        """Handle one datagram that arrived at ``rx_t_ns`` (None: now). Never raises for any
        content."""
        if addr[0] != self.config.server_ip:
            self.monitor.count_foreign()
            return
        if rx_t_ns is None:
            rx_t_ns = self._clock()
        if self._handshaking and data[:2] == _FRAME_ID:
            return  # its version may not be settled yet
        try:
            # markers are not built: the client hands out rigid-body poses only
            msg = natnet.decode_message(data, self._version, markers=False)
        except natnet.NatNetDecodeError as exc:
            self.monitor.count_malformed()
            log.debug("%s: dropped malformed datagram: %s", self.config.name, exc)
            return
        if isinstance(msg, natnet.FrameOfData):
            self._on_frame(msg, rx_t_ns)
        elif isinstance(msg, natnet.ServerInfo):
            if msg.version not in natnet.SUPPORTED_VERSIONS:
                self._unsupported = msg.version
                log.warning("%s: server speaks NatNet %s, supported: %s", self.config.name,
                            msg.version, natnet.SUPPORTED_VERSIONS)
                return
            with self._cond:
                if self._server_info is None:
                    self._version = msg.version
                self._server_info = msg
                self._cond.notify_all()
        elif isinstance(msg, natnet.ModelDefinitions):
            with self._cond:
                self._models = msg
                self._names_by_id = {rb.body_id: rb.name for rb in msg.rigid_bodies}
                if self.config.body:
                    self._body_id = msg.body_ids_by_name().get(self.config.body, self._body_id)
                self._cond.notify_all()
        elif isinstance(msg, natnet.Response | natnet.UnrecognizedRequest):
            self._response = msg

    def _sample(self, rb: natnet.RigidBodyData | None, body_id: int, frame: int,
                rx_t_ns: int, t_ns: int, latency_s: float) -> PoseSample | None:
        """The world-frame sample of one rigid body; None if its pose is implausible."""
        name = self._names_by_id.get(body_id, "")
        if rb is None:
            return PoseSample(t_ns, rx_t_ns, frame, body_id, name, TrackingStatus.MISSING,
                              NAN3, NAN4, latency_s, math.nan)
        if not rb.tracking_valid:
            return PoseSample(t_ns, rx_t_ns, frame, body_id, name, TrackingStatus.INVALID,
                              NAN3, NAN4, latency_s, rb.mean_error_m)
        limits = self.config.limits
        pose = limits.world_pose(self._transform, rb.pos, rb.q_xyzw)
        if pose is None or not 0.0 <= rb.mean_error_m <= limits.max_range_m:
            return None
        pos, q = pose
        return PoseSample(t_ns, rx_t_ns, frame, body_id, name, TrackingStatus.OK,
                          pos, q, latency_s, rb.mean_error_m)

    def _on_frame(self, frame: natnet.FrameOfData, rx_t_ns: int) -> None:
        info = self._server_info
        clock_hz = info.high_res_clock_hz if info else 0
        latency_s = frame.latency_s(clock_hz)
        if (clock_hz > 0 and frame.transmit_ticks < frame.camera_mid_exposure_ticks) \
                or not self.config.limits.latency_ok(latency_s):
            # Sent before it was exposed, or more than a second late: the stamps are wrong,
            # so would be the capture time of every pose in it.
            self.monitor.count_implausible()
            return
        delay_ns = round(self.config.network_delay_s * 1e9)
        if clock_hz > 0:
            sync = self.server_clock
            sync.update(frame.transmit_ticks * 1_000_000_000 // clock_hz, rx_t_ns)
            t_ns = min(sync.map(frame.camera_mid_exposure_ticks * 1_000_000_000 // clock_hz),
                       rx_t_ns) - delay_ns
            self.monitor.set_server_clock(sync.offset_ns * 1e-9, sync.drift_ppm
                                          if sync.rate_known else math.nan,
                                          sync.drift_sigma_ppm)
        else:
            t_ns = rx_t_ns - round(latency_s * 1e9) - delay_ns
        latency_s = (rx_t_ns - t_ns) * 1e-9
        if not latency_s <= self.config.limits.max_latency_s + self.config.network_delay_s:
            # The synchronised server clock puts the exposure more than a second back (never
            # after the arrival, by construction): the stamps of this frame are broken.
            self.monitor.count_implausible()
            return
        bid = self._body_id
        main = None
        if bid is not None:
            # Only the configured body is converted here; others on demand (latest_of).
            rb = next((b for b in frame.rigid_bodies if b.body_id == bid), None)
            main = self._sample(rb, bid, frame.frame_number, rx_t_ns, t_ns, latency_s)
            if main is None:
                self.monitor.count_implausible()
                return
        self.monitor.on_frame(frame.frame_number, rx_t_ns, latency_s)
        if main is not None:
            self.monitor.on_sample(main)
        with self._cond:
            self._last_frame = frame
            self._last_frame_times = (rx_t_ns, t_ns, latency_s)
            self._latest = main
            self._frames_seen += 1
            self._cond.notify_all()
        if frame.models_changed:
            self._send(natnet.encode_request_modeldef())

    # ------------------------------------------------------------------ PoseSource

    def latest(self) -> PoseSample | None:
        """The configured body in the newest frame (None before the first frame)."""
        return self._latest

    def latest_of(self, name: str) -> PoseSample | None:
        """Any defined rigid body in the newest frame, by name (None if not defined, no frame
        yet, or its pose is implausible)."""
        with self._cond:
            ids = self._models.body_ids_by_name() if self._models else {}
            frame, times = self._last_frame, self._last_frame_times
        if name not in ids or frame is None:
            return None
        bid = ids[name]
        rb = next((b for b in frame.rigid_bodies if b.body_id == bid), None)
        return self._sample(rb, bid, frame.frame_number, *times)


    # ------------------------------------------------------------------ info

    @property
    def local_address(self) -> tuple[str, int] | None:
        """Address of the command socket (where unicast frames arrive)."""
        if self._cmd is None:
            return None
        host, port = self._cmd.getsockname()
        return (str(host), int(port))

    @property
    def server_info(self) -> natnet.ServerInfo | None:
        return self._server_info

    @property
    def version(self) -> natnet.NatNetVersion | None:
        return self._version

    @property
    def body_id(self) -> int | None:
        return self._body_id

    def bodies(self) -> dict[str, int]:
        """Rigid bodies the server defines: name -> id."""
        with self._cond:
            return self._models.body_ids_by_name() if self._models else {}

    @property
    def models(self) -> natnet.ModelDefinitions | None:
        return self._models


_FRAME_ID = int(natnet.MessageId.FRAMEOFDATA).to_bytes(2, "little")


def _dotted(version: natnet.NatNetVersion | None) -> str:
    return "?" if version is None else ".".join(map(str, version))


def _open_multicast(cfg: NatNetConfig) -> socket.socket:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        s.bind(("", cfg.data_port))  # not (local_ip, port): Linux would deliver nothing
        s.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP,
                     socket.inet_aton(cfg.multicast_group) + socket.inet_aton(cfg.local_ip))
    except OSError:
        s.close()
        raise
    return s

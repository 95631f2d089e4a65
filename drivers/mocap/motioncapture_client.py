"""libmotioncapture adapter: one rigid body of any system it reads, as a PoseSource.

Wire protocol: none of ours. PyPI ``motioncapture`` (IMRCLab/libmotioncapture, C++, optional
extra ``fasthex[motioncapture]``) speaks the system's own protocol with the vendor's code
compiled in: ``vicon`` (Vicon DataStream SDK, TCP 801; the only way to read Vicon's native
stream, whose SDK has no other Python binding that builds offline), ``optitrack`` (NatNet),
``qualisys`` (QTM RT) and ``vrpn`` (the mainline VRPN 07.38 client: the classic UDP request
and TCP call-back). What this module relies on from it, all it offers to Python:
``motioncapture.connect(system, options)`` (``hostname``, and ``port`` for qualisys),
``waitForNextFrame()`` (blocks in C++ with the GIL released) and ``rigidBodies`` (name ->
position (3,) in metres, rotation quaternion ``w, x, y, z``), holding the bodies updated in
that frame.

URI (see :mod:`drivers.mocap.uri`): ``motioncapture://SYSTEM?host=HOST&body=NAME&up=y|z``
``&units=m|mm&latency_ms=F&stale_ms=F&range_m=F``; ``host`` is passed as libmotioncapture's
``hostname``; ``vrpn`` and ``vicon`` take ``HOST:PORT`` there as it is (VRPN 3883, DataStream
801). ``qualisys`` takes ``HOST:PORT`` with ``PORT`` the little-endian RT port QTM listens on
(22223, as ``qtm://``): the library's ``port`` option is QTM's base port and its RT SDK
connects to base + 1, so the adapter passes ``PORT - 1`` (without a port, the library's base
22222, i.e. 22223). The qualisys backend streams frames over UDP to the fixed local port 6734:
one such reader per PC. Frames: the position and attitude are in the system's world axes;
``up`` defaults to ``z`` for vicon, qualisys and vrpn (Vicon Tracker and QTM are Z-up) and to
``y`` for optitrack (Motive's default), and the pose is converted into the ground-station
world frame by :class:`drivers.mocap.frames.FrameTransform`.

Device behaviour, as the VRPN client's (:mod:`drivers.mocap.vrpn_client`): libmotioncapture
gives no frame number, latency or validity flag to Python, so ``frame_number`` counts the
frames that held the body, ``t_ns`` is the arrival minus the configured ``latency_s``, and a
body absent from the frames for ``stale_after_s`` reads ``MISSING``. A pose that is
non-finite, out of ``limits.max_range_m`` or has a far-from-unit quaternion is dropped and
counted (``stats().implausible_samples``).

Threading: ``connect`` and ``waitForNextFrame`` run on the receive thread, never on the
caller's. ``start()`` waits up to ``connect_timeout_s`` for a frame holding the body: none
raises :class:`~drivers.mocap.pose.MocapConnectError` (no frame at all) or
:class:`~drivers.mocap.pose.UnknownBodyError` (listing the bodies seen). A C++ wait cannot be
interrupted: ``close()`` stops the thread once its current wait returns (a silent server can
keep it, a daemon, until the process ends).

Known limitation, the GIL: ``motioncapture.connect`` (the library's connect and handshake) does
not release the GIL, so while it runs every Python thread of the process stops, the caller of
``start()`` and its timeout included. Against a server that answers this is short (qualisys:
about 2 ms on loopback); against a wrong or silent host it lasts the library's own timeout, or
for ever. Measured with ``motioncapture`` 1.1: ``qualisys`` froze the process for 5.0 s before
failing (a silent port, an unreachable host), ``vrpn`` for 1.0 s (an unreachable host), and
``vicon`` (a refused port) and ``optitrack`` (a silent host) had not returned after 40 s. So
start the adapter before anything timed runs (it connects once, never again), and an emulated
server for it must run in another process. ``waitForNextFrame`` does release the GIL (a ticker
thread kept its rate while it streamed 200 Hz), so once connected the adapter starves nothing.
"""

from __future__ import annotations

import importlib
import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from config.schema import ConfigValueError
from drivers.mocap.frames import FrameConfig, FrameTransform, Quat, Vec3
from drivers.mocap.pose import (
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

#: Systems libmotioncapture reads, with the up axis of their world frame by default.
SYSTEM_UP_AXIS: dict[str, str] = {"vicon": "z", "qualisys": "z", "vrpn": "z", "optitrack": "y"}


@dataclass(frozen=True)
class MotionCaptureConfig:
    """Which system and body libmotioncapture reads. Loadable from YAML (``config.schema``)."""

    system: str = "vicon"
    host: str = "127.0.0.1"
    body: str = ""
    latency_s: float = 0.0  # the MoCap chain's latency (measured once), subtracted
    stale_after_s: float = 0.05
    connect_timeout_s: float = 5.0
    frames: FrameConfig = field(default_factory=lambda: FrameConfig(up_axis="z"))
    limits: PoseLimits = field(default_factory=PoseLimits)

    def __post_init__(self) -> None:
        if self.system not in SYSTEM_UP_AXIS:
            raise ConfigValueError("system", f"must be one of {', '.join(SYSTEM_UP_AXIS)}, "
                                   f"not {self.system!r}")
        if not self.host:
            raise ConfigValueError("host", "must name the MoCap server")
        if not self.body:
            raise ConfigValueError("body", "must name the rigid body")
        if self.system == "qualisys" and ":" in self.host:
            port = self.host.rpartition(":")[2]
            if not port.isdigit() or not 2 <= int(port) <= 65535:  # base port = PORT - 1 >= 1
                raise ConfigValueError("host", f"HOST:PORT needs a TCP port 2..65535, not "
                                       f"{port!r}")
        if not 0.0 <= self.latency_s <= self.limits.max_latency_s:
            raise ConfigValueError("latency_s", f"must be in 0..{self.limits.max_latency_s} s")
        if not self.stale_after_s > 0.0 or not self.connect_timeout_s > 0.0:
            raise ConfigValueError("stale_after_s", "staleness and timeout must be > 0")

    @property
    def name(self) -> str:
        return f"motioncapture://{self.system}?host={self.host}&body={self.body}"


class MotionCaptureClient(FrameWaits):
    """A :class:`~drivers.mocap.pose.PoseSource` reading one body through libmotioncapture.

    ``connect`` builds the library's object from ``(system, library_options(system, host))``;
    tests may pass another factory with the same interface."""

    def __init__(self, config: MotionCaptureConfig,
                 clock: Callable[[], int] = time.monotonic_ns,
                 connect: Callable[[str, dict[str, str]], Any] | None = None) -> None:
        self.config = config
        self._clock = clock
        self._connect = connect
        self._transform = FrameTransform(config.frames)
        self.monitor = StreamMonitor(clock)
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._latest: PoseSample | None = None
        self._frames_seen = 0
        self._waits = 0  # frames the library returned, with or without the body
        self._seen_bodies: set[str] = set()
        self._error: BaseException | None = None

    def __enter__(self) -> MotionCaptureClient:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def start(self) -> None:
        """Connect on the receive thread; return once a frame holds the body (see module)."""
        cfg = self.config
        connect = self._connect or _library_connect(cfg.name)
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, args=(connect,),
                                        name="motioncapture-rx", daemon=True)
        self._thread.start()
        deadline = time.monotonic() + cfg.connect_timeout_s
        with self._cond:
            while self._frames_seen == 0 and self._error is None:
                left = deadline - time.monotonic()
                if left <= 0.0:
                    break
                self._cond.wait(left)
            error, waits, seen = self._error, self._waits, sorted(self._seen_bodies)
            got = self._frames_seen > 0
        if got:
            return
        self.close()
        if error is not None:
            raise MocapConnectError(cfg.name, f"libmotioncapture: {error}") from error
        if not seen:
            raise MocapConnectError(cfg.name, f"no rigid body within {cfg.connect_timeout_s:g}"
                                    f" s ({waits} frames; server not running, wrong host?)")
        raise UnknownBodyError(cfg.name, f"no rigid body named {cfg.body!r} within "
                               f"{cfg.connect_timeout_s:g} s; the server sends "
                               f"{', '.join(seen)}")

    def close(self) -> None:
        self._stop.set()
        thread, self._thread = self._thread, None
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout=2.0)
            if thread.is_alive():
                log.warning("%s: the library is still waiting for a frame; its thread ends "
                            "with its wait", self.config.name)

    def _run(self, connect: Callable[[str, dict[str, str]], Any]) -> None:
        cfg = self.config
        try:
            mc = connect(cfg.system, library_options(cfg.system, cfg.host))
            while not self._stop.is_set():
                mc.waitForNextFrame()
                bodies = mc.rigidBodies
                rx_t_ns = self._clock()
                with self._cond:
                    self._waits += 1
                    self._seen_bodies.update(bodies)
                    self._cond.notify_all()
                rb = bodies.get(cfg.body)
                if rb is not None:
                    self.on_body(rb.position, rb.rotation, rx_t_ns)
        except Exception as exc:  # the library raises RuntimeError; the thread must not die
            log.warning("%s: libmotioncapture failed: %s", cfg.name, exc)
            with self._cond:
                self._error = exc
                self._cond.notify_all()

    def on_body(self, position_m: Any, rotation: Any, rx_t_ns: int) -> None:
        """Handle the body's pose in one frame: ``position_m`` 3 floats in the system's axes,
        ``rotation`` with ``w, x, y, z``. Never raises for any values (fuzzing, tests)."""
        try:
            pos: Vec3 = (float(position_m[0]), float(position_m[1]), float(position_m[2]))
            q_xyzw: Quat = (float(rotation.x), float(rotation.y), float(rotation.z),
                            float(rotation.w))
        except (TypeError, ValueError, IndexError, AttributeError):
            self.monitor.count_malformed()
            return
        cfg = self.config
        t_ns = rx_t_ns - round(cfg.latency_s * 1e9)
        pose = cfg.limits.world_pose(self._transform, pos, q_xyzw)
        if pose is None:
            self.monitor.count_implausible()
            return
        pos_w, q_wb = pose
        with self._cond:
            self._frames_seen += 1
            sample = PoseSample(t_ns, rx_t_ns, self._frames_seen, 0, cfg.body,
                                TrackingStatus.OK, pos_w, q_wb, cfg.latency_s, math.nan)
            self.monitor.on_frame(None, rx_t_ns, cfg.latency_s)
            self.monitor.on_sample(sample)
            self._latest = sample
            self._cond.notify_all()

    # ------------------------------------------------------------------ PoseSource

    def latest(self) -> PoseSample | None:
        s = self._latest
        if s is None:
            return None
        if (self._clock() - s.rx_t_ns) * 1e-9 > self.config.stale_after_s:
            return s.as_missing()
        return s

    def bodies(self) -> dict[str, int]:
        """Rigid bodies seen in the frames so far: name -> 0 (libmotioncapture has no ids)."""
        with self._cond:
            return dict.fromkeys(sorted(self._seen_bodies), 0)


def library_options(system: str, host: str) -> dict[str, str]:
    """libmotioncapture's connect options for ``host`` as the URI gives it (see module)."""
    if system != "qualisys":
        return {"hostname": host}
    name, sep, port = host.rpartition(":")
    if not sep:
        return {"hostname": host}
    # the library's port is QTM's base port; its RT SDK adds 1 (the little-endian port)
    return {"hostname": name, "port": str(int(port) - 1)}


def _library_connect(device: str) -> Callable[[str, dict[str, str]], Any]:
    try:
        module = importlib.import_module("motioncapture")
    except ImportError as exc:
        raise MocapError(device, "needs libmotioncapture: pip install 'fasthex[motioncapture]'"
                         ) from exc
    connect: Callable[[str, dict[str, str]], Any] = module.connect
    return connect


__all__ = ["SYSTEM_UP_AXIS", "MotionCaptureClient", "MotionCaptureConfig", "library_options"]

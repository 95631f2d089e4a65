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

Process: the library runs in a child process (:mod:`drivers.mocap.motioncapture_child`,
started with ``python -P -m`` and this package's root on its ``PYTHONPATH``, so also under the
``fasthex`` console script), because ``motioncapture.connect`` holds the GIL for its whole
connect and handshake: in this process a silent or wrong host froze every Python thread (5 s
for qualisys, for ever for vicon against a refused port and optitrack against a silent host),
the caller's timeout and Ctrl-C included. The child sends each frame's bodies (name,
position, quaternion, the host receive time) over a pipe in the binary format its module
describes; the receive thread here turns them into samples, stats and health. The receive
time is the child's stamp (``time.monotonic_ns``, a system-wide clock, so the pipe adds no
delay to it), or with an injected clock that clock when the report arrives.

``start()`` waits up to ``connect_timeout_s`` for a frame holding the body, with the GIL free.
None raises :class:`~drivers.mocap.pose.MocapConnectError` (the library did not answer: its
connect had not returned; or no frame at all) or :class:`~drivers.mocap.pose.UnknownBodyError`
(listing the bodies seen), after ending the child; an error the library raises in the child
(a refused connection, an unknown system) arrives as a ``MocapConnectError`` with its
message. So a silent host costs ``connect_timeout_s`` and a clear error, never a frozen ground
station. ``close()`` ends the child (SIGTERM, SIGKILL after :data:`TERMINATE_GRACE_S`) and
reaps it, whatever the library is doing. The child ignores SIGINT and SIGHUP (Ctrl-C is this
process's to handle) and never outlives this process: see its module. A ``connect`` factory
passed to the constructor (tests' stand-ins for the library) runs on the receive thread of
this process.
"""

from __future__ import annotations

import importlib.util
import json
import logging
import math
import os
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from config.schema import ConfigValueError
from drivers.mocap.frames import FrameConfig, FrameTransform, Quat, Vec3
from drivers.mocap.motioncapture_child import (
    STAGE_CONNECT,
    STAGE_FRAMES,
    STAGE_IMPORT,
    ChildError,
    Frame,
    PipeFormatError,
    read_message,
)
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

#: The module the library runs in (``python -P -m``).
CHILD_MODULE = "drivers.mocap.motioncapture_child"
#: How long ``close()`` gives the library's process after SIGTERM before SIGKILL.
TERMINATE_GRACE_S = 0.5

#: Systems libmotioncapture reads, with the up axis of their world frame by default.
SYSTEM_UP_AXIS: dict[str, str] = {"vicon": "z", "qualisys": "z", "vrpn": "z", "optitrack": "y"}


class LibraryProcessError(Exception):
    """What the library's process reported (or that it ended); ``stage`` as the child's."""

    def __init__(self, stage: int, message: str) -> None:
        self.stage = stage
        super().__init__(message)


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

    By default the library runs in a child process (see module). ``connect`` instead builds
    the library's object from ``(system, library_options(system, host))`` on the receive
    thread of this process: tests pass stand-ins with the library's interface."""

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
        self._proc_lock = threading.Lock()  # the child is started and ended under it
        self._proc: subprocess.Popen[bytes] | None = None
        self._latest: PoseSample | None = None
        self._frames_seen = 0
        self._waits = 0  # frames the library returned, with or without the body
        self._connected = False  # the library's connect returned
        self._seen_bodies: set[str] = set()
        self._error: BaseException | None = None

    def __enter__(self) -> MotionCaptureClient:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def child_pid(self) -> int | None:
        """The library's process id until it has ended and been reaped (None in-process)."""
        proc = self._proc
        return None if proc is None or proc.returncode is not None else proc.pid

    def start(self) -> None:
        """Start the library, return once a frame holds the body (see module). Started
        again, the client first ends its running library."""
        cfg = self.config
        if self._thread is not None:
            self.close()  # one child per client: a second would outlive close()
        if self._connect is None:
            _require_library(cfg.name)
            thread = threading.Thread(target=self._run_child, name="motioncapture-rx",
                                      daemon=True)
        else:
            thread = threading.Thread(target=self._run_in_process, args=(self._connect,),
                                      name="motioncapture-rx", daemon=True)
        self._stop.clear()
        with self._cond:
            self._error, self._connected = None, False
            frames_before = self._frames_seen
        self._thread = thread
        thread.start()
        deadline = time.monotonic() + cfg.connect_timeout_s
        try:
            with self._cond:
                while (self._frames_seen == frames_before and self._error is None
                       and not self._stop.is_set()):
                    left = deadline - time.monotonic()
                    if left <= 0.0:
                        break
                    self._cond.wait(left)
                error, waits, seen = self._error, self._waits, sorted(self._seen_bodies)
                got, connected = self._frames_seen > frames_before, self._connected
        except BaseException:  # Ctrl-C while connecting: the caller gets no client to close
            self.close()
            raise
        closed = self._stop.is_set()  # close() from another thread
        if got and not closed:
            return
        self.close()
        if closed:
            raise MocapConnectError(cfg.name, "closed while connecting")
        if isinstance(error, LibraryProcessError) and error.stage == STAGE_IMPORT:
            raise MocapError(cfg.name, f"needs libmotioncapture: pip install "
                             f"'fasthex[motioncapture]' ({error})") from error
        if error is not None:
            raise MocapConnectError(cfg.name, f"libmotioncapture: {error}") from error
        if not connected:
            raise MocapConnectError(cfg.name, f"libmotioncapture's {cfg.system} connect to "
                                    f"{cfg.host} did not answer within "
                                    f"{cfg.connect_timeout_s:g} s (wrong host, server not "
                                    f"running, firewall?); its process was ended")
        if not seen:
            raise MocapConnectError(cfg.name, f"no rigid body within {cfg.connect_timeout_s:g}"
                                    f" s ({waits} frames; server not running, wrong host?)")
        raise UnknownBodyError(cfg.name, f"no rigid body named {cfg.body!r} within "
                               f"{cfg.connect_timeout_s:g} s; the server sends "
                               f"{', '.join(seen)}")

    def close(self) -> None:
        """End the library's process (reaped) and the receive thread."""
        self._stop.set()
        with self._cond:
            self._cond.notify_all()  # a start() waiting for the first frame gives up
        with self._proc_lock:
            proc = self._proc
            if proc is not None:
                _end_process(proc)
        thread, self._thread = self._thread, None
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout=2.0)
            if thread.is_alive():
                log.warning("%s: the library is still waiting for a frame; its thread ends "
                            "with its wait", self.config.name)
        if proc is not None and (thread is None or not thread.is_alive()):
            for pipe in (proc.stdin, proc.stdout):
                if pipe is not None:
                    pipe.close()

    def _fail(self, error: BaseException) -> None:
        if not self._stop.is_set():
            log.warning("%s: libmotioncapture failed: %s", self.config.name, error)
        with self._cond:
            self._error = error
            self._cond.notify_all()

    def _on_connected(self) -> None:
        with self._cond:
            self._connected = True
            self._cond.notify_all()

    def _on_frame(self, names: Iterable[str]) -> None:
        with self._cond:
            self._waits += 1
            self._seen_bodies.update(names)
            self._cond.notify_all()

    def _run_in_process(self, connect: Callable[[str, dict[str, str]], Any]) -> None:
        cfg = self.config
        try:
            mc = connect(cfg.system, library_options(cfg.system, cfg.host))
            self._on_connected()
            while not self._stop.is_set():
                mc.waitForNextFrame()
                bodies = mc.rigidBodies
                rx_t_ns = self._clock()
                self._on_frame(bodies)
                rb = bodies.get(cfg.body)
                if rb is not None:
                    self.on_body(rb.position, rb.rotation, rx_t_ns)
        except Exception as exc:  # the library raises RuntimeError; the thread must not die
            self._fail(exc)

    def _run_child(self) -> None:
        cfg = self.config
        try:
            with self._proc_lock:
                if self._stop.is_set():
                    return
                # Started from this thread, which lives until the child has ended: Linux's
                # parent-death signal (see the child's module) fires when the *thread* that
                # started a process ends, not only when the process does.
                proc = subprocess.Popen(_child_command(cfg), stdin=subprocess.PIPE,
                                        stdout=subprocess.PIPE, env=_child_env(),
                                        start_new_session=True)  # no terminal signals
                self._proc = proc
        except OSError as exc:
            self._fail(LibraryProcessError(STAGE_CONNECT,
                                           f"cannot start the library's process: {exc}"))
            return
        assert proc.stdout is not None
        try:
            while (msg := read_message(proc.stdout)) is not None:
                if isinstance(msg, Frame):
                    self._on_child_frame(msg)
                elif isinstance(msg, ChildError):
                    self._fail(LibraryProcessError(msg.stage, msg.message))
                else:
                    self._on_connected()
        except PipeFormatError as exc:
            self._fail(LibraryProcessError(STAGE_FRAMES, f"unreadable report: {exc}"))
            with self._proc_lock:
                _end_process(proc)
            return
        # End of the pipe: the child has ended (or is ending)
        try:
            code = proc.wait(timeout=2.0)
        except subprocess.TimeoutExpired:
            code = None
        if self._error is None and not self._stop.is_set():
            self._fail(LibraryProcessError(STAGE_FRAMES, f"the library's process ended "
                                           f"(exit code {code}) without a word"))

    def _on_child_frame(self, frame: Frame) -> None:
        # the child stamps with the system-wide monotonic clock: the default clock here, so
        # the stamp is the arrival itself; another clock (a simulation's) reads its own now
        rx_t_ns = (frame.rx_monotonic_ns if self._clock is time.monotonic_ns
                   else self._clock())
        self._on_frame(b.name for b in frame.bodies)
        for body in frame.bodies:
            if body.name != self.config.body:
                continue
            if not body.ok:
                self.monitor.count_malformed()
                continue
            w, x, y, z = body.q_wxyz
            self._on_pose(body.position_m, (x, y, z, w), rx_t_ns)

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
        self._on_pose(pos, q_xyzw, rx_t_ns)

    def _on_pose(self, pos: Vec3, q_xyzw: Quat, rx_t_ns: int) -> None:
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


def _require_library(device: str) -> None:
    # looked up here, imported only in the child: a missing library is an error at once
    if importlib.util.find_spec("motioncapture") is None:
        raise MocapError(device, "needs libmotioncapture: pip install 'fasthex[motioncapture]'")


def _child_command(cfg: MotionCaptureConfig) -> list[str]:
    options = json.dumps(library_options(cfg.system, cfg.host))
    return [sys.executable, "-P", "-m", CHILD_MODULE, cfg.system, options, str(os.getpid())]


def _child_env() -> dict[str, str]:
    # -P keeps the working directory off the child's path; this package's root goes first
    root = str(Path(__file__).resolve().parents[2])
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([root, *filter(None, [env.get("PYTHONPATH")])])
    return env


def _end_process(proc: subprocess.Popen[bytes]) -> None:
    """SIGTERM (its default action: the library may hold the GIL), SIGKILL after a grace;
    reaped either way."""
    if proc.poll() is not None:
        return
    proc.terminate()
    try:
        proc.wait(timeout=TERMINATE_GRACE_S)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


__all__ = ["SYSTEM_UP_AXIS", "MotionCaptureClient", "MotionCaptureConfig", "library_options"]

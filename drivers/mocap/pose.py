"""What a MoCap device hands to the ground station: pose samples, stream health, errors.

A :class:`PoseSample` is the newest information about one rigid body, already in the ground
station's world frame (z up, ``q_wb`` body -> world, ``(w, x, y, z)``). Its ``t_ns`` is the
*capture* time on the ground-station clock (``time.monotonic_ns`` unless a clock is injected):
receive time minus the latency the server reports (NatNet >= 3.0), minus a configured constant
network delay. When the body is not tracked in the newest frame (tracking-valid flag cleared,
body missing from the frame) the sample says so (``valid`` False, position and quaternion NaN):
a stale pose is never handed out as current.

A pose no rigid body can have is *dropped* at the device, never handed out, and counted
(:attr:`MocapStats.implausible_samples`): a non-finite position or quaternion, a position
farther from the world origin than the workspace (:attr:`PoseLimits.max_range_m`, 100 m by
default), a wire quaternion whose norm is far from 1 (servers send unit quaternions; a
corrupted float is not one), or a reported latency outside 0..1 s (the stamps are wrong, so is
the capture time). The latest sample then stays the previous one and ages.
"""

from __future__ import annotations

import enum
import math
import select
import socket
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

from config.schema import ConfigValueError
from drivers.mocap.frames import FrameTransform, Quat, Vec3

NAN3: Vec3 = (math.nan, math.nan, math.nan)
NAN4: Quat = (math.nan, math.nan, math.nan, math.nan)

#: A frame-number step larger than this (or backwards) is a discontinuity of the server's
#: numbering (Motive restarted, timeline jumped), not a count of lost frames.
MAX_FRAME_GAP = 1000

#: The stream rate counts the frames that arrived in this last stretch of the injected clock.
RATE_WINDOW_S = 1.0
#: No rate is given before the stream is this old: two frames that arrive together (one TCP
#: read, one burst off the network) would otherwise read as thousands of hertz.
MIN_RATE_SPAN_S = 0.25


class TrackingStatus(enum.Enum):
    OK = "ok"
    INVALID = "tracking_invalid"  # server says the body is not tracked (occluded markers)
    MISSING = "missing"  # body absent from the frame


@dataclass(frozen=True, slots=True)
class PoseSample:
    """One rigid body in one MoCap frame, world frame, ground-station clock."""

    t_ns: int  # capture time, ground-station clock
    rx_t_ns: int  # arrival time of the packet, ground-station clock
    frame_number: int
    body_id: int
    body_name: str
    status: TrackingStatus
    pos_w_m: Vec3  # NaN unless valid
    q_wb: Quat  # (w, x, y, z) body -> world; NaN unless valid
    latency_s: float  # server-reported latency + configured network delay
    mean_error_m: float  # mean marker error (NatNet); NaN if the server does not give it

    @property
    def valid(self) -> bool:
        return self.status is TrackingStatus.OK

    def as_missing(self) -> PoseSample:
        """This sample's stamps with the body reported missing (a stale pose, never current)."""
        return PoseSample(self.t_ns, self.rx_t_ns, self.frame_number, self.body_id,
                          self.body_name, TrackingStatus.MISSING, NAN3, NAN4, self.latency_s,
                          math.nan)


@dataclass(frozen=True)
class PoseLimits:
    """What a MoCap pose can physically be. Loadable from YAML (``config.schema``)."""

    max_range_m: float = 100.0
    """Workspace radius around the world origin; a pose farther away is dropped."""
    max_quat_norm_error: float = 0.05
    """Largest ``| |q| - 1 |`` of the wire quaternion (float32 rounding is ~1e-7)."""
    max_latency_s: float = 1.0
    """Largest plausible server-reported latency (a MoCap chain takes a few ms)."""

    def __post_init__(self) -> None:
        for key in ("max_range_m", "max_quat_norm_error", "max_latency_s"):
            value = getattr(self, key)
            if not 0.0 < value < math.inf:
                raise ConfigValueError(key, f"must be a finite limit > 0, got {value!r}")

    def latency_ok(self, latency_s: float) -> bool:
        return 0.0 <= latency_s <= self.max_latency_s

    def wire_quat_ok(self, q: tuple[float, float, float, float]) -> bool:
        n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
        return abs(n - 1.0) <= self.max_quat_norm_error  # False for NaN

    def position_ok(self, pos_w_m: Vec3) -> bool:
        r2 = pos_w_m[0] * pos_w_m[0] + pos_w_m[1] * pos_w_m[1] + pos_w_m[2] * pos_w_m[2]
        return r2 <= self.max_range_m * self.max_range_m  # False for NaN, inf

    def world_pose(self, transform: FrameTransform, pos: Vec3,
                   q_xyzw: tuple[float, float, float, float]) -> tuple[Vec3, Quat] | None:
        """The wire pose in the world frame, or None if no rigid body can have it."""
        if not self.wire_quat_ok(q_xyzw):
            return None
        try:
            pos_w, q_wb = transform.to_world(pos, q_xyzw)
        except ValueError:  # a zero or non-finite quaternion
            return None
        return (pos_w, q_wb) if self.position_ok(pos_w) else None


@dataclass(frozen=True, slots=True)
class MocapStats:
    """Stream health of one MoCap device at ``now_ns``."""

    frames_received: int
    frames_dropped: int  # missing frame numbers (gaps up to MAX_FRAME_GAP)
    frame_jumps: int  # frame-number discontinuities
    invalid_samples: int  # frames where the configured body was invalid or missing
    malformed_packets: int
    foreign_packets: int  # from an address other than the configured server
    rate_hz: float  # frames per second over the last RATE_WINDOW_S; 0 until MIN_RATE_SPAN_S
    age_s: float  # now - capture time of the newest valid sample; inf if none
    latency_s: float  # of the newest frame; NaN if unknown
    implausible_samples: int = 0  # poses or frames outside PoseLimits, dropped
    clock_offset_s: float = math.nan  # server clock -> host clock (host - server); NaN if none
    clock_drift_ppm: float = math.nan  # rate error of the server's clock; NaN until learnt
    clock_drift_sigma_ppm: float = math.inf  # standard error of clock_drift_ppm


@runtime_checkable
class PoseSource(Protocol):
    """The interface the ground-station loop reads MoCap through (single-slot mailbox)."""

    def latest(self) -> PoseSample | None:
        """The newest sample of the configured body, or None before the first frame."""
        ...

    def stats(self) -> MocapStats:
        """Stream health now."""
        ...


class MocapError(Exception):
    """A MoCap device cannot do what was asked; ``device`` names it (URI or address)."""

    def __init__(self, device: str, message: str) -> None:
        self.device = device
        super().__init__(f"{device}: {message}")


class MocapConnectError(MocapError):
    """The server did not answer (wrong address, server not running, firewall)."""


class UnknownBodyError(MocapError):
    """The configured rigid body name is not defined on the server."""


class StreamMonitor:
    """Thread-safe counters and rate/age bookkeeping shared by the MoCap devices."""

    def __init__(self, clock: Callable[[], int], rate_window_s: float = RATE_WINDOW_S,
                 min_rate_span_s: float = MIN_RATE_SPAN_S) -> None:
        self._clock = clock
        self._lock = threading.Lock()
        self._rate_window_ns = round(rate_window_s * 1e9)
        self._min_rate_span_ns = round(min(min_rate_span_s, rate_window_s) * 1e9)
        self._rx: deque[int] = deque()  # arrivals within the rate window (pruned on use)
        self._first_rx_ns: int | None = None
        self._last_frame: int | None = None
        self.frames_received = 0
        self.frames_dropped = 0
        self.frame_jumps = 0
        self.invalid_samples = 0
        self.malformed_packets = 0
        self.foreign_packets = 0
        self.implausible_samples = 0
        self._last_valid_t_ns: int | None = None
        self._latency_s = math.nan
        self._clock_est = (math.nan, math.nan, math.inf)

    def set_server_clock(self, offset_s: float, drift_ppm: float,
                         drift_sigma_ppm: float = math.inf) -> None:
        """The server clock as the client's clock sync sees it (offset, drift, its error)."""
        self._clock_est = (offset_s, drift_ppm, drift_sigma_ppm)

    def count_malformed(self) -> None:
        with self._lock:
            self.malformed_packets += 1

    def count_implausible(self) -> None:
        with self._lock:
            self.implausible_samples += 1

    def count_foreign(self) -> None:
        with self._lock:
            self.foreign_packets += 1

    def on_frame(self, frame_number: int | None, rx_t_ns: int, latency_s: float) -> None:
        """Record one frame (``frame_number`` None for streams without numbering)."""
        with self._lock:
            self.frames_received += 1
            if self._first_rx_ns is None:
                self._first_rx_ns = rx_t_ns
            self._rx.append(rx_t_ns)
            self._prune(rx_t_ns)
            self._latency_s = latency_s
            if frame_number is None:
                return
            last = self._last_frame
            if last is not None:
                gap = frame_number - last
                if gap <= 0 or gap > MAX_FRAME_GAP:
                    self.frame_jumps += 1
                elif gap > 1:
                    self.frames_dropped += gap - 1
            self._last_frame = frame_number

    def on_sample(self, sample: PoseSample) -> None:
        with self._lock:
            if sample.valid:
                self._last_valid_t_ns = sample.t_ns
            else:
                self.invalid_samples += 1

    def _prune(self, now_ns: int) -> None:
        while self._rx and self._rx[0] <= now_ns - self._rate_window_ns:
            self._rx.popleft()

    def _rate_hz(self, now_ns: int) -> float:
        """Frames per second over the window ending *now* (so a stream that stops reads a
        falling rate); while the stream is younger than the window, over its whole life."""
        if self._first_rx_ns is None:
            return 0.0
        self._prune(now_ns)
        span_ns = now_ns - self._first_rx_ns
        if span_ns < self._min_rate_span_ns:
            return 0.0
        if span_ns >= self._rate_window_ns:
            return len(self._rx) * 1e9 / self._rate_window_ns
        return (len(self._rx) - 1) * 1e9 / span_ns  # the first frame opens the span

    def snapshot(self) -> MocapStats:
        now = self._clock()
        with self._lock:
            rate = self._rate_hz(now)
            age = math.inf if self._last_valid_t_ns is None \
                else (now - self._last_valid_t_ns) * 1e-9
            return MocapStats(self.frames_received, self.frames_dropped, self.frame_jumps,
                              self.invalid_samples, self.malformed_packets,
                              self.foreign_packets, rate, age, self._latency_s,
                              self.implausible_samples, *self._clock_est)


class WaitingSockets:
    """Whether any of a client's sockets has input waiting, in one ``poll(2)`` (~1 us) rather
    than one failed non-blocking receive per socket (~2.3 us each, an exception apiece): a
    lockstep loop polls its MoCap client every tick and finds a frame on one tick in five.
    Registers the sockets again whenever the client's set of sockets changes (re-opened)."""

    def __init__(self) -> None:
        self._socks: tuple[socket.socket | None, ...] = ()
        self._poll = select.poll()

    def any(self, socks: tuple[socket.socket | None, ...]) -> bool:
        if socks != self._socks:
            self._poll = select.poll()
            for s in socks:
                if s is not None:
                    self._poll.register(s, select.POLLIN)
            self._socks = socks
        return bool(self._poll.poll(0))


class FrameWaits:
    """What every MoCap client offers on top of :class:`PoseSource`: the stream statistics and
    waits for received frames (tools and tests; never the control loop). The client keeps
    ``_frames_seen`` (incremented under ``_cond``, notifying it) and a ``monitor``."""

    _cond: threading.Condition
    _frames_seen: int
    monitor: StreamMonitor

    def stats(self) -> MocapStats:
        return self.monitor.snapshot()

    @property
    def frames_seen(self) -> int:
        """Frames (reports) received so far; pair with :meth:`wait_for_total`."""
        return self._frames_seen

    def wait_for_total(self, total: int, timeout_s: float) -> bool:
        """Block until ``total`` frames have been received in all; False on timeout."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while self._frames_seen < total:
                left = deadline - time.monotonic()
                if left <= 0.0:
                    return False
                self._cond.wait(left)
        return True

    def wait_frames(self, count: int, timeout_s: float) -> bool:
        """Block until ``count`` more frames arrive after this call; False on timeout."""
        return self.wait_for_total(self._frames_seen + count, timeout_s)

    def wait_for_rate(self, timeout_s: float) -> float:
        """Block until the stream rate is measured (frames over ``MIN_RATE_SPAN_S``); returns
        it, or 0.0 on timeout."""
        deadline = time.monotonic() + timeout_s
        while True:
            rate = self.stats().rate_hz
            left = deadline - time.monotonic()
            if rate > 0.0 or left <= 0.0:
                return rate
            self.wait_frames(1, min(left, 0.05))

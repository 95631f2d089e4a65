"""The Flight-Ctrl device: the 500 Hz link between the ground station and the FAST-Hex.

Wire protocol: LAAS tk3 (:mod:`.framing_tk3`, :mod:`.messages`) over a raw 8N1 serial line,
500000 baud on the real robot (``serial:///dev/ttyUSB0?baud=500000``) or a pty to the emulator
(``pty:///tmp/fasthex/flight-ctrl``); any :mod:`drivers.transport` URI works.

Connect sequence (as the LAAS ``rotorcraft`` host does it): flush, send ``?`` up to four times
with a 0.5 s wait each and match the answer against the accepted firmware ids (``fnmatch``
patterns, default ``mkfl1.8*``). A board that stays silent is asked ``v`` in the stock
MikroKopter framing (``#bv@x\\r``); if it answers, :class:`StockFirmwareError` says it runs the
stock firmware, which cannot stream the IMU at 500 Hz nor take per-motor spin rates. Then the
stream periods are set (``b``, ``m``, ``i``, ``c``).

A reader thread owns the receive side. It timestamps every chunk on the injected clock, deframes,
decodes, checks lengths, ranges, IMU steps and sequence numbers (an accelerometer spike under
the implausible-step limit is held at the axis's last value for a sample: tk3 carries no
checksum), and puts the results into single-slot
mailboxes: the newest IMU sample (handed to :meth:`FlightCtrl.wait_next`, never queued), the
newest state of each motor, battery and magnetometer. IMU sample times are rebuilt from the
sequence number on the board's own clock, mapped onto the host clock by
:class:`drivers.clock_sync.ClockSync` (the board's real rate and offset, learnt on the earliest
arrivals: a board whose crystal is off by 1.2 % still gets sample times that are never later
than their arrival); ``link_stats().imu_clock`` has the measured rate, offset and drift. Link
statistics (measured rates, gaps, staleness, every kind of dropped frame) come from
:meth:`FlightCtrl.link_stats`.
A loop that owns the link alone (a lockstep flight, where every sample answers the loop's own
``w``) can take the receive side over (:meth:`FlightCtrl.read_in_caller_thread`): the same
processing then runs inside its waits, which saves a thread hand-over per sample.

The write side is called from the control loop: one ``w`` frame per tick
(:meth:`FlightCtrl.send_rotor_speeds_hz`), about 15 bytes, under a lock shared with the other
commands.
"""

from __future__ import annotations

import contextlib
import enum
import fnmatch
import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

from config.schema import ConfigValueError
from drivers.clock_sync import ClockSync
from drivers.errors import DeviceLostError, DriverError, TransportError
from drivers.mikrokopter import framing_stock, framing_tk3
from drivers.mikrokopter import messages as mkm
from drivers.transport import Transport, open_transport, parse_uri

__all__ = [
    "BatterySample",
    "BoardIdentity",
    "FlightCtrl",
    "FlightCtrlConfig",
    "FlightCtrlError",
    "FlightCtrlIdentityError",
    "ImuClock",
    "ImuSample",
    "LinkHealth",
    "LinkStats",
    "MagSample",
    "MotorStartError",
    "MotorState",
    "MotorStatus",
    "MotorsSnapshot",
    "StockFirmwareError",
    "StreamStats",
    "probe",
]

log = logging.getLogger(__name__)

Vec3 = tuple[float, float, float]
Clock = Callable[[], int]

_SEQ_JUMP_RESET = 16  # rotorcraft mk_get_ts: a larger jump resets the time base
#: the accelerometer's typical step: an exponential average, ~256 samples (0.5 s at 500 Hz)
ACCEL_STEP_GAIN = 1.0 / 256.0


# ------------------------------------------------------------------------------------ errors


class FlightCtrlError(DriverError):
    """The Flight-Ctrl answered, but not as a flyable FAST-Hex board."""


class FlightCtrlIdentityError(FlightCtrlError):
    """No answer to the identification, or a firmware id that is not accepted."""


class StockFirmwareError(FlightCtrlIdentityError):
    """The board runs the stock HiSystems firmware: fine for bench tests, unable to fly here."""

    def __init__(self, device: str, version: str) -> None:
        self.version = version
        super().__init__(
            device,
            f"board runs the stock MikroKopter firmware {version}, which cannot stream the IMU "
            "at 500 Hz nor take per-motor spin rates in flight; flash tk3-mikrokopter")


class MotorStartError(FlightCtrlError):
    """The motors did not all reach ``spinning`` (or one raised its emergency flag)."""


# ------------------------------------------------------------------------------------ samples


@dataclass(frozen=True, slots=True)
class ImuSample:
    """One IMU sample, body frame of the vehicle (x to propeller 1, z up; at rest +g on z)."""

    seq: int
    """Sample counter rebuilt from the 8-bit wire sequence (``seq % 256`` is on the wire)."""
    t_ns: int
    """Sample time on the host clock, rebuilt from ``seq`` and the configured IMU period."""
    arrival_t_ns: int
    """When the reader thread received the bytes (host clock)."""
    gyro_rad_s: Vec3
    accel_m_s2: Vec3
    period_ns: int = 2_000_000
    """The configured IMU period. ``seq * period_ns`` is the board's own time base: the one
    to integrate with (exact in lockstep, where host arrival times mean nothing)."""

    @property
    def board_t_ns(self) -> int:
        """Sample time on the board's clock (``seq * period_ns``)."""
        return self.seq * self.period_ns


class MotorState(enum.Enum):
    OFF = "off"
    STARTING = "starting"
    SPINNING = "spinning"
    EMERGENCY = "emergency"


@dataclass(frozen=True, slots=True)
class MotorStatus:
    motor_id: int
    """1-based, propeller order of the paper."""
    state: MotorState
    speed_hz: float
    """Measured spin rate (Hz, positive; 0 when not spinning)."""
    throttle_pct: float
    current_a: float
    t_ns: int
    """Arrival time of the ``M`` frame."""


@dataclass(frozen=True, slots=True)
class MotorsSnapshot:
    """The newest state of every motor (``None``: no ``M`` frame yet for that motor)."""

    motors: tuple[MotorStatus | None, ...]

    @property
    def all_spinning(self) -> bool:
        return all(m is not None and m.state == MotorState.SPINNING for m in self.motors)

    @property
    def any_emergency(self) -> bool:
        return any(m is not None and m.state == MotorState.EMERGENCY for m in self.motors)

    @property
    def speeds_hz(self) -> tuple[float, ...]:
        return tuple(m.speed_hz if m is not None else math.nan for m in self.motors)

    @property
    def currents_a(self) -> tuple[float, ...]:
        return tuple(m.current_a if m is not None else math.nan for m in self.motors)


@dataclass(frozen=True, slots=True)
class BatterySample:
    seq: int
    t_ns: int
    voltage_v: float


@dataclass(frozen=True, slots=True)
class MagSample:
    seq: int
    t_ns: int
    field_t: Vec3
    """Body frame, tesla."""


@dataclass(frozen=True, slots=True)
class BoardIdentity:
    protocol: str
    """``tk3`` or ``stock``."""
    firmware_id: str
    """tk3 id (``mkfl1.8``) or the stock version (``2.12a``)."""
    accepted: bool
    """Whether this board can fly the FAST-Hex with the configured firmware ids."""
    replies: tuple[str, ...] = ()
    """Every tk3 id the board gave when none was accepted (the link has no checksum: ids that
    differ are a corrupted link, the same one each time a board with other firmware)."""


class LinkHealth(enum.Enum):
    NOT_CONNECTED = "not connected"
    OK = "ok"
    RATE_LOW = "IMU rate below the minimum fraction of the set rate"
    STALE = "no IMU sample for longer than the staleness limit"
    LOST = "device lost"


@dataclass(frozen=True, slots=True)
class StreamStats:
    name: str
    nominal_rate_hz: float
    measured_rate_hz: float
    """Arrivals per second over the last rate window (host clock)."""
    received: int
    missing: int
    """Samples known lost from sequence-number gaps (IMU only)."""
    age_s: float
    """Time since the last arrival (inf if none)."""
    max_interval_s: float
    """Largest interval between two arrivals within the rate window."""


@dataclass(frozen=True, slots=True)
class ImuClock:
    """The board's sample clock as measured against the host clock."""

    rate_hz: float
    """IMU samples per host second (the set rate corrected by the drift); NaN before any."""
    offset_s: float
    """Host time minus board time (sample counter x set period) at the newest sample."""
    drift_ppm: float
    """Rate error of the board's clock (negative: slow); 0 until learnt (``known``)."""
    known: bool = False
    drift_sigma_ppm: float = math.inf
    """Standard error of ``drift_ppm`` (large in the first seconds, then a few ppm)."""


@dataclass(frozen=True, slots=True)
class LinkStats:
    health: LinkHealth
    imu: StreamStats
    motor: StreamStats
    battery: StreamStats
    mag: StreamStats
    frames: int
    """Deframed messages, valid or not."""
    garbage_bytes: int
    frame_errors: int
    """Aborted, truncated, oversize, empty or badly escaped frames."""
    malformed: int
    """Wrong length or unknown command."""
    implausible: int
    """Frames with a value outside what the hardware can produce, dropped: IMU beyond full
    scale (or an implausible jump), spin rate, current or throttle beyond the BL-Ctrl's range,
    battery voltage above any pack."""
    seq_rejected: int
    """IMU samples dropped because their sequence number did not fit."""
    accel_saturated: int
    """IMU samples kept with an accelerometer axis at the ``I`` frame's limit (±32.767 m/s²):
    the true specific force was larger (an impact), the sample says too little."""
    late_steps: int
    """IMU steps believed only after their first three samples were dropped as implausible."""
    accel_spikes_held: int
    """Accelerometer axes held at their last value for one sample: a jump far beyond the axis's
    recent sample-to-sample steps (a corrupted byte under the implausible-step limit)."""
    resyncs: int
    imu_overwritten: int
    """Samples replaced in the mailbox before the loop took them."""
    frames_sent: int
    texts: tuple[str, ...]
    """The last info/warning/error texts from the board (``N: ...``)."""
    imu_clock: ImuClock = ImuClock(math.nan, math.nan, 0.0)

    @property
    def dropped(self) -> int:
        return self.frame_errors + self.malformed + self.implausible + self.seq_rejected


# ------------------------------------------------------------------------------------ config


@dataclass(frozen=True, slots=True)
class FlightCtrlConfig:
    """Settings of the Flight-Ctrl link (rates in Hz, times in s)."""

    firmware_ids: tuple[str, ...] = ("mkfl1.8*",)
    imu_rate_hz: float = 500.0
    motor_rate_hz: float = 50.0
    battery_rate_hz: float = 1.0
    mag_rate_hz: float = 0.0
    n_motors: int = 6
    spin_directions: tuple[int, ...] = (1, 1, 1, 1, 1, 1)
    """Sign of the ``w`` value per motor (+1/-1), as the BL-Ctrls are wired."""
    imu_axes: mkm.ImuAxes = field(default_factory=mkm.ImuAxes)
    identify_attempts: int = 4
    identify_timeout_s: float = 0.5
    imu_stale_after_s: float = 0.01
    min_rate_fraction: float = 0.8
    rate_window_s: float = 0.5
    max_gyro_step_rad_s: float = 0.25
    """Largest plausible change of a gyro axis between two samples (the vehicle's angular
    acceleration reaches ~60 rad/s^2, 0.12 rad/s per 2 ms). tk3 frames carry no checksum: a
    larger jump is a corrupted byte (a high byte changes a value by >= 0.256 rad/s) and the
    sample is dropped as implausible. The check is against the last two samples taken (a
    corrupted one just under the limit, once taken, does not make the next good ones
    implausible). A real step: three dropped in a row, each within the limits of the one
    before, then a fourth within them, is taken (a run of dropped samples once accepted the
    fourth whatever it read, and a corrupted byte there put 15.3 rad/s in the gyro for 8 ms:
    a 7 deg turn the vehicle never made, which the flight then corrected for real)."""
    max_accel_step_m_s2: float = 20.0
    """The same for the accelerometer, wide enough for touchdown impacts and vibration (2 g per
    sample): it catches the gross corruptions (high bits of the high byte)."""
    accel_spike_factor: float = 10.0
    """An accelerometer axis that jumps from its last value by more than this many times its
    recent typical step (an average of the steps over ~256 samples), and by more than
    ``accel_spike_floor_m_s2``, is held at the last value for that one sample; the next
    sample is taken whatever it reads. tk3 frames carry no checksum, and a corrupted byte
    under the implausible-step limit still kicks an integrated velocity (a 0.5 % corrupted
    link: ~3 such samples a second, 0.6-0.9 m/s of kicks in 11 s of flight, which a
    dead-reckoned landing cannot afford). A real step is taken one sample late (at an
    emulated touchdown, the first sample of the gear's impact). 0 turns it off."""
    accel_spike_floor_m_s2: float = 1.0
    """The smallest jump ``accel_spike_factor`` holds (the emulated IMU's steps in flight
    are ~0.05-0.14 m/s^2; a vibrating airframe's are larger, and the typical step with them)."""
    max_gyro_rad_s: float = 17.5
    """Gyro full scale (±1000 °/s); larger readings are corrupted and dropped."""
    max_accel_m_s2: float = 78.5
    """Accelerometer full scale (±8 g); larger readings are corrupted and dropped."""
    max_battery_v: float = 60.0
    """Above any pack the BL-Ctrls take (a 12S pack is 50.4 V charged); dropped."""
    max_motor_speed_hz: float = mkm.MAX_SPIN_HZ
    """A measured spin rate above this is beyond the BL-Ctrl's range: the ``M`` frame is
    dropped (a corrupted half period of 1 µs would read as 500 kHz)."""
    max_motor_current_a: float = 60.0
    """Above what a BL-Ctrl 2.0 can carry (35 A continuous, 40 A peak) with margin."""

    def __post_init__(self) -> None:
        if len(self.spin_directions) != self.n_motors or any(
                d not in (1, -1) for d in self.spin_directions):
            raise ConfigValueError("spin_directions",
                                   f"needs {self.n_motors} values of +1 or -1")
        for name in ("imu_rate_hz", "motor_rate_hz", "battery_rate_hz", "mag_rate_hz"):
            rate = getattr(self, name)
            if not 0.0 <= rate <= 2000.0:
                raise ConfigValueError(name, f"{rate} outside 0..2000 Hz")
        if not 0.0 < self.min_rate_fraction <= 1.0:
            raise ConfigValueError("min_rate_fraction", "must be in (0, 1]")
        for name in ("max_gyro_rad_s", "max_accel_m_s2", "max_battery_v", "max_motor_speed_hz",
                     "max_motor_current_a"):
            if not 0.0 < getattr(self, name) < math.inf:
                raise ConfigValueError(name, "must be a finite limit > 0")


# ------------------------------------------------------------------------------------ streams


#: one IMU sample as the board sent it (gyro, accelerometer), for the implausible-step check
_RawImu = tuple[tuple[float, ...], tuple[float, ...]]


def _within_steps(g: Sequence[float], a: Sequence[float], ref: _RawImu | None,
                  g_step: float, a_step: float) -> bool:
    """Whether a sample is within the per-sample step limits of ``ref`` (False without one)."""
    if ref is None:
        return False
    rg, ra = ref
    return (abs(g[0] - rg[0]) <= g_step and abs(g[1] - rg[1]) <= g_step
            and abs(g[2] - rg[2]) <= g_step and abs(a[0] - ra[0]) <= a_step
            and abs(a[1] - ra[1]) <= a_step and abs(a[2] - ra[2]) <= a_step)


class _RateMeter:
    """Arrival times over a sliding window (host clock, ns).

    The largest interval in the window is kept as it goes (a deque of the intervals that can
    still be the largest, by their earlier arrival): a stats call costs the same at 1 kHz as
    at 10 Hz, instead of a pass over the window's thousand arrivals with the driver's lock
    held (it was the flight loop's costliest tick at 1 kHz)."""

    def __init__(self, window_ns: int) -> None:
        self.window_ns = window_ns
        self.arrivals: deque[int] = deque(maxlen=8192)
        #: (earlier arrival, interval), intervals strictly decreasing front to back
        self.gaps: deque[tuple[int, int]] = deque()
        self.received = 0
        self.first_ns: int | None = None

    def add(self, t_ns: int) -> None:
        self.received += 1
        if self.first_ns is None:
            self.first_ns = t_ns
        arrivals, gaps = self.arrivals, self.gaps
        if arrivals:
            last = arrivals[-1]
            gap = t_ns - last
            while gaps and gaps[-1][1] <= gap:   # never the largest again: gone before it
                gaps.pop()
            gaps.append((last, gap))
        arrivals.append(t_ns)

    def reset(self) -> None:
        self.arrivals.clear()
        self.gaps.clear()
        self.first_ns = None

    def stats(self, name: str, nominal_hz: float, now_ns: int, missing: int = 0) -> StreamStats:
        arrivals, gaps = self.arrivals, self.gaps
        while arrivals and arrivals[0] < now_ns - self.window_ns:
            arrivals.popleft()
        # an interval is in the window while its earlier arrival is
        oldest = arrivals[0] if arrivals else now_ns + 1
        while gaps and gaps[0][0] < oldest:
            gaps.popleft()
        n = len(arrivals)
        span = self.window_ns if self.first_ns is None else min(
            self.window_ns, max(now_ns - self.first_ns, 1))
        rate = n * 1e9 / span if n else 0.0
        age = (now_ns - arrivals[-1]) / 1e9 if n else math.inf
        return StreamStats(name, nominal_hz, rate, self.received, missing, age,
                           gaps[0][1] / 1e9 if gaps else math.inf)


class _ImuTimeBase:
    """Rebuilds sample counters and times from 8-bit sequence numbers.

    A sample whose sequence number is not the next one is accepted as a gap only if at most
    16 samples are missing *and* enough time passed for them; otherwise it is held as a suspect
    (a corrupted sequence byte looks the same) and dropped, and the next sample that continues
    the suspect's sequence resynchronises the time base, unless it is at most 16 behind the
    counter (the stream catching up after a sequence byte corrupted ahead of it).
    """

    def __init__(self, period_ns: int) -> None:
        self.period_ns = period_ns
        self.count: int | None = None  # unwrapped counter of the last accepted sample
        self.last_arrival_ns = 0
        self.sync = ClockSync()  # board time (count x period) -> host time
        self.suspect: int | None = None
        self.missing = 0
        self.rejected = 0
        self.resyncs = 0

    def accept(self, seq8: int, arrival_ns: int) -> tuple[int, int] | None:
        """(counter, sample time) for an accepted sample, None for a rejected one."""
        if self.count is None:
            return self._reset(seq8, seq8, arrival_ns)
        gap = (seq8 - self.count - 1) & 0xFF
        if gap == 0:
            count = self.count + 1
        elif (self.suspect is not None and seq8 == (self.suspect + 1) & 0xFF
              and (self.count - seq8) & 0xFF > _SEQ_JUMP_RESET):
            # (A continuation at or just behind the counter is not a resync: the sample taken
            # last had a corrupted sequence byte ahead of the stream, 84 read as 86, and a
            # resync on the real 85, 86 moved the counter a whole wrap, 0.512 s, ahead. Its
            # samples are dropped until the stream passes the counter.)
            self.resyncs += 1
            self.missing += (seq8 - self.count - 1) & 0xFF
            return self._reset(self.count + 1 + ((seq8 - self.count - 1) & 0xFF), seq8,
                               arrival_ns)
        elif gap <= _SEQ_JUMP_RESET and (
                arrival_ns - self.last_arrival_ns) * 2 >= (gap + 1) * self.period_ns:
            self.missing += gap
            count = self.count + 1 + gap
        else:
            self.suspect = seq8
            self.rejected += 1
            return None
        self.suspect = None
        self.count = count
        self.last_arrival_ns = arrival_ns
        return count, self.sync.update(count * self.period_ns, arrival_ns)

    def _reset(self, count: int, seq8: int, arrival_ns: int) -> tuple[int, int]:
        self.count = count
        self.suspect = None
        self.last_arrival_ns = arrival_ns
        # a counter that does not continue the old one is a step the clock sync re-learns
        return count, self.sync.update(count * self.period_ns, arrival_ns)

    def clock(self) -> ImuClock:
        sync = self.sync
        if not sync.samples:
            return ImuClock(math.nan, math.nan, 0.0)
        return ImuClock(1e9 / (self.period_ns * sync.rate_ratio), sync.offset_ns * 1e-9,
                        sync.drift_ppm, sync.rate_known, sync.drift_sigma_ppm)


# ------------------------------------------------------------------------------------ device


class FlightCtrl:
    """The MikroKopter Flight-Ctrl running tk3-mikrokopter, as the 500 Hz loop uses it.

    Build with :meth:`open` (from a URI) or from any :class:`~drivers.transport.Transport`.
    ``clock`` returns nanoseconds (``time.monotonic_ns`` on hardware); every timestamp, rate
    and staleness figure reads it.
    """

    def __init__(self, transport: Transport, config: FlightCtrlConfig | None = None,
                 clock: Clock = time.monotonic_ns) -> None:
        self.config = config or FlightCtrlConfig()
        self.device = transport.name
        self._transport = transport
        self._clock = clock
        self._write_lock = threading.Lock()
        self._cond = threading.Condition()
        # fixed-length board messages: one whose `$` was corrupted is dropped at its last
        # byte, not when the next frame starts
        self._tk3 = framing_tk3.Tk3Parser(message_bytes_by_cmd=mkm.BOARD_MESSAGE_BYTES)
        self._stock = framing_stock.StockParser()
        self._listen_stock = False
        self._reader: threading.Thread | None = None
        self._stop = threading.Event()
        self._reader_stop = threading.Event()
        self._caller_reads = False      # no reader thread: the waits read the port themselves
        self._lost: TransportError | None = None
        self._connected = False
        # mailboxes (guarded by _cond)
        self._imu: ImuSample | None = None
        self._imu_count = 0
        self._imu_taken = 0
        self._motors: list[MotorStatus | None] = [None] * self.config.n_motors
        self._motor_updates = 0
        self._battery: BatterySample | None = None
        self._mag: MagSample | None = None
        self._identity: str | None = None
        self._stock_version: mkm.VersionInfo | None = None
        self._texts: deque[str] = deque(maxlen=16)
        # statistics (reader thread writes, others read under _cond)
        self._rates: dict[str, float] = {"imu": 0.0, "motor": 0.0, "battery": 0.0, "mag": 0.0}
        window = round(self.config.rate_window_s * 1e9)
        self._meters = {k: _RateMeter(window) for k in self._rates}
        self._timebase = _ImuTimeBase(2_000_000)
        self._malformed = 0
        self._implausible = 0
        self._saturated = 0
        self._late_steps = 0
        # the implausible-step check: the last two samples taken (raw), the run of dropped
        # samples that may be a real step and its newest sample
        self._last_imu_raw: _RawImu | None = None
        self._prev_imu_raw: _RawImu | None = None
        self._spike_run = 0
        self._step_candidate: _RawImu | None = None
        # accelerometer spike hold (body frame, the filed samples): last value, typical step
        self._accel_last: tuple[float, float, float] | None = None
        self._accel_step = [0.0, 0.0, 0.0]
        self._accel_held = [False, False, False]
        self._accel_spikes = 0
        self._imu_overwritten = 0
        self._frames_sent = 0

    @classmethod
    def open(cls, uri: str, config: FlightCtrlConfig | None = None,
             clock: Clock = time.monotonic_ns) -> FlightCtrl:
        """Open the transport named by ``uri`` (see :mod:`drivers.transport`)."""
        return cls(open_transport(uri), config, clock)

    # ---------------------------------------------------------------- connection

    def identify(self, *, tk3: bool = True, stock: bool = True) -> BoardIdentity:
        """Ask ``?`` (tk3), then ``v`` (stock); starts the reader thread if needed.

        A tk3 id that is not accepted is asked for again, up to ``identify_attempts`` in all:
        tk3 frames carry no checksum, so one corrupted byte on a noisy line would otherwise
        refuse a good board. Raises :class:`FlightCtrlIdentityError` if the board answers
        neither.
        """
        self._ensure_reader()
        cfg = self.config
        replies: list[str] = []
        for _ in range(cfg.identify_attempts if tk3 else 0):
            with self._cond:
                self._identity = None
            self._write(framing_tk3.encode_frame(mkm.Identify().encode()))
            if self._wait_for(lambda: self._identity is not None, cfg.identify_timeout_s):
                ident = (self._identity or "").lstrip("?")
                if any(fnmatch.fnmatchcase(ident, p) for p in cfg.firmware_ids):
                    return BoardIdentity("tk3", ident, True)
                replies.append(ident)
        if replies:
            return BoardIdentity("tk3", replies[-1], False, tuple(replies))
        if stock:
            with self._cond:
                self._listen_stock = True
                self._stock_version = None
            try:
                self._write(framing_stock.encode_frame(framing_stock.Address.FLIGHT_CTRL, b"v"))
                if self._wait_for(lambda: self._stock_version is not None,
                                  2 * cfg.identify_timeout_s):
                    assert self._stock_version is not None
                    return BoardIdentity("stock", self._stock_version.version, False)
            finally:
                with self._cond:
                    self._listen_stock = False
        asked = " nor ".join(q for q, on in ((f"'?' (tk3, {cfg.identify_attempts} tries)", tk3),
                                            ("'v' (stock MikroKopter)", stock)) if on)
        raise FlightCtrlIdentityError(
            self.device, f"no answer to {asked}: check the cable, power and baud rate")

    def connect(self) -> BoardIdentity:
        """Flush, identify, refuse boards that cannot fly, then set the stream rates."""
        discard = getattr(self._transport, "discard_input", None)
        if callable(discard):
            discard()
        ident = self.identify()
        if ident.protocol == "stock":
            raise StockFirmwareError(self.device, ident.firmware_id)
        if not ident.accepted:
            seen = sorted(set(ident.replies)) or [ident.firmware_id]
            if len(seen) > 1:
                raise FlightCtrlIdentityError(
                    self.device, f"firmware ids differ from one answer to the next "
                    f"({', '.join(map(repr, seen))}), none of the accepted "
                    f"{', '.join(self.config.firmware_ids)}: a corrupted link? check the "
                    "cable, its grounding and the baud rate")
            raise FlightCtrlIdentityError(
                self.device, f"firmware id {ident.firmware_id!r} is not one of the accepted "
                f"{', '.join(self.config.firmware_ids)}")
        cfg = self.config
        self.set_stream_rates(imu_hz=cfg.imu_rate_hz, motor_hz=cfg.motor_rate_hz,
                              battery_hz=cfg.battery_rate_hz, mag_hz=cfg.mag_rate_hz)
        self._connected = True
        log.info("%s: Flight-Ctrl %s, IMU %.0f Hz", self.device, ident.firmware_id,
                 cfg.imu_rate_hz)
        return ident

    def set_stream_rates(self, *, imu_hz: float | None = None, motor_hz: float | None = None,
                         battery_hz: float | None = None, mag_hz: float | None = None) -> None:
        """Set stream rates in Hz (0 = off; None = unchanged), in the LAAS order b, m, i, c."""
        for key, stream, rate in (("battery", mkm.Stream.BATTERY, battery_hz),
                                  ("motor", mkm.Stream.MOTOR, motor_hz),
                                  ("imu", mkm.Stream.IMU, imu_hz),
                                  ("mag", mkm.Stream.MAG, mag_hz)):
            if rate is None:
                continue
            msg = mkm.SetStreamPeriod.from_rate_hz(stream, rate)
            with self._cond:
                self._rates[key] = rate
                self._meters[key].reset()
                # at least 2.5 periods in the window, so that a 1 Hz battery stream has a rate
                self._meters[key].window_ns = round(
                    max(self.config.rate_window_s, 2.5 / rate if rate > 0 else 0.0) * 1e9)
                if key == "imu" and msg.period_us:
                    self._timebase = _ImuTimeBase(msg.period_us * 1000)
            self._write(framing_tk3.encode_frame(msg.encode()))

    # ---------------------------------------------------------------- the loop's side

    def wait_next(self, timeout_s: float) -> ImuSample | None:
        """The newest IMU sample not yet returned, waiting up to ``timeout_s``; None on timeout.

        Samples that arrived while the caller was busy are skipped (counted as overwritten),
        never queued. Raises :class:`DeviceLostError` once the device is gone.
        """
        if not self._wait_for(lambda: self._imu_count != self._imu_taken or self._stop.is_set(),
                              timeout_s):
            return None
        with self._cond:
            if self._imu_count == self._imu_taken:      # stopped
                return None
            self._imu_overwritten += self._imu_count - self._imu_taken - 1
            self._imu_taken = self._imu_count
            return self._imu

    @property
    def rx_errors(self) -> int:
        """Receive errors so far (framing errors, bytes outside any frame, malformed or
        implausible messages, rejected sequence numbers): a cheap counter the loop can poll
        every tick. A frame whose start byte was corrupted shows only as bytes outside any
        frame, so those count too.

        Read without the receive lock (it may show a chunk's errors while the reader is still
        filing that chunk); :meth:`wait_next` takes the lock, so a call after the count changed
        sees every sample of the chunk that changed it (the lockstep loop tells a lost sample
        from a late one that way)."""
        stats = self._tk3.stats
        return (stats.frame_errors + stats.garbage_bytes + self._malformed + self._implausible
                + self._timebase.rejected)

    @property
    def imu_anomalies(self) -> int:
        """Receive errors, samples kept with a saturated accelerometer or a held accelerometer
        spike, and samples the loop never took (overwritten in the mailbox: a late host):
        every event after which the motion the IMU gave the loop may be short of the real
        one. Polled by the loop at the MoCap rate, not per tick."""
        return self.rx_errors + self._saturated + self._imu_overwritten + self._accel_spikes

    @property
    def imu_motion_missed(self) -> int:
        """Of those, the events in which the IMU surely missed motion: an accelerometer at the
        ``I`` frame's limit, or a step taken as real only after its first three samples were
        dropped as implausible (an impact). A corrupted byte makes neither (a lone spike)."""
        return self._saturated + self._late_steps

    def latest_imu(self) -> ImuSample | None:
        with self._cond:
            return self._imu

    def send_rotor_speeds_hz(self, speeds_hz: Sequence[float]) -> None:
        """One ``w`` frame: the spin rate of every motor in Hz (positive; the configured
        directions give the sign on the wire; below 15.26 Hz the slowest speed is sent)."""
        dirs = self.config.spin_directions
        if len(speeds_hz) != len(dirs):
            raise ValueError(f"{self.device}: expected {len(dirs)} spin rates, "
                             f"got {len(speeds_hz)}")
        self._write(framing_tk3.encode_frame(mkm.encode_spin_rates_hz(speeds_hz, dirs)))

    def start_motors(self, timeout_s: float = 3.0, idle_spin_hz: float = 16.0
                     ) -> MotorsSnapshot:
        """Start every motor as the flight loop arms, and wait until all report ``spinning``.

        The loop's sequence: :meth:`request_motor_start` (``g`` per motor), then one ``w`` at
        ``idle_spin_hz`` per IMU sample (or every 20 ms without an IMU stream), so that the
        board's watchdog stays fed (and a lockstep emulator advances). The idle speed must be
        above 1e6/65535 = 15.26 Hz: below it ``w`` carries the slowest half period 32767, which
        tk3 hosts send to stop (``mk_servo_stop``) and a board may take as stop. ``g`` is
        re-sent every 100 such periods to motors that are neither starting nor spinning. On an
        emergency flag or a timeout every motor is stopped and :class:`MotorStartError` raised.
        Needs the motor (``M``) stream.
        """
        if not idle_spin_hz > mkm.MIN_SPIN_HZ:
            raise ValueError(f"{self.device}: idle_spin_hz {idle_spin_hz} must be above "
                             f"{mkm.MIN_SPIN_HZ:.2f} Hz (below it w means the slowest speed)")
        if self._rates["motor"] <= 0.0:
            raise MotorStartError(self.device, "the motor stream is off: cannot see the motors")
        n = self.config.n_motors
        self.request_motor_start()
        idle = [idle_spin_hz] * n
        deadline = time.monotonic() + timeout_s
        ticks = 0
        while True:
            if self.wait_next(0.02) is None and self._lost is not None:
                raise self._lost
            self.send_rotor_speeds_hz(idle)
            ticks += 1
            snap = self.motors()
            if snap.any_emergency:
                self.stop_motors()
                raise MotorStartError(self.device, "a motor raised its emergency flag "
                                      f"while starting: {self._describe(snap)}")
            if snap.all_spinning:
                return snap
            if time.monotonic() > deadline:
                self.stop_motors()
                raise MotorStartError(self.device, f"motors not spinning after {timeout_s} s: "
                                      f"{self._describe(snap)}")
            if ticks % 100 == 0:
                for i, m in enumerate(snap.motors):
                    if m is None or m.state == MotorState.OFF:
                        self._write(framing_tk3.encode_frame(mkm.StartMotors(i + 1).encode()))

    def request_motor_start(self) -> None:
        """Send ``g`` to every motor and return at once (the 500 Hz loop keeps ticking and
        watches :meth:`motors`; :meth:`start_motors` is the blocking variant for tools)."""
        for motor_id in range(1, self.config.n_motors + 1):
            self._write(framing_tk3.encode_frame(mkm.StartMotors(motor_id).encode()))

    @staticmethod
    def _describe(snap: MotorsSnapshot) -> str:
        return ", ".join(f"{i + 1}: {m.state.value if m else 'no data'}"
                         for i, m in enumerate(snap.motors))

    def stop_motors(self) -> None:
        """Stop every motor (``x``)."""
        self._write(framing_tk3.encode_frame(mkm.StopMotors().encode()))

    def beep(self, freq_hz: int = 440) -> None:
        self._write(framing_tk3.encode_frame(mkm.Beep(freq_hz).encode()))

    # ---------------------------------------------------------------- snapshots

    def motors(self) -> MotorsSnapshot:
        with self._cond:
            return MotorsSnapshot(tuple(self._motors))

    def wait_motor_update(self, timeout_s: float) -> MotorsSnapshot | None:
        """Block until a new ``M`` frame arrives (or the timeout); the snapshot or None."""
        with self._cond:
            seen = self._motor_updates
        if not self._wait_for(lambda: self._motor_updates != seen, timeout_s):
            return None
        with self._cond:
            return MotorsSnapshot(tuple(self._motors))

    def battery(self) -> BatterySample | None:
        with self._cond:
            return self._battery

    def magnetometer(self) -> MagSample | None:
        with self._cond:
            return self._mag

    def health(self) -> LinkHealth:
        return self.link_stats().health

    def link_stats(self) -> LinkStats:
        now = self._clock()
        cfg = self.config
        with self._cond:
            streams = {k: self._meters[k].stats(k, self._rates[k], now,
                                                self._timebase.missing if k == "imu" else 0)
                       for k in self._meters}
            imu = streams["imu"]
            if self._lost is not None:
                health = LinkHealth.LOST
            elif not self._connected:
                health = LinkHealth.NOT_CONNECTED
            elif imu.nominal_rate_hz > 0 and imu.age_s > cfg.imu_stale_after_s:
                health = LinkHealth.STALE
            elif (imu.nominal_rate_hz > 0 and self._meters["imu"].first_ns is not None
                  and now - self._meters["imu"].first_ns >= cfg.rate_window_s * 1e9
                  and imu.measured_rate_hz < cfg.min_rate_fraction * imu.nominal_rate_hz):
                health = LinkHealth.RATE_LOW
            else:
                health = LinkHealth.OK
            tk3s = self._tk3.stats
            return LinkStats(
                health=health, imu=imu, motor=streams["motor"], battery=streams["battery"],
                mag=streams["mag"], frames=tk3s.messages + tk3s.frame_errors,
                garbage_bytes=tk3s.garbage_bytes, frame_errors=tk3s.frame_errors,
                malformed=self._malformed, implausible=self._implausible,
                seq_rejected=self._timebase.rejected, accel_saturated=self._saturated,
                late_steps=self._late_steps, accel_spikes_held=self._accel_spikes,
                resyncs=self._timebase.resyncs,
                imu_overwritten=self._imu_overwritten, frames_sent=self._frames_sent,
                texts=tuple(self._texts), imu_clock=self._timebase.clock())

    # ---------------------------------------------------------------- lifetime

    def close(self) -> None:
        """Leave the board as found, then stop the reader thread and release the transport.

        Sends ``x`` (stop every motor) and sets the ``b``, ``m``, ``i``, ``c`` stream periods to
        0, best effort (a board that is gone cannot be told): a board left streaming fills the
        next client's input, and one left spinning waits for its BL watchdog. Only to a board
        that spoke tk3 on this link (a silent port or a stock board gets no tk3 bytes).
        Idempotent.
        """
        with self._cond:
            heard_tk3 = (self._connected or self._identity is not None or self._imu_count > 0
                         or self._motor_updates > 0)
        if heard_tk3 and not self._stop.is_set() and self._lost is None:
            with contextlib.suppress(TransportError, OSError):
                self.stop_motors()
                for stream in (mkm.Stream.BATTERY, mkm.Stream.MOTOR, mkm.Stream.IMU,
                               mkm.Stream.MAG):
                    self._write(framing_tk3.encode_frame(
                        mkm.SetStreamPeriod(stream, 0).encode()))
        self._stop.set()
        with self._cond:
            self._cond.notify_all()
        if self._reader is not None and self._reader is not threading.current_thread():
            self._reader.join(timeout=2.0)
        self._transport.close()

    def __enter__(self) -> FlightCtrl:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ---------------------------------------------------------------- internals

    def _write(self, frame: bytes) -> None:
        if self._lost is not None:
            raise self._lost
        with self._write_lock:
            try:
                self._transport.write(frame)
            except DeviceLostError as exc:
                self._mark_lost(exc)
                raise
            self._frames_sent += 1

    def _wait_for(self, predicate: Callable[[], bool], timeout_s: float) -> bool:
        if self._caller_reads:
            deadline = time.monotonic() + timeout_s
            while True:
                with self._cond:
                    if self._lost is not None:
                        raise self._lost
                    if predicate():
                        return True
                remaining = deadline - time.monotonic()
                if remaining <= 0.0:
                    return False
                self._read_once(remaining)
        with self._cond:
            ok = self._cond.wait_for(lambda: predicate() or self._lost is not None, timeout_s)
            if self._lost is not None:
                raise self._lost
            return ok

    def start(self) -> FlightCtrl:
        """Start the reader thread (``identify``/``connect`` do it); idempotent."""
        self._ensure_reader()
        return self

    def _ensure_reader(self) -> None:
        if self._reader is None and not self._caller_reads:
            self._reader = threading.Thread(target=self._read_loop, daemon=True,
                                            name=f"flightctrl-reader {self.device}")
            self._reader.start()

    def _mark_lost(self, exc: TransportError) -> None:
        with self._cond:
            if self._lost is None:
                self._lost = exc
                log.error("%s: %s", self.device, exc.message)
            self._cond.notify_all()

    def read_in_caller_thread(self) -> None:
        """Stop the reader thread: from now on :meth:`wait_next` and the other waits read the
        port in the calling thread (one thread hand-over less per sample).

        For a loop that owns the link alone, e.g. a lockstep flight where every sample
        answers the loop's own ``w``; the snapshots (``motors``, ``battery``,
        ``link_stats``...) then change only while the loop waits."""
        self._reader_stop.set()
        if self._reader is not None and self._reader is not threading.current_thread():
            self._reader.join()
        self._caller_reads = True

    def _read_loop(self) -> None:
        while not (self._stop.is_set() or self._reader_stop.is_set()):
            self._read_once()
            if self._lost is not None:
                return

    def feed(self, data: bytes, t_ns: int | None = None) -> None:
        """Process bytes as if they had just been read from the port (arrival ``t_ns``, default
        the clock's now): replaying a recording, or fuzzing the receive path in process.
        Never raises for any content; what does not decode is counted in :meth:`link_stats`."""
        if not data:
            return
        arrival = self._clock() if t_ns is None else t_ns
        with self._cond:
            if self._listen_stock:
                for frame in self._stock.feed(data):
                    self._on_stock(frame)
            for raw in self._tk3.feed(data):
                self._on_message(raw, arrival)

    def _read_once(self, timeout_s: float | None = None) -> None:
        """One transport read (waiting up to ``timeout_s``, None: the transport's read timeout)
        and its frames."""
        try:
            data = self._transport.read(4096, timeout_s)
        except TransportError as exc:
            if not self._stop.is_set():
                self._mark_lost(exc)
            return
        self.feed(data)

    def _on_message(self, raw: bytes, t_ns: int) -> None:
        """Decode and file one tk3 message (reader thread, ``_cond`` held)."""
        try:
            msg = mkm.decode_board_message(raw)
        except mkm.MalformedMessageError:
            self._malformed += 1
            return
        if isinstance(msg, mkm.ImuMessage):
            self._on_imu(msg, t_ns)
        elif isinstance(msg, mkm.MotorMessage):
            self._on_motor(msg, t_ns)
        elif isinstance(msg, mkm.BatteryMessage):
            if not msg.voltage_v <= self.config.max_battery_v:
                self._implausible += 1
                return
            self._battery = BatterySample(msg.seq, t_ns, msg.voltage_v)
            self._meters["battery"].add(t_ns)
        elif isinstance(msg, mkm.MagMessage):
            self._mag = MagSample(msg.seq, t_ns, self.config.imu_axes.to_body(msg.field_t))
            self._meters["mag"].add(t_ns)
        elif isinstance(msg, mkm.IdentityMessage):
            self._identity = msg.firmware_id
        elif isinstance(msg, mkm.TextMessage):
            text = f"{msg.level.decode()}: {msg.text}"
            self._texts.append(text)
            (log.error if msg.level == b"E" else log.info)("%s: board says %s", self.device, text)
        else:
            return
        self._cond.notify_all()

    def _on_imu(self, msg: mkm.ImuMessage, t_ns: int) -> None:
        """File one IMU sample (``_on_message`` notifies the waiters). The range and step
        checks on plain floats: generators over the two vectors cost ~3 us per sample."""
        cfg = self.config
        g = msg.gyro_rad_s
        a = msg.accel_m_s2
        gx, gy, gz = g
        ax, ay, az = a
        g_max, a_max = cfg.max_gyro_rad_s, cfg.max_accel_m_s2
        if not (abs(gx) <= g_max and abs(gy) <= g_max and abs(gz) <= g_max
                and abs(ax) <= a_max and abs(ay) <= a_max and abs(az) <= a_max):
            self._implausible += 1
            return
        last = self._last_imu_raw
        if last is not None:
            g_step, a_step = cfg.max_gyro_step_rad_s, cfg.max_accel_step_m_s2
            if (not _within_steps(g, a, last, g_step, a_step)
                    and not _within_steps(g, a, self._prev_imu_raw, g_step, a_step)):
                # Implausible against the last two samples taken (the one before the last:
                # a corrupted sample just under the limits was taken and the link is back).
                # A real step is three dropped samples in a row, each near the one before,
                # and a fourth near them; a run broken by a sample far from the one before
                # starts again from it (a corrupted sample ending a run is not a step).
                if _within_steps(g, a, self._step_candidate, g_step, a_step):
                    self._spike_run += 1
                else:
                    self._spike_run = 1
                self._step_candidate = (g, a)
                if self._spike_run <= 3:
                    self._implausible += 1
                    return
                self._late_steps += 1   # the three dropped samples were a real step
        self._spike_run = 0
        self._step_candidate = None
        self._prev_imu_raw = last
        self._last_imu_raw = (g, a)
        lim = mkm.IMU_ACCEL_WIRE_LIMIT_M_S2
        if abs(ax) >= lim or abs(ay) >= lim or abs(az) >= lim:
            self._saturated += 1
        stamped = self._timebase.accept(msg.seq, t_ns)
        if stamped is None:
            return
        accel, gyro = cfg.imu_axes.imu_to_body(msg)
        if cfg.accel_spike_factor > 0.0:
            spikes = self._accel_spikes
            accel = self._hold_accel_spike(accel)
            if self._accel_spikes != spikes and last is not None:
                # A held spike is not the reference of the next implausible-step check: its
                # accelerometer reading was corrupted (a 0.5 % corrupted link once sent -5.9,
                # held, then -25.6 m/s^2, 19.7 from it and taken: 0.15 m/s kicked into the
                # estimate, which the controller then flew for real)
                self._last_imu_raw = (g, last[1])
        self._imu = ImuSample(stamped[0], stamped[1], t_ns, gyro, accel,
                              self._timebase.period_ns)
        self._imu_count += 1
        self._meters["imu"].add(t_ns)

    def _hold_accel_spike(self, accel: Vec3) -> Vec3:
        """``accel`` with an axis that jumped far beyond its typical step held at its last
        value (``accel_spike_factor``); at most one sample in a row per axis."""
        last = self._accel_last
        if last is None:
            self._accel_last = accel
            return accel
        cfg = self.config
        factor, floor = cfg.accel_spike_factor, cfg.accel_spike_floor_m_s2
        typical, held = self._accel_step, self._accel_held
        out = list(accel)
        for i in range(3):
            step = abs(accel[i] - last[i])
            limit = max(floor, factor * typical[i])
            if step > limit and not held[i]:
                out[i] = last[i]
                held[i] = True
                self._accel_spikes += 1
            else:
                held[i] = False
                # the average step, each step counted up to the limit (a spike taken as
                # real must not widen the limit for the next ones)
                typical[i] += (min(step, limit) - typical[i]) * ACCEL_STEP_GAIN
        # the held axes keep their last value, the others move on
        new = (out[0], out[1], out[2])
        self._accel_last = new
        return new

    def _on_motor(self, msg: mkm.MotorMessage, t_ns: int) -> None:
        cfg = self.config
        if not 1 <= msg.motor_id <= cfg.n_motors:
            self._malformed += 1
            return
        if (not abs(msg.speed_hz) <= cfg.max_motor_speed_hz
                or not msg.current_a <= cfg.max_motor_current_a
                or not abs(msg.throttle_raw) <= mkm.THROTTLE_RAW_MAX):
            # Beyond the BL-Ctrl's range: a corrupted frame (tk3 has no checksum).
            self._implausible += 1
            return
        if msg.emergency:
            state = MotorState.EMERGENCY
        elif msg.spinning:
            state = MotorState.SPINNING
        elif msg.starting:
            state = MotorState.STARTING
        else:
            state = MotorState.OFF
        self._motors[msg.motor_id - 1] = MotorStatus(
            msg.motor_id, state, abs(msg.speed_hz), msg.throttle_pct, msg.current_a, t_ns)
        self._motor_updates += 1
        if msg.motor_id == 1:
            self._meters["motor"].add(t_ns)

    def _on_stock(self, frame: framing_stock.StockFrame) -> None:
        if frame.cmd != b"V":
            return
        with contextlib.suppress(mkm.MalformedMessageError):
            version = mkm.decode_stock_message(frame.cmd, frame.data)
            if isinstance(version, mkm.VersionInfo):
                self._stock_version = version
                self._cond.notify_all()


STOCK_BAUD = 57_600
"""Line speed of the stock HiSystems firmware (fixed at compile time)."""


def probe(uri: str, config: FlightCtrlConfig | None = None) -> BoardIdentity:
    """Identify the board behind ``uri`` without configuring it (for ``fasthex probe``).

    Asks ``?`` and ``v`` at the URI's settings; if nothing answers and the URI is a
    ``serial://`` port at another speed, asks ``v`` again at 57600 baud, the fixed speed of the
    stock firmware. Raises :class:`FlightCtrlIdentityError` if no board answers.
    """
    with FlightCtrl.open(uri, config) as fc:
        try:
            return fc.identify()
        except FlightCtrlIdentityError as first:
            error = first
    parsed = parse_uri(uri)
    if parsed.scheme != "serial" or parsed.options.get("baud") == str(STOCK_BAUD):
        raise error
    options = {**parsed.options, "baud": str(STOCK_BAUD)}
    stock_uri = f"serial://{parsed.target}?" + "&".join(f"{k}={v}" for k, v in options.items())
    with FlightCtrl.open(stock_uri, config) as fc:
        return fc.identify(tk3=False)

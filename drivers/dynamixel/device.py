"""The FAST-Hex tilt servo: one Dynamixel MX-28T (Protocol 1.0, multi-turn) behind a 20:1 worm.

Wire protocol: Dynamixel Protocol 1.0 on a half-duplex TTL bus through a USB2Dynamixel/U2D2,
spoken by the official ``dynamixel-sdk`` (``PortHandler`` + ``PacketHandler(1.0)``, the float:
``"1.0"`` silently selects Protocol 2.0). Packets ``FF FF ID LEN INST params CHK`` with
``CHK = ~(ID + LEN + INST + sum(params)) & 0xFF`` (:mod:`drivers.dynamixel.protocol1`).
Registers: :mod:`drivers.dynamixel.control_table` (P1 addresses: Torque 24, Goal 30, Moving
Speed 32, Present 36..46).

URI: ``serial:///dev/ttyUSB1?baud=1000000&id=1``, ``pty:///path/of/a/pty?id=1`` or a bare path.
``baud`` must be one the SDK can open (1 Mbps recommended: Baud Rate register 1); ``id`` 0..253.

Per service cycle (``rate_hz``, 50 Hz by default): one WRITE of Goal Position (only when the
rate-limited goal moved) and one READ of the 11-byte block 36..46 (position, speed, load,
voltage, temperature, Registered, Moving); GroupBulkRead is broken for P1 in SDK 4.1.0.

Why a separate process: the SDK waits for every reply by polling ``read()`` for up to its
~34 ms timeout, burning a core and taking the GIL over and over. The servo is therefore served by
its own process (or, for comparison, a thread) and the control loop only touches a
shared-memory mailbox: :meth:`TiltServo.set_tilt` stores a goal, :meth:`TiltServo.latest`
copies the newest :class:`ServoState` (seqlock; never waits). In that process the serial port
gets a 1 ms read timeout, so the SDK's polling loop blocks in ``select()`` instead of spinning.
A lockstep flight is the exception (``isolation="inline"``): its loop waits for every cycle
anyway, at a fixed simulated time, so the SDK runs in the loop's thread, split in two: the
goal write and the READ request at :meth:`TiltServo.begin_cycle`, the reply at
:meth:`TiltServo.finish_cycle`; the servo answers while the tick computes. Two process hops
saved per cycle: in an Exp. 1 lockstep flight a cycle cost the tick 39 + 491 us (begin +
finish, medians) through the servo process, 37 + 69 us inline (the READ sent first thing in
the tick); the flight ran ~1.3x faster. ``benchmarks/bench_servo.py`` (4.) compares the two.

Configuration on every (re)connect: model 29 (an MX-28 with P2 firmware reports 30: refused),
firmware >= ``min_firmware``, SRL 2, Return Delay 0, multi-turn (CW = CCW limit = 4095), Moving
Speed for ``max_tilt_rate_deg_s`` at the tilt, goal = present, torque on, LED on. The LED is a
power-up marker: found off after a reconnect or a silent spell, the servo was power-cycled and
its turn count (the zero) is gone -> ``HOMING_REQUIRED`` until :meth:`TiltServo.home`.

Faults: a failed transaction is published at once (``NO_REPLY``, ``CORRUPT_REPLY``,
``DISCONNECTED``): within one period plus the SDK timeout (~54 ms at 50 Hz); independently,
:meth:`TiltServo.latest` turns a measurement older than ``stale_after_s`` (100 ms) into
``STALE``. The last measured tilt is kept through faults. Status error bits become
``SERVO_ERROR`` with ``ServoState.errors`` (an :class:`ErrorBit` flag set).

SDK traps handled here: a late reply taken as the answer to the next request (after any failed
transaction the worker waits ``resync_quiet_s`` and flushes the input; READ replies of the wrong
length are rejected), a port left ``is_using`` after an exception (the port is dropped and a new
``PortHandler`` opened), SRL < 2 (set to 2 with a write that expects no reply).

Geometry: ``tilt_rad = gear_ratio * servo_angle_rad`` (k = 0.05); Present Position ``p`` steps
(0.088 deg) maps to ``tilt = (p - zero_offset_steps) * RAD_PER_STEP * k``. The multi-turn count
does not survive a power cycle: :meth:`TiltServo.home` sets the zero offset at a known tilt.
"""

from __future__ import annotations

import contextlib
import logging
import math
import multiprocessing as mp
import signal
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from enum import IntEnum
from typing import Any, Literal, TypeVar
from urllib.parse import parse_qs, urlparse

from config.schema import ConfigValueError, spec
from drivers.dynamixel.control_table import (
    ALL_ERROR_BITS,
    MAX_ID,
    MODEL_MX28_P1,
    MODEL_MX28_P2,
    MULTI_TURN_LIMIT,
    MULTI_TURN_MAX_STEPS,
    MULTI_TURN_MIN_STEPS,
    NO_LOAD_SPEED_RPM,
    RAD_PER_STEP,
    STATE_BLOCK_LENGTH,
    STEPS_PER_TURN,
    ErrorBit,
    Mode,
    Reg,
    mode_from_limits,
    moving_speed_for_rate,
    signed_magnitude_11,
    speed_rad_s,
    to_signed16,
    to_unsigned16,
)
from drivers.errors import DriverError, TransportUriError
from drivers.shared_flag import SharedFlag
from drivers.transport import describe_open_error

log = logging.getLogger(__name__)

SDK_BAUDS = (9600, 19200, 38400, 57600, 115200, 230400, 460800, 500000, 576000, 921600,
             1000000, 1152000, 2000000, 2500000, 3000000, 3500000, 4000000)
"""The only rates ``PortHandler.setBaudRate`` accepts (dynamixel-sdk 4.1.0)."""
TURN_JUMP_STEPS = 2048
"""A Present Position jump larger than half a turn (plus what the servo can move at top speed in
the time between the two reads) means the turn count restarted: a power cycle."""
TOP_SPEED_STEPS_S = NO_LOAD_SPEED_RPM * STEPS_PER_TURN / 60.0


# ---------------------------------------------------------------------------- errors
class ServoError(DriverError):
    """A tilt-servo problem; ``device`` is the URI."""

    def __reduce__(self) -> tuple[Any, tuple[str, str]]:
        # Raised in the servo process and re-raised in the caller's: must survive pickling.
        return (type(self), (self.device, self.message))


class ServoIdentityError(ServoError):
    """The device answering is not an MX-28 with Protocol 1.0 firmware (or too old)."""


class ServoCommError(ServoError):
    """A transaction failed (no reply, corrupt reply, port gone)."""


# ---------------------------------------------------------------------------- config
@dataclass(frozen=True)
class TiltServoConfig:
    """How the tilt servo is reached, geared and served. Loadable with ``config.schema``."""

    uri: str = spec("serial:///dev/ttyUSB1?baud=1000000&id=1",
                    doc="serial:// or pty:// URI with baud and id, or a bare device path")
    gear_ratio: float = spec(0.05, gt=0.0, le=1.0, doc="tilt angle / servo angle (worm 20:1)")
    zero_offset_steps: int = spec(0, ge=MULTI_TURN_MIN_STEPS, le=MULTI_TURN_MAX_STEPS,
                                  doc="Present Position (steps) at tilt 0")
    max_tilt_deg: float = spec(35.0, gt=0.0, le=90.0, doc="goal tilts are clamped to [0, max]")
    max_tilt_rate_deg_s: float = spec(10.0, gt=0.0, le=60.0, doc="goal tilt rate limit")
    rate_hz: float = spec(50.0, ge=5.0, le=200.0, doc="service rate of the servo process")
    stale_after_s: float = spec(0.1, gt=0.0, le=5.0,
                                doc="a measurement older than this is reported STALE")
    resync_quiet_s: float = spec(0.1, ge=0.0, le=2.0,
                                 doc="wait after a failed transaction before flushing the input")
    reconnect_period_s: float = spec(0.2, gt=0.0, le=10.0, doc="retry period when unplugged")
    sdk_latency_timer_ms: float = spec(16.0, ge=1.0, le=1000.0,
                                       doc="dynamixel_sdk LATENCY_TIMER: timeout = 2x this + 2 ms")
    sdk_read_block_ms: float = spec(1.0, ge=0.0, le=10.0,
                                    doc="serial read timeout under the SDK's reply loop: its "
                                        "wait blocks in select() instead of spinning (0 = spin)")
    min_firmware: int = spec(0, ge=0, le=255, doc="refuse older firmware")
    rate_limit_goal: bool = spec(True, doc="ramp goals at max_tilt_rate_deg_s on the wall clock; "
                                 "False when the tilt planner already ramps them (lockstep: "
                                 "the servo's Moving Speed still bounds the motion)")
    late_reply_retries: int = spec(
        0, ge=0, le=5, doc="a requested cycle (on_request) of a servo that answered its last "
        "cycle is tried this many more times (after the resync wait) before a missing or "
        "garbled reply is reported "
        "(lockstep: an emulated servo starved by a loaded host is late, not faulty; a servo "
        "already in fault is never retried, so its 2 Hz retries cost one timeout each)")
    assume_homed: bool = spec(True, doc="trust zero_offset_steps at start (else home() first)")
    serve: Literal["periodic", "on_request"] = spec(
        "periodic", doc="periodic: a service cycle every 1/rate_hz s of wall time; on_request: "
        "only when the owner calls sync_cycle() or begin_cycle()/finish_cycle() (a lockstep "
        "flight, where the cycle must happen at a fixed simulated time)")

    def __post_init__(self) -> None:
        parse_servo_uri(self.uri)  # raises TransportUriError, a ValueError
        problem = tilt_range_problem(self.zero_offset_steps, self.max_tilt_deg, self.gear_ratio)
        if problem:
            raise ConfigValueError("zero_offset_steps", problem)

    @property
    def max_tilt_rad(self) -> float:
        return math.radians(self.max_tilt_deg)

    @property
    def max_tilt_rate_rad_s(self) -> float:
        return math.radians(self.max_tilt_rate_deg_s)


@dataclass(frozen=True, slots=True)
class ServoUri:
    port: str
    baud: int
    dxl_id: int


def parse_servo_uri(uri: str) -> ServoUri:
    """``serial:///dev/ttyUSB1?baud=1000000&id=1`` (or ``pty://``, or a bare path)."""
    if "://" not in uri:
        parsed_path, query = uri, ""
        if "?" in uri:
            parsed_path, query = uri.split("?", 1)
    else:
        parsed = urlparse(uri)
        if parsed.scheme not in ("serial", "pty"):
            raise TransportUriError(uri, f"unknown scheme {parsed.scheme!r} (serial, pty)")
        parsed_path, query = parsed.netloc + parsed.path, parsed.query
    if not parsed_path:
        raise TransportUriError(uri, "no device path")
    options = parse_qs(query, keep_blank_values=True)
    unknown = set(options) - {"baud", "id"}
    if unknown:
        raise TransportUriError(uri, f"unknown option(s) {sorted(unknown)} (baud, id)")
    try:
        baud = int(options.get("baud", ["1000000"])[-1])
        dxl_id = int(options.get("id", ["1"])[-1])
    except ValueError as exc:
        raise TransportUriError(uri, f"baud and id must be integers ({exc})") from None
    if baud not in SDK_BAUDS:
        raise TransportUriError(uri, f"baud {baud} cannot be opened by dynamixel-sdk")
    if not 0 <= dxl_id <= MAX_ID:
        raise TransportUriError(uri, f"id {dxl_id} outside 0..{MAX_ID}")
    return ServoUri(parsed_path, baud, dxl_id)


# ---------------------------------------------------------------------------- geometry
def tilt_range_problem(zero_offset_steps: int, max_tilt_deg: float, gear_ratio: float) -> str:
    """Why the tilt range [0, max] from this zero does not fit the multi-turn position range
    (empty if it does). The zero itself is within the range (its config spec); the tilt only
    adds steps to it."""
    top = tilt_to_steps(math.radians(max_tilt_deg), gear_ratio, zero_offset_steps)
    if top <= MULTI_TURN_MAX_STEPS:
        return ""
    return (f"the max tilt {max_tilt_deg:g} deg maps to {top} steps from a zero at "
            f"{zero_offset_steps}, beyond the servo's multi-turn range (+-{MULTI_TURN_MAX_STEPS});"
            f" expected a zero of at most {MULTI_TURN_MAX_STEPS - (top - zero_offset_steps)}")


def tilt_to_steps(tilt_rad: float, gear_ratio: float, zero_offset_steps: int) -> int:
    """Goal Position (steps) for a tilt angle: through the worm, then 0.088 deg steps."""
    return round(tilt_rad / gear_ratio / RAD_PER_STEP) + zero_offset_steps


def steps_to_tilt(steps: int, gear_ratio: float, zero_offset_steps: int) -> float:
    """Tilt angle (rad) of a Present Position (steps)."""
    return (steps - zero_offset_steps) * RAD_PER_STEP * gear_ratio


def rate_limited_goal(previous_rad: float, requested_rad: float, max_tilt_rad: float,
                      max_rate_rad_s: float, dt_s: float) -> float:
    """Next goal tilt: the request clamped to [0, max_tilt], approached at <= max_rate."""
    target = min(max(requested_rad, 0.0), max_tilt_rad)
    step = max_rate_rad_s * max(dt_s, 0.0)
    return previous_rad + max(-step, min(step, target - previous_rad))


# ---------------------------------------------------------------------------- state
class ServoHealth(IntEnum):
    """What the loop needs to know about the servo, worst last."""

    OK = 0
    NOT_STARTED = 1
    HOMING_REQUIRED = 2
    SERVO_ERROR = 3
    """The servo answers but its status error byte is set: see ``ServoState.errors``."""
    NO_REPLY = 4
    CORRUPT_REPLY = 5
    DISCONNECTED = 6
    WRONG_MODEL = 7
    MISCONFIGURED = 8
    STALE = 9
    """The mailbox has not been refreshed for ``stale_after_s`` (whatever the worker said)."""
    STOPPED = 10


@dataclass(frozen=True, slots=True)
class ServoState:
    """The newest measurement of the tilt servo. NaN until the first good reading.

    ``t_s`` is the ``time.monotonic()`` of the last good READ (system-wide clock, comparable
    across processes); ``age_s`` is how old it was when :meth:`TiltServo.latest` was called.
    The measured values are kept through faults: ``health`` says whether they are fresh.
    """

    t_s: float
    seq: int
    tilt_rad: float
    tilt_rate_rad_s: float
    servo_position_steps: int
    load_fraction: float
    voltage_v: float
    temperature_c: float
    moving: bool
    health: ServoHealth
    errors: ErrorBit
    goal_tilt_rad: float
    age_s: float
    homed: bool
    timeouts: int
    corrupt_replies: int
    reconnects: int
    implausible_readings: int = 0
    """Present Positions beyond the multi-turn range (±28672): dropped, never published."""

    @property
    def ok(self) -> bool:
        return self.health is ServoHealth.OK

    def describe(self) -> str:
        """One line for a person: tilt and goal (deg), motion, health and errors."""
        if math.isnan(self.t_s):
            return f"no reading yet (health {self.health.name})"
        return (f"tilt {math.degrees(self.tilt_rad):.2f} deg (goal "
                f"{math.degrees(self.goal_tilt_rad):.2f} deg), "
                f"{'moving' if self.moving else 'still'}, health {self.health.name}, errors "
                f"{error_names(self.errors)}, read {1e3 * self.age_s:.0f} ms ago")


def error_names(errors: ErrorBit) -> str:
    """The status error byte for a person: ``none``, or its flags (``voltage, overload``)."""
    names = [bit.name.lower() for bit in ErrorBit if bit and bit in errors and bit.name]
    unknown = int(errors) & ~int(ALL_ERROR_BITS)
    if unknown:
        names.append(f"0x{unknown:02x}")
    return ", ".join(names) or "none"


@dataclass(frozen=True, slots=True)
class ServoIdentity:
    """What :func:`probe_servo` found."""

    device: str
    dxl_id: int
    model_number: int
    firmware_version: int
    mode: Mode
    present_position_steps: int
    status_return_level: int
    return_delay_us: int

    @property
    def is_mx28_p1(self) -> bool:
        return self.model_number == MODEL_MX28_P1


_FRESH = (ServoHealth.OK, ServoHealth.SERVO_ERROR, ServoHealth.HOMING_REQUIRED)
#: the published health codes (a dict lookup: the enum call costs ~1 us in every loop tick)
_HEALTH_OF = {int(h): h for h in ServoHealth}
_ERRORS_OF: dict[int, ErrorBit] = {}


def _error_bits(code: int) -> ErrorBit:
    bits = _ERRORS_OF.get(code)
    if bits is None:
        bits = ErrorBit(code)
        if 0 <= code <= 0xFF:   # the error byte: at most 256 entries
            _ERRORS_OF[code] = bits
    return bits
"""Health states that come with a fresh measurement: they turn STALE when it ages."""


class _S(IntEnum):
    """Slots of the shared state array (doubles)."""

    SEQLOCK = 0
    T_S = 1
    SEQ = 2
    TILT = 3
    RATE = 4
    POS = 5
    LOAD = 6
    VOLT = 7
    TEMP = 8
    MOVING = 9
    HEALTH = 10
    ERRORS = 11
    GOAL = 12
    HOMED = 13
    TIMEOUTS = 14
    CORRUPT = 15
    RECONNECTS = 16
    ZERO = 17
    HEARTBEAT_T = 18
    IMPLAUSIBLE = 19
    N = 20


class _Mailbox:
    """Single-writer shared-memory mailbox: a seqlock-protected state array and a goal slot."""

    def __init__(self, ctx: Any) -> None:
        self.state = ctx.RawArray("d", int(_S.N))
        self.goal = ctx.RawArray("d", 1)
        nan = math.nan
        for i in range(int(_S.N)):
            self.state[i] = nan
        for slot in (_S.SEQLOCK, _S.SEQ, _S.ERRORS, _S.TIMEOUTS, _S.CORRUPT, _S.RECONNECTS,
                     _S.IMPLAUSIBLE):
            self.state[slot] = 0.0
        self.state[_S.HEALTH] = float(ServoHealth.NOT_STARTED)
        self.goal[0] = nan

    def publish(self, values: list[float]) -> None:
        state = self.state
        state[_S.SEQLOCK] += 1.0  # odd: being written
        state[1:] = values[1:]
        state[_S.SEQLOCK] += 1.0

    def snapshot(self, previous: list[float] | None) -> list[float] | None:
        state = self.state
        if previous is not None and state[_S.SEQLOCK] == previous[_S.SEQLOCK]:
            return previous  # nothing published since (the loop reads far more often)
        for _ in range(4):
            before = state[_S.SEQLOCK]
            if int(before) % 2 == 0:
                values = state[:]
                if state[_S.SEQLOCK] == before:
                    return values
        return previous  # a writer was mid-update every time: never wait for it


# ---------------------------------------------------------------------------- the SDK side
def _sdk() -> Any:
    import dynamixel_sdk
    return dynamixel_sdk


class _Link:
    """The SDK wrapped: result codes become exceptions, the port is dropped after one."""

    def __init__(self, uri: str, latency_timer_ms: float, read_block_ms: float = 1.0) -> None:
        self.uri = uri
        self.read_block_s = read_block_ms / 1000.0
        self.target = parse_servo_uri(uri)
        self.sdk = _sdk()
        self.sdk.port_handler.LATENCY_TIMER = latency_timer_ms
        self.latency_timer_ms = latency_timer_ms
        self.ph = self.sdk.PacketHandler(1.0)  # the float: "1.0" would be Protocol 2.0
        self.port: Any = None

    def cap_reply_wait(self, wait_s: float | None) -> None:
        """Wait at most ``wait_s`` for each reply from now on (None: the configured timeout,
        2 x the latency timer + 2 ms). The SDK reads its timeout from a module setting when a
        request goes out: one servo per process (the servo process, or the loop's thread)."""
        timer_ms = self.latency_timer_ms
        if wait_s is not None:
            timer_ms = min(timer_ms, max((wait_s * 1000.0 - 2.0) / 2.0, 1.0))
        self.sdk.port_handler.LATENCY_TIMER = timer_ms

    @property
    def is_open(self) -> bool:
        return self.port is not None

    def open(self) -> None:
        port = self.sdk.PortHandler(self.target.port)
        try:
            ok = port.openPort() and port.setBaudRate(self.target.baud)
        except Exception as exc:  # serial.SerialException, OSError, termios.error
            err = getattr(exc, "errno", None)  # absent, no permission: one line with the fix
            why = describe_open_error(self.target.port, err, str(exc)) if err else None
            raise ServoCommError(self.uri, why or f"cannot open: {exc}") from exc
        if not ok:
            with contextlib.suppress(Exception):
                port.closePort()
            raise ServoCommError(self.uri, "cannot open the port")
        # The SDK opens with timeout=0 and polls read() until its deadline: one core at 100 %.
        # A short read timeout makes each poll block in select() until bytes arrive; the SDK's
        # own deadline logic is unchanged (it just checks it at most every read_block_s).
        port.ser.timeout = self.read_block_s
        self.port = port

    def drop(self) -> None:
        """Close and forget the port (a fresh PortHandler clears the stuck is_using flag)."""
        if self.port is not None:
            with contextlib.suppress(Exception):
                self.port.is_using = False
                self.port.closePort()
        self.port = None

    def flush(self) -> None:
        if self.port is not None:
            self.port.is_using = False
            self.port.clearPort()

    def _check(self, what: str, result: int) -> None:
        if result != self.sdk.COMM_SUCCESS:
            text = self.ph.getTxRxResult(result)
            if result == self.sdk.COMM_RX_CORRUPT:
                raise _CorruptReplyError(self.uri, f"{what}: {text}") from None
            raise ServoCommError(self.uri, f"{what}: {text}") from None

    def call(self, what: str, fn: Any, *args: Any) -> Any:
        if self.port is None:
            raise _PortLostError(self.uri, f"{what}: port not open")
        try:
            return fn(self.port, self.target.dxl_id, *args)
        except ServoCommError:
            raise
        except Exception as exc:  # the SDK lets termios/serial/Index errors escape
            self.drop()
            raise _PortLostError(self.uri, f"{what}: {type(exc).__name__}: {exc}") from exc

    def ping(self) -> tuple[int, ErrorBit]:
        model, result, error = self.call("ping", self.ph.ping)
        self._check("ping", result)
        return model, ErrorBit(error & 0x7F)

    def read(self, reg: Reg, length: int) -> tuple[list[int], ErrorBit]:
        data, result, error = self.call(f"read {reg.name}", self.ph.readTxRx, int(reg), length)
        self._check(f"read {reg.name}", result)
        if len(data) != length:
            # A status packet meant for another request (a late reply): not ours.
            raise _CorruptReplyError(
                self.uri, f"read {reg.name}: {len(data)} bytes, expected {length}")
        return list(data), ErrorBit(error & 0x7F)

    def read_tx(self, reg: Reg, length: int) -> None:
        """The request half of :meth:`read` (the reply is awaited by :meth:`read_rx`)."""
        result = self.call(f"read {reg.name}", self.ph.readTx, int(reg), length)
        self._check(f"read {reg.name}", result)

    def read_rx(self, reg: Reg, length: int) -> tuple[list[int], ErrorBit]:
        """The reply half of :meth:`read`: the same checks."""
        data, result, error = self.call(f"read {reg.name}", self.ph.readRx, length)
        self._check(f"read {reg.name}", result)
        if len(data) != length:
            raise _CorruptReplyError(
                self.uri, f"read {reg.name}: {len(data)} bytes, expected {length}")
        return list(data), ErrorBit(error & 0x7F)

    def write(self, reg: Reg, size: int, value: int) -> ErrorBit:
        fn = {1: self.ph.write1ByteTxRx, 2: self.ph.write2ByteTxRx, 4: self.ph.write4ByteTxRx}
        result, error = self.call(f"write {reg.name}", fn[size], int(reg), value)
        self._check(f"write {reg.name}", result)
        return ErrorBit(error & 0x7F)

    def write_no_reply(self, reg: Reg, value: int) -> None:
        result = self.call(f"write {reg.name}", self.ph.write1ByteTxOnly, int(reg), value)
        self._check(f"write {reg.name}", result)

    def result_code(self, exc: ServoCommError) -> ServoHealth:
        if isinstance(exc, _PortLostError):
            return ServoHealth.DISCONNECTED
        if isinstance(exc, _CorruptReplyError):
            return ServoHealth.CORRUPT_REPLY
        return ServoHealth.NO_REPLY


class _PortLostError(ServoCommError):
    """The port raised (unplugged, EIO): it has been dropped."""


class _CorruptReplyError(ServoCommError):
    """A reply that cannot be the answer to the request."""


def _u16(data: list[int], i: int) -> int:
    return data[i] | (data[i + 1] << 8)


def probe_servo(uri: str, latency_timer_ms: float = 16.0,
                read_block_ms: float = 1.0) -> ServoIdentity:
    """Identify the servo at ``uri`` from the calling process (preflight / CLI; it busy-waits,
    so not from the control loop). Raises :class:`ServoCommError` if nothing answers."""
    link = _Link(uri, latency_timer_ms, read_block_ms)
    link.open()
    try:
        return _identify(link)
    finally:
        link.drop()


@dataclass(frozen=True, slots=True)
class ServoReading:
    """What :func:`read_servo` measured: the identity and the RAM state, as raw as it came."""

    identity: ServoIdentity
    goal_position_steps: int
    present_position_steps: int
    speed_servo_rad_s: float
    load_fraction: float
    voltage_v: float
    temperature_c: float
    moving: bool
    torque_enabled: bool
    led_on: bool
    """The driver leaves the LED on once it has configured the servo since its power-up."""


def read_servo(uri: str, latency_timer_ms: float = 16.0,
               read_block_ms: float = 1.0) -> ServoReading:
    """Identify the servo at ``uri`` and read its state with PING and READ only: nothing is
    written, EEPROM or RAM (``fasthex servo status``). Raises :class:`ServoCommError`."""
    link = _Link(uri, latency_timer_ms, read_block_ms)
    link.open()
    try:
        ident = _identify(link)
        torque, _ = _again(link.read, Reg.TORQUE_ENABLE, 2)  # Torque Enable (24), LED (25)
        goal = to_signed16(_u16(_again(link.read, Reg.GOAL_POSITION, 2)[0], 0))
        data, _ = _again(link.read, Reg.PRESENT_POSITION, STATE_BLOCK_LENGTH)
    finally:
        link.drop()
    return ServoReading(
        identity=ident, goal_position_steps=goal, present_position_steps=to_signed16(
            _u16(data, 0)), speed_servo_rad_s=speed_rad_s(signed_magnitude_11(_u16(data, 2))),
        load_fraction=0.001 * signed_magnitude_11(_u16(data, 4)), voltage_v=0.1 * data[6],
        temperature_c=float(data[7]), moving=bool(data[10]), torque_enabled=bool(torque[0]),
        led_on=bool(torque[1]))


#: bench identification and status: attempts at each of their requests, all of them reads (a
#: loaded host or a servo that was just powered may miss a reply; the SDK's own wait is only
#: ~34 ms: a `servo status` beside a test suite on 2 cores lost the reply to its first READ)
IDENTIFY_ATTEMPTS = 3

_T = TypeVar("_T")


def _again(request: Callable[..., _T], *args: Any) -> _T:
    """``request(*args)``, asked up to IDENTIFY_ATTEMPTS times while the servo does not
    answer or answers garbled (a lost port is not asked again)."""
    for attempt in range(IDENTIFY_ATTEMPTS - 1):
        try:
            return request(*args)
        except _PortLostError:
            raise
        except ServoCommError:
            log.debug("servo request %s failed (attempt %d)", request.__name__, attempt + 1)
    return request(*args)


def _identify(link: _Link) -> ServoIdentity:
    model, _ = _again(link.ping)
    firmware = _again(link.read, Reg.FIRMWARE_VERSION, 1)[0][0]
    eeprom, _ = _again(link.read, Reg.RETURN_DELAY_TIME, 5)
    srl = _again(link.read, Reg.STATUS_RETURN_LEVEL, 1)[0][0]
    present = to_signed16(_u16(_again(link.read, Reg.PRESENT_POSITION, 2)[0], 0))
    return ServoIdentity(
        device=link.uri, dxl_id=link.target.dxl_id, model_number=model,
        firmware_version=firmware, mode=mode_from_limits(_u16(eeprom, 1), _u16(eeprom, 3)),
        present_position_steps=present, status_return_level=srl,
        return_delay_us=2 * eeprom[0])


class _Worker:
    """The servo service loop. Runs in the servo process (or a thread) and owns the port."""

    def __init__(self, cfg: TiltServoConfig, mailbox: _Mailbox, conn: Any, stop: Any) -> None:
        self.cfg = cfg
        self.mailbox = mailbox
        self.conn = conn
        self.stop = stop
        self.link = _Link(cfg.uri, cfg.sdk_latency_timer_ms, cfg.sdk_read_block_ms)
        self.zero = cfg.zero_offset_steps
        self.homed = cfg.assume_homed
        self.values = [math.nan] * int(_S.N)
        self.values[_S.SEQ] = 0.0
        self.values[_S.HEALTH] = float(ServoHealth.NOT_STARTED)
        self.values[_S.ERRORS] = 0.0
        for slot in (_S.TIMEOUTS, _S.CORRUPT, _S.RECONNECTS, _S.IMPLAUSIBLE):
            self.values[slot] = 0.0
        self.configured = False
        self.goal_rad = math.nan      # last rate-limited goal written
        self.goal_t = 0.0
        self.last_present: int | None = None
        self.last_present_t = 0.0
        self.ever_configured = False
        self.recovering = False
        self.had_errors = False
        #: the last cycle got its answer (or the servo has just been configured): the next
        #: one may be retried (``late_reply_retries``)
        self.answered_last_cycle = False
        self.next_reconnect = 0.0

    # -- publishing
    def publish(self, health: ServoHealth, errors: ErrorBit | None = None) -> None:
        v = self.values
        v[_S.HEALTH] = float(health)
        if errors is not None:
            v[_S.ERRORS] = float(int(errors))
        v[_S.GOAL] = self.goal_rad
        v[_S.HOMED] = 1.0 if self.homed else 0.0
        v[_S.ZERO] = float(self.zero)
        v[_S.HEARTBEAT_T] = time.monotonic()
        self.mailbox.publish(v)

    # -- connection and configuration
    def connect(self) -> None:
        if not self.link.is_open:
            self.link.open()
            self.values[_S.RECONNECTS] += 1
        self.configure()

    def configure(self) -> None:
        link, cfg = self.link, self.cfg
        model, _ = link.ping()
        if model != MODEL_MX28_P1:
            why = ("an MX-28 running the Protocol 2.0 firmware" if model == MODEL_MX28_P2
                   else f"model {model}")
            raise ServoIdentityError(link.uri, f"expected an MX-28 (P1, model 29), found {why}")
        firmware = link.read(Reg.FIRMWARE_VERSION, 1)[0][0]
        if firmware < cfg.min_firmware:
            raise ServoIdentityError(link.uri, f"firmware {firmware} < {cfg.min_firmware}")
        try:
            srl = link.read(Reg.STATUS_RETURN_LEVEL, 1)[0][0]
        except ServoCommError:
            srl = 0  # SRL 0 does not answer READ
        if srl != 2:
            # With SRL < 2 every write*TxRx times out although applied: write without reply.
            link.write_no_reply(Reg.STATUS_RETURN_LEVEL, 2)
        if link.read(Reg.RETURN_DELAY_TIME, 1)[0][0] != 0:
            link.write(Reg.RETURN_DELAY_TIME, 1, 0)
        limits, _ = link.read(Reg.CW_ANGLE_LIMIT, 4)
        if mode_from_limits(_u16(limits, 0), _u16(limits, 2)) is not Mode.MULTI_TURN:
            link.write(Reg.CW_ANGLE_LIMIT, 4, MULTI_TURN_LIMIT | (MULTI_TURN_LIMIT << 16))
            limits, _ = link.read(Reg.CW_ANGLE_LIMIT, 4)
            if mode_from_limits(_u16(limits, 0), _u16(limits, 2)) is not Mode.MULTI_TURN:
                raise _MisconfiguredError(link.uri, "multi-turn mode refused (EEPROM locked?)")
        speed = moving_speed_for_rate(cfg.max_tilt_rate_rad_s / cfg.gear_ratio)
        link.write(Reg.MOVING_SPEED, 2, speed)
        self.check_power_marker()
        present = to_signed16(_u16(link.read(Reg.PRESENT_POSITION, 2)[0], 0))
        self.last_present, self.last_present_t = present, time.monotonic()
        # Hold where it is: goal = present before the torque comes on.
        link.write(Reg.GOAL_POSITION, 2, to_unsigned16(present))
        link.write(Reg.TORQUE_ENABLE, 1, 1)
        # LED on = "configured since power-up": RAM, so a power cycle clears it.
        link.write(Reg.LED, 1, 1)
        self.ever_configured = True
        self.recovering = False
        self.answered_last_cycle = True
        self.goal_rad = steps_to_tilt(present, cfg.gear_ratio, self.zero)
        self.goal_t = time.monotonic()
        self.configured = True

    def check_power_marker(self) -> None:
        """After a reconnect or a silent spell: if the LED we left on is off, the servo was
        power-cycled, and its turn count (our zero) is gone."""
        if self.ever_configured and self.link.read(Reg.LED, 1)[0][0] == 0:
            log.warning("%s: servo was power-cycled: home it again", self.link.uri)
            self.homed = False
            self.configured = False

    # -- one cycle
    def cycle(self) -> tuple[ServoHealth, ErrorBit]:
        errors = self.cycle_start()
        data, err = self.link.read(Reg.PRESENT_POSITION, STATE_BLOCK_LENGTH)
        return self.cycle_end(data, errors | err)

    def cycle_start(self) -> ErrorBit:
        """A cycle up to its READ: the power-marker check after a fault, the goal write."""
        cfg, link = self.cfg, self.link
        errors = ErrorBit.NONE
        if self.recovering:
            self.check_power_marker()
            self.recovering = False
            if not self.configured:
                raise _ReconfigureError(link.uri, "power cycle: configure again")
        now = time.monotonic()
        requested = self.mailbox.goal[0]
        if self.homed and math.isfinite(requested) and math.isfinite(self.goal_rad):
            # dt is the real elapsed time, stalls included: the goal keeps to the configured rate
            # on average, and the servo's Moving Speed (set to the same rate) bounds the motion.
            dt = now - self.goal_t if cfg.rate_limit_goal else math.inf
            goal = rate_limited_goal(self.goal_rad, requested, cfg.max_tilt_rad,
                                     cfg.max_tilt_rate_rad_s, dt)
            steps = tilt_to_steps(goal, cfg.gear_ratio, self.zero)
            if steps != tilt_to_steps(self.goal_rad, cfg.gear_ratio, self.zero):
                errors |= link.write(Reg.GOAL_POSITION, 2, to_unsigned16(steps))
            self.goal_rad = goal
        self.goal_t = now
        return errors

    def cycle_end(self, data: list[int], errors: ErrorBit) -> tuple[ServoHealth, ErrorBit]:
        """A cycle from its READ's answer (the state block) on: checks, then the state."""
        cfg = self.cfg
        t_s = time.monotonic()
        present = to_signed16(_u16(data, 0))
        if not MULTI_TURN_MIN_STEPS <= present <= MULTI_TURN_MAX_STEPS:
            # No MX-28 reports this in multi-turn mode: a corrupted reply. Keep the last
            # reading (its age shows it) and count the drop.
            self.values[_S.IMPLAUSIBLE] += 1
            return ServoHealth.CORRUPT_REPLY, errors
        if self.last_present is not None:
            reach = TURN_JUMP_STEPS + TOP_SPEED_STEPS_S * (t_s - self.last_present_t)
            if abs(present - self.last_present) > reach:
                # Farther than the servo can move: the turn count restarted (a power cycle too
                # short to miss a reply). The zero is lost; configure again, wait for home().
                self.homed = False
                self.configured = False
        self.last_present, self.last_present_t = present, t_s
        v = self.values
        v[_S.T_S] = t_s
        v[_S.SEQ] += 1
        v[_S.POS] = float(present)
        v[_S.TILT] = steps_to_tilt(present, cfg.gear_ratio, self.zero)
        v[_S.RATE] = cfg.gear_ratio * speed_rad_s(signed_magnitude_11(_u16(data, 2)))
        v[_S.LOAD] = 0.001 * signed_magnitude_11(_u16(data, 4))
        v[_S.VOLT] = 0.1 * data[6]
        v[_S.TEMP] = float(data[7])
        v[_S.MOVING] = float(data[10])
        if errors:
            self.had_errors = True
            return ServoHealth.SERVO_ERROR, errors
        if self.had_errors:
            # The Shutdown mask may have cut the torque during the fault: configure again.
            self.had_errors = False
            self.configured = False
        return (ServoHealth.OK if self.homed else ServoHealth.HOMING_REQUIRED), errors

    # -- commands from the owner (rare; the owner waits for the answer)
    def serve_commands(self) -> None:
        while True:
            try:
                if not self.conn.poll(0):
                    return
                request_id, *request = self.conn.recv()
            except (EOFError, OSError):  # the owner is gone (killed): stop serving
                self.stop.set()
                self.conn = None
                return
            if not self.configured:
                error = ServoCommError(self.link.uri, f"{request[0]}: servo not connected")
                self.conn.send((request_id, "error", error))
                continue
            try:
                self.conn.send((request_id, "ok", self.command(*request)))
            except ServoCommError as exc:
                self.conn.send((request_id, "error", exc))
                raise  # the link needs the usual recovery
            except (ServoError, ValueError) as exc:
                self.conn.send((request_id, "error", exc))

    def command(self, name: str, *args: Any) -> Any:
        if name == "identify":
            return _identify(self.link)
        if name == "home":
            at_tilt = float(args[0])
            present = to_signed16(_u16(self.link.read(Reg.PRESENT_POSITION, 2)[0], 0))
            self.zero = present - tilt_to_steps(at_tilt, self.cfg.gear_ratio, 0)
            self.homed = True
            self.goal_rad = at_tilt
            self.goal_t = time.monotonic()
            return self.zero
        if name == "torque":
            return self.link.write(Reg.TORQUE_ENABLE, 1, int(bool(args[0])))
        if name == "cycle":
            return self.requested_cycle()
        raise ValueError(f"unknown servo command {name!r}")

    def requested_cycle(self, first: Callable[[], tuple[ServoHealth, ErrorBit]] | None = None
                        ) -> int:
        """A cycle asked for by the owner (``serve="on_request"``), with the late-reply
        retries; published, its health returned. ``first`` runs the first attempt instead of
        :meth:`cycle` (the inline owner's split cycle); the retries are whole cycles."""
        retries = self.cfg.late_reply_retries if self.answered_last_cycle else 0
        for attempt in range(retries + 1):
            try:
                health, errors = first() if attempt == 0 and first is not None \
                    else self.cycle()
                break
            except _PortLostError:
                raise
            except ServoCommError as exc:
                if attempt == retries or isinstance(exc, _ReconfigureError):
                    self.answered_last_cycle = False
                    raise
                # late, not (yet) faulty: counted, not published; resync, ask again
                self._count_failure(exc)
                log.debug("%s (retrying)", exc)
                if not self._resync():
                    raise
        self.answered_last_cycle = True
        self.publish(health, errors)
        return int(health)

    def fail(self, exc: ServoCommError) -> None:
        self.recovering = True
        health = self._count_failure(exc)
        self.publish(health)
        log.debug("%s", exc)
        if health is ServoHealth.DISCONNECTED:
            self.configured = False
            self.next_reconnect = time.monotonic() + self.cfg.reconnect_period_s
            return
        self._resync()

    def _count_failure(self, exc: ServoCommError) -> ServoHealth:
        """Count a failed transaction (timeouts or corrupt replies); its health."""
        health = self.link.result_code(exc)
        if health is not ServoHealth.DISCONNECTED:
            self.values[_S.CORRUPT if health is ServoHealth.CORRUPT_REPLY
                        else _S.TIMEOUTS] += 1
        return health

    def _resync(self) -> bool:
        """A late reply could still arrive and answer the next request: wait, then flush.
        False when stopping, or when the port died while we waited."""
        if self.stop.wait(self.cfg.resync_quiet_s):
            return False
        try:
            self.link.flush()
        except Exception:  # the port died while we waited
            self.link.drop()
            self.configured = False
            return False
        return True

    def ready(self) -> bool:
        """Configured, or configured by the connection attempt made now if one is due (the
        inline owner's check before each request: the servo process's loop does the same)."""
        return self.configured or (time.monotonic() >= self.next_reconnect
                                   and self.try_connect())

    def try_connect(self) -> bool:
        """One attempt to open and configure the servo; a failure is published, never raised
        (a lost port or a refused servo is tried again after ``reconnect_period_s``, a missing
        or garbled reply after the resync wait). True when configured."""
        try:
            self.connect()
        except ServoIdentityError as exc:
            log.error("%s", exc)
            self.publish(ServoHealth.WRONG_MODEL)
            self.link.drop()
            self.next_reconnect = time.monotonic() + self.cfg.reconnect_period_s
        except _MisconfiguredError as exc:
            log.error("%s", exc)
            self.publish(ServoHealth.MISCONFIGURED)
            self.next_reconnect = time.monotonic() + self.cfg.reconnect_period_s
        except ServoCommError as exc:
            if isinstance(exc, _PortLostError) or not self.link.is_open:
                self.publish(ServoHealth.DISCONNECTED)
                self.next_reconnect = time.monotonic() + self.cfg.reconnect_period_s
            else:
                self.fail(exc)
        return self.configured

    def run(self) -> None:
        period = 1.0 / self.cfg.rate_hz
        deadline = time.monotonic()
        while not self.stop.is_set():
            if self.conn is not None:
                try:
                    self.serve_commands()
                except ServoCommError as exc:
                    self.fail(exc)
                    continue
            if not self.configured:
                if time.monotonic() < self.next_reconnect:
                    self.stop.wait(min(period, self.next_reconnect - time.monotonic()))
                    continue
                if not self.try_connect():
                    continue
            if self.cfg.serve == "on_request":
                if self.conn is not None:
                    self.conn.poll(period)  # wake for the next request
                else:
                    self.stop.wait(period)
                continue
            try:
                health, errors = self.cycle()
            except _ReconfigureError:
                self.publish(ServoHealth.HOMING_REQUIRED)
                continue
            except ServoCommError as exc:
                self.fail(exc)
                deadline = time.monotonic()
                continue
            self.publish(health, errors)
            deadline += period
            wait = deadline - time.monotonic()
            if wait < -period:
                deadline = time.monotonic()  # overran: do not try to catch up
            elif wait > 0:
                self.stop.wait(wait)
        self.shutdown()

    def shutdown(self) -> None:
        """Torque off, then let go of the port."""
        if self.link.is_open:
            try:
                self.link.write(Reg.TORQUE_ENABLE, 1, 0)
            except ServoCommError as exc:
                log.warning("torque off failed: %s", exc)
        self.link.drop()
        self.publish(ServoHealth.STOPPED)


class _MisconfiguredError(ServoError):
    pass


class _ReconfigureError(ServoCommError):
    """Not a fault of the link: the servo must be configured again before the next cycle."""


def _run_worker(cfg: TiltServoConfig, mailbox: _Mailbox, conn: Any, stop: Any,
                in_process: bool) -> None:
    if in_process:
        # Ctrl-C, SIGTERM and SIGHUP to the process group belong to the flight state machine
        # (land first): the servo process keeps holding the tilt until it is told to stop.
        # Ctrl-\ would kill it and Ctrl-Z (and a background job's terminal stops) freeze it
        # in flight: ignored.
        stop_signals = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
        for sig in (*stop_signals, signal.SIGQUIT, signal.SIGTSTP, signal.SIGTTIN,
                    signal.SIGTTOU):
            signal.signal(sig, signal.SIG_IGN)
        # the owner may have started us with them blocked (so that none kills us before
        # this point): ignored now, they can be let through
        signal.pthread_sigmask(signal.SIG_UNBLOCK, stop_signals)
        logging.basicConfig(level=logging.WARNING)
    _Worker(cfg, mailbox, conn, stop).run()


# ---------------------------------------------------------------------------- the loop side
class TiltServo:
    """The tilt servo as the 500 Hz loop sees it: a mailbox, never a wait.

    ``set_tilt`` (the ``TiltCommandSink``) stores the goal; ``latest`` returns the newest
    :class:`ServoState`. The SDK runs in a child process (``isolation="process"``, the default)
    so its busy-waiting never takes the loop's GIL; ``"thread"`` exists for comparison.
    ``"inline"`` (``serve="on_request"`` only: lockstep flights, where the loop waits for the
    cycle anyway) runs it in the caller's thread: :meth:`begin_cycle` writes the goal and sends
    the READ, :meth:`finish_cycle` takes its reply, so the servo answers while the loop computes,
    with no process between them.
    The process is started with ``spawn`` (safe in a process that already runs threads), so a
    script that starts it needs the usual ``if __name__ == "__main__":`` guard.
    """

    def __init__(self, config: TiltServoConfig,
                 isolation: Literal["process", "thread", "inline"] = "process") -> None:
        if isolation == "inline" and config.serve != "on_request":
            raise ValueError(f"{config.uri}: an inline servo is served on request only "
                             f"(serve: on_request), not {config.serve!r}")
        self.config = config
        self.isolation = isolation
        self._ctx = mp.get_context("spawn")
        self._mailbox = _Mailbox(self._ctx)
        self._stop: Any = None
        self._runner: mp.process.BaseProcess | threading.Thread | None = None
        self._conn: Any = None
        self._request_lock = threading.Lock()
        self._request_id = 0
        self._cycle_id: int | None = None
        self._last: list[float] | None = None
        self._stopped = False
        self._inline: _Worker | None = None  # isolation="inline": the worker, in this thread
        #: the second half of a begun inline cycle, or why none was begun ("not connected")
        self._inline_pending: Callable[[], tuple[ServoHealth, ErrorBit]] | ServoCommError \
            | None = None

    # -- lifecycle
    def start(self) -> TiltServo:
        """Start serving (returns at once; ``latest().health`` says when it is connected)."""
        if self._runner is not None or self._inline is not None:
            return self
        self._stopped = False
        if self.isolation == "inline":
            # connected at the first request or cycle (as the servo process would, soon after)
            self._inline = _Worker(self.config, self._mailbox, None, threading.Event())
            return self
        ours, theirs = self._ctx.Pipe()
        self._conn = ours
        self._stopped = False
        if self.isolation == "process":
            # not an Event: its set() would wait for ever on a servo process that died asleep
            # in its wait (drivers.shared_flag)
            self._stop = SharedFlag(self._ctx)
            self._runner = self._ctx.Process(
                target=_run_worker, name="tilt-servo", daemon=True,
                args=(self.config, self._mailbox, theirs, self._stop, True))
        else:
            self._stop = threading.Event()
            self._runner = threading.Thread(
                target=_run_worker, name="tilt-servo", daemon=True,
                args=(self.config, self._mailbox, theirs, self._stop, False))
        self._runner.start()
        return self

    def stop(self, timeout_s: float = 5.0) -> None:
        """Torque off and stop the servo process (the tilt holds: the worm is self-locking)."""
        if self._inline is not None:
            self._inline.shutdown()
            self._inline, self._inline_pending = None, None
            self._stopped = True
            return
        if self._runner is None:
            return
        self._stop.set()
        self._runner.join(timeout_s)
        if isinstance(self._runner, mp.process.BaseProcess) and self._runner.is_alive():
            self._runner.terminate()
            self._runner.join(1.0)
        self._runner = None
        self._stopped = True

    close = stop

    def __enter__(self) -> TiltServo:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- the loop-facing API
    def set_tilt(self, tilt_rad: float) -> None:
        """Goal tilt angle alpha (rad). Clamped to [0, max tilt] and rate-limited by the servo
        process. Stores one float: never blocks."""
        if not math.isfinite(tilt_rad):
            raise ValueError(f"{self.config.uri}: tilt goal must be finite, got {tilt_rad}")
        self._mailbox.goal[0] = min(max(tilt_rad, 0.0), self.config.max_tilt_rad)

    def latest(self, now_s: float | None = None, *, as_measured: bool = False) -> ServoState:
        """The newest state; ``now_s`` (monotonic) defaults to ``time.monotonic()``.

        ``as_measured``: its age taken at its own measurement (0), for the answer of a cycle
        just run on request, whose measurement is this cycle's however late the caller got to
        read it (a lockstep loop descheduled for 100 ms on a loaded host is not a stale servo)."""
        values = self._mailbox.snapshot(self._last)
        if values is None:
            values = list(self._mailbox.state)
        self._last = values
        t_s = values[_S.T_S]
        now = t_s if as_measured and math.isfinite(t_s) else (
            time.monotonic() if now_s is None else now_s)
        age = now - t_s if math.isfinite(t_s) else math.inf
        health = _HEALTH_OF[int(values[_S.HEALTH])]
        if self._stopped:
            health = ServoHealth.STOPPED
        elif health in _FRESH and age > self.config.stale_after_s:
            # The worker last said all was well but has not measured since: it is stuck,
            # starved or gone. (A fault it reported stays that fault.)
            health = ServoHealth.STALE
        pos = values[_S.POS]
        return ServoState(
            t_s=t_s, seq=int(values[_S.SEQ]), tilt_rad=values[_S.TILT],
            tilt_rate_rad_s=values[_S.RATE],
            servo_position_steps=int(pos) if math.isfinite(pos) else 0,
            load_fraction=values[_S.LOAD], voltage_v=values[_S.VOLT],
            temperature_c=values[_S.TEMP], moving=values[_S.MOVING] == 1.0,
            health=health, errors=_error_bits(int(values[_S.ERRORS])),
            goal_tilt_rad=values[_S.GOAL], age_s=age, homed=values[_S.HOMED] == 1.0,
            timeouts=int(values[_S.TIMEOUTS]), corrupt_replies=int(values[_S.CORRUPT]),
            reconnects=int(values[_S.RECONNECTS]),
            implausible_readings=int(values[_S.IMPLAUSIBLE]))

    # -- rare requests (preflight, bench): these wait for the servo process
    def _request(self, timeout_s: float, *request: Any) -> Any:
        if self._inline is not None:  # the SDK's own timeouts bound the wait
            with self._request_lock:
                return self._inline_call(lambda w: w.command(*request), request[0])
        with self._request_lock:
            request_id = self._send_request(*request)
            return self._await_answer(request_id, request[0], timeout_s)

    def _inline_call(self, fn: Callable[[_Worker], Any], what: str) -> Any:
        """Run ``fn`` on the inline worker as the servo process serves a request: connected
        first if it is not (a failed attempt: "not connected"), a link failure recovered from
        (``_Worker.fail``) and raised."""
        worker = self._inline
        assert worker is not None
        if not worker.ready():
            raise ServoCommError(self.config.uri, f"{what}: servo not connected")
        try:
            return fn(worker)
        except ServoCommError as exc:
            worker.fail(exc)
            raise

    def _send_request(self, *request: Any) -> int:
        if self._runner is None:
            raise ServoError(self.config.uri, "servo not started")
        self._request_id += 1
        self._conn.send((self._request_id, *request))
        return self._request_id

    def _await_answer(self, request_id: int, what: str, timeout_s: float) -> Any:
        deadline = time.monotonic() + timeout_s
        while True:
            # Answers to earlier requests that timed out are still in the pipe: skip them.
            if not self._conn.poll(max(0.0, deadline - time.monotonic())):
                raise ServoCommError(self.config.uri, f"{what}: no answer in {timeout_s} s")
            answer_id, status, value = self._conn.recv()
            if answer_id == request_id:
                break
        if status == "error":
            raise value
        return value

    def sync_cycle(self, timeout_s: float) -> ServoState:
        """Run one service cycle now (goal write + state read) and return its measurement.

        For ``serve="on_request"`` (lockstep flights): the caller blocks for one bus round trip
        (about 1.3 ms), so the exchange happens at a fixed simulated time. Raises
        :class:`ServoCommError` if the servo process does not answer within ``timeout_s``."""
        self.begin_cycle(timeout_s)
        return self.finish_cycle(timeout_s)

    def begin_cycle(self, timeout_s: float | None = None) -> None:
        """Start one service cycle and return at once; :meth:`finish_cycle` waits for it.

        Lets a lockstep loop compute while the servo process talks to the bus (the bus
        exchange happens between the two calls: keep the simulated time fixed there).
        ``timeout_s``: inline, the longest each reply of this cycle is waited for, if shorter
        than the SDK's timeout (a servo already in fault is asked briefly); the servo process
        does not use it (the wait is :meth:`finish_cycle`'s)."""
        if self._inline is not None:
            with self._request_lock:
                self._inline.link.cap_reply_wait(timeout_s)
                self._inline_pending = self._begin_inline_cycle()
            return
        with self._request_lock:
            # a cycle never finished (its answer is skipped by id) is simply superseded
            self._cycle_id = self._send_request("cycle")

    def _begin_inline_cycle(self) -> Callable[[], tuple[ServoHealth, ErrorBit]] | ServoCommError:
        """The first half of an inline cycle (goal write, READ sent); returns the second half,
        which raises what the first half met (its failure then takes the usual retries), or
        the "not connected" answer of a servo that could not be configured."""
        worker = self._inline
        assert worker is not None
        if not worker.ready():
            return ServoCommError(self.config.uri, "cycle: servo not connected")
        try:
            errors = worker.cycle_start()
            worker.link.read_tx(Reg.PRESENT_POSITION, STATE_BLOCK_LENGTH)
        except ServoCommError as exc:
            failed = exc

            def reraise() -> tuple[ServoHealth, ErrorBit]:
                raise failed
            return reraise

        def take_reply() -> tuple[ServoHealth, ErrorBit]:
            data, err = worker.link.read_rx(Reg.PRESENT_POSITION, STATE_BLOCK_LENGTH)
            return worker.cycle_end(data, errors | err)
        return take_reply

    def finish_cycle(self, timeout_s: float) -> ServoState:
        """Wait for the cycle of :meth:`begin_cycle`; its measurement (``ServoCommError`` if the
        servo process does not answer within ``timeout_s``). Inline, the SDK's own reply
        timeout (capped by :meth:`begin_cycle`'s ``timeout_s``) bounds each attempt."""
        if self._inline is not None:
            with self._request_lock:
                pending, self._inline_pending = self._inline_pending, None
                if pending is None:
                    raise ServoError(self.config.uri, "no service cycle pending")
                worker = self._inline
                try:
                    if isinstance(pending, ServoCommError):
                        raise pending  # not connected: nothing to recover from
                    try:
                        worker.requested_cycle(pending)
                    except ServoCommError as exc:
                        worker.fail(exc)
                        raise
                finally:
                    worker.link.cap_reply_wait(None)
            return self.latest(as_measured=True)
        with self._request_lock:
            request_id, self._cycle_id = self._cycle_id, None
            if request_id is None:
                raise ServoError(self.config.uri, "no service cycle pending")
            self._await_answer(request_id, "cycle", timeout_s)
        return self.latest(as_measured=True)

    def probe(self, timeout_s: float = 2.0) -> ServoIdentity:
        """Identify the servo (model, firmware, mode): through the servo process if started."""
        if self._runner is None and self._inline is None:
            return probe_servo(self.config.uri, self.config.sdk_latency_timer_ms,
                               self.config.sdk_read_block_ms)
        identity: ServoIdentity = self._request(timeout_s, "identify")
        return identity

    def home(self, at_tilt_rad: float = 0.0, timeout_s: float = 2.0) -> int:
        """Zero calibration: the mechanism is at ``at_tilt_rad`` now (jig or end stop); returns
        the new zero offset (Present Position at tilt 0), to be saved in the config."""
        return int(self._request(timeout_s, "home", at_tilt_rad))

    def torque(self, enabled: bool, timeout_s: float = 2.0) -> ErrorBit:
        return ErrorBit(self._request(timeout_s, "torque", enabled))

    def wait_for(self, predicate: Any, timeout_s: float) -> ServoState:
        """Poll :meth:`latest` until ``predicate(state)`` (bench/preflight helper, not the loop).
        Raises :class:`ServoError` with the last state on timeout."""
        deadline = time.monotonic() + timeout_s
        state = self.latest()
        while not predicate(state):
            if time.monotonic() > deadline:
                raise ServoError(self.config.uri, f"timed out after {timeout_s:.1f} s; last "
                                 f"state: {state.describe()}")
            time.sleep(1.0 / self.config.rate_hz)
            state = self.latest()
        return state

    def with_config(self, **changes: Any) -> TiltServoConfig:
        return replace(self.config, **changes)

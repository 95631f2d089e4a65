"""MikroKopter Flight-Ctrl messages: one frozen dataclass per message, SI units in field names.

Pure codecs over *unframed* message bytes; the framings live in :mod:`.framing_tk3` and
:mod:`.framing_stock`.

tk3 (LAAS tk3-mikrokopter firmware, big-endian; ``encode()`` returns ``cmd + payload``)

======================  =====  =========================================================
host -> board           cmd    payload
======================  =====  =========================================================
:class:`Identify`       ``?``  none; the board answers ``?`` + ASCII id (``mkfl1.8``)
:class:`SetStreamPeriod` ``i m b c``  ``u32`` period in µs (0 = off) of IMU / motor /
                               battery / magnetometer streams
:class:`StartMotors`    ``g``  ``u8`` motor id (1-based); none = all (firmware < 2016-11)
:class:`StopMotors`     ``x``  none = all, or ``u8`` motor id
:class:`SpinRates`      ``w``  ``s16`` half period per motor, ``p = 500000 / ω`` (ω in Hz,
                               truncated toward 0; sign = direction; ``|ω| < 15.26`` -> ±32767)
:class:`Throttles`      ``q``  ``s16`` per motor, open loop, −1023..1023 (= % × 1023/100)
:class:`Beep`           ``~``  ``u16`` frequency in Hz
======================  =====  =========================================================

======================  =====  =========================================================
board -> host           cmd    payload (length includes the cmd byte)
======================  =====  =========================================================
:class:`ImuMessage`     ``I``  14: ``u8 seq; s16 ax, ay, az; s16 gx, gy, gz``; ×1e-3 m/s², rad/s
:class:`MagMessage`     ``C``  8: ``u8 seq; s16 mx, my, mz``; ×1e-8 T
:class:`MotorMessage`   ``M``  9: ``u8 seq; u8 state; s16 half period; s16 throttle; u16 mA``;
                               state: 0x80 emergency, 0x20 spinning, 0x10 starting, low
                               nibble = motor id
:class:`BatteryMessage` ``B``  4: ``u8 seq; u16 mV``
:class:`ClockRateMessage` ``T``  3: ``u8 id; u8 rate``
:class:`IdentityMessage` ``?``  ASCII id
:class:`TextMessage`    ``N A E``  info / warning / error text
======================  =====  =========================================================

A message of the wrong length is rejected (:class:`MalformedMessageError`), as the LAAS host does.

Stock MikroKopter (HiSystems FlightCtrl V2.12a, little-endian AVR structs; ``payload()`` gives
the bytes before base64 framing; decoders truncate the over-decoded payload to the struct size):
``v``/:class:`VersionInfo` ``V`` (10 B), ``d``/:class:`DebugOut` ``D`` (66 B), ``c``/:class:`Data3D`
``C`` (14 B), ``b`` :class:`ExternControl` (7 B) / ``B`` ack, ``t`` :class:`EngineTest` (16 or 4 B)
/ ``T`` ack.

IMU axes and scales: the board sends its own axes; :class:`ImuAxes` is the single place that maps
them to the body frame of ``sim_backend/vehicle.py`` (x towards propeller 1, z up; at rest the
accelerometer reads +g on z). The emulator encodes with the same object, so both ends agree.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Sequence
from dataclasses import dataclass
from enum import Enum
from typing import ClassVar, Self

from config.schema import ConfigValueError

__all__ = [
    "BOARD_MESSAGES",
    "BOARD_MESSAGE_BYTES",
    "HALF_PERIOD_SLOWEST",
    "MAX_SPIN_HZ",
    "MAX_STREAM_PERIOD_US",
    "MIN_MOTOR_PERIOD_US",
    "MIN_SPIN_HZ",
    "MIN_STREAM_PERIOD_US",
    "THROTTLE_RAW_MAX",
    "BatteryMessage",
    "Beep",
    "BoardMessage",
    "ClockRateMessage",
    "Data3D",
    "Data3DRequest",
    "DebugOut",
    "DebugRequest",
    "EngineTest",
    "EngineTestAck",
    "ExternControl",
    "ExternControlAck",
    "HostMessage",
    "Identify",
    "IdentityMessage",
    "ImuAxes",
    "ImuMessage",
    "MagMessage",
    "MalformedMessageError",
    "MotorMessage",
    "SetStreamPeriod",
    "SpinRates",
    "StartMotors",
    "StockMessage",
    "StopMotors",
    "Stream",
    "TextMessage",
    "Throttles",
    "VersionInfo",
    "VersionRequest",
    "decode_board_message",
    "decode_host_message",
    "decode_stock_message",
    "half_period_to_spin_hz",
    "spin_hz_to_half_period",
]

Vec3 = tuple[float, float, float]

HALF_PERIOD_SLOWEST = 32767
"""The ``w`` sentinel for "slowest speed" (sign = direction)."""
MIN_SPIN_HZ = 1e6 / 65535
"""Below this spin rate (≈15.26 Hz) the half period does not fit: the sentinel is sent."""
_HALF_PERIOD_NUM = 500_000.0  # 1e6 / 2: half period in µs of a rotation at 1 Hz
MAX_SPIN_HZ = 500.0
#: the ``I`` frame's accelerometer limit: an s16 of mm/s^2 clips at +-32.767 m/s^2 (3.3 g, below
#: the sensor's own 8 g), so a hard impact reads as a run of samples at this value
IMU_ACCEL_WIRE_LIMIT_M_S2 = 32.767
"""Fastest spin rate a BL-Ctrl can report or be held to (30 000 rpm; half period 1000 µs).
The FAST-Hex propellers top out near 102 Hz and hobby outrunners near 300 Hz: a faster reading
is a corrupted frame, never a motor."""
THROTTLE_RAW_MAX = 1023
"""Open-loop throttle full scale (100 %); ``|throttle| > 1023`` cannot come from a BL-Ctrl."""
MIN_STREAM_PERIOD_US = 500
"""Shortest stream period the board supports: 2 kHz, the top rate of ``i`` (tk3 §4.2)."""
MIN_MOTOR_PERIOD_US = 2000
"""Shortest ``m`` period: 500 Hz. Each period sends one 11-byte ``M`` frame per motor, six of
them 330 kbit/s on the 500 kbit/s line (tk3 §5); faster cannot leave the board."""
MAX_STREAM_PERIOD_US = 1_000_000
"""Longest stream period the board keeps: 1 s (the 1 Hz battery stream of the LAAS host)."""


class MalformedMessageError(ValueError):
    """A deframed message with an unknown command or the wrong length for its command."""

    def __init__(self, cmd: bytes, reason: str) -> None:
        self.cmd = cmd
        self.reason = reason
        super().__init__(f"bad {cmd!r} message: {reason}")


def spin_hz_to_half_period(speed_hz: float) -> int:
    """The tk3 ``w`` value for a spin rate in Hz (rev/s): ``int(500000 / ω)`` truncated toward 0.

    ``|ω| < 1e6/65535`` (≈15.26 Hz, 0 included) gives the slowest-speed sentinel ±32767; the
    sign of ``ω`` selects the direction (0 counts as positive). Non-finite input raises.
    """
    if not math.isfinite(speed_hz):
        raise ValueError(f"spin rate {speed_hz!r} Hz is not finite")
    if abs(speed_hz) < MIN_SPIN_HZ:
        return -HALF_PERIOD_SLOWEST if speed_hz < 0 else HALF_PERIOD_SLOWEST
    p = int(_HALF_PERIOD_NUM / speed_hz)  # int() truncates toward 0
    if p == 0:
        p = 1 if speed_hz > 0 else -1
    return max(-HALF_PERIOD_SLOWEST, min(HALF_PERIOD_SLOWEST, p))


_W_STRUCTS = {n: struct.Struct(f">{n}h") for n in range(1, 13)}
#: up to this rate a ``w`` half period is at least 1 us (``int(500000 / rate)`` >= 1)
_FAST_MAX_SPIN_HZ = _HALF_PERIOD_NUM


def encode_spin_rates_hz(speeds_hz: Sequence[float], directions: Sequence[int]) -> bytes:
    """The ``w`` message (unframed) for spin rates in Hz, each signed by its motor's direction
    (+1 / -1; the magnitude of the rate is used): ``SpinRates.from_hz(d * |s|).encode()``
    without the intermediate objects (the 500 Hz-1 kHz send path). Non-finite rates raise.

    A rate within ``[MIN_SPIN_HZ, 500 kHz]`` (every one in flight) is converted inline:
    there ``int(500000 / rate)`` lies in 1..32767, so :func:`spin_hz_to_half_period`'s
    clamps cannot change it; any other (idle, stop, non-finite) goes through that function."""
    periods = []
    for d, s in zip(directions, speeds_hz, strict=True):
        v = d * abs(s)
        if MIN_SPIN_HZ <= abs(v) <= _FAST_MAX_SPIN_HZ:   # False for NaN
            periods.append(int(_HALF_PERIOD_NUM / v))
        else:
            periods.append(spin_hz_to_half_period(v))
    packer = _W_STRUCTS.get(len(periods))
    if packer is None:
        packer = struct.Struct(f">{len(periods)}h")
    return b"w" + packer.pack(*periods)


def half_period_to_spin_hz(half_period_us: int) -> float:
    """The spin rate in Hz for a tk3 half period in µs (``500000 / p``; 0 -> 0.0)."""
    if half_period_us == 0:
        return 0.0
    return _HALF_PERIOD_NUM / half_period_us


def _s16(value: float) -> int:
    return max(-32768, min(32767, round(value)))


def _u16(value: float) -> int:
    return max(0, min(65535, round(value)))


@dataclass(frozen=True, slots=True)
class ImuAxes:
    """Board IMU -> body frame: the one place that maps axes and scales.

    The wire scales are fixed by the tk3 protocol and applied by the codec
    (:class:`ImuMessage`: 1e-3 m/s² and 1e-3 rad/s per LSB; :class:`MagMessage`: 1e-8 T), so
    messages are already SI in the *board* frame. This object then gives the body frame of
    ``sim_backend/vehicle.py`` (x towards propeller 1, z up; at rest the accelerometer reads +g
    on z): ``body[i] = sign[i] * gain * board[axis[i]]``. The defaults (identity, gains 1) are
    for a Flight-Ctrl mounted with its x arrow towards propeller 1 and its component side up,
    the FAST-Hex mounting; ``accel_gain``/``gyro_gain`` hold a calibration if one is needed.
    The emulator encodes with the inverse of the same object, so both ends agree.
    """

    axis: tuple[int, int, int] = (0, 1, 2)
    sign: tuple[int, int, int] = (1, 1, 1)
    accel_gain: float = 1.0
    gyro_gain: float = 1.0

    def __post_init__(self) -> None:
        if sorted(self.axis) != [0, 1, 2]:
            raise ConfigValueError("axis", f"{self.axis} is not a permutation of (0, 1, 2)")
        if any(s not in (1, -1) for s in self.sign):
            raise ConfigValueError("sign", f"{self.sign} must be +1 or -1 per axis")
        for name in ("accel_gain", "gyro_gain"):
            if not 0.5 <= getattr(self, name) <= 2.0:
                raise ConfigValueError(name, "a calibration gain must lie in 0.5..2")

    def to_body(self, board: Vec3, gain: float = 1.0) -> Vec3:
        """A board-frame vector in the body frame (axes only unless ``gain`` is given)."""
        a, s = self.axis, self.sign
        return (s[0] * gain * board[a[0]], s[1] * gain * board[a[1]],
                s[2] * gain * board[a[2]])

    def to_board(self, body: Vec3, gain: float = 1.0) -> Vec3:
        """Inverse of :meth:`to_body`."""
        out = [0.0, 0.0, 0.0]
        for i in range(3):
            out[self.axis[i]] = self.sign[i] * body[i] / gain
        return (out[0], out[1], out[2])

    def imu_to_body(self, msg: ImuMessage) -> tuple[Vec3, Vec3]:
        """(accel_m_s2, gyro_rad_s) of an ``I`` message in the body frame."""
        return (self.to_body(msg.accel_m_s2, self.accel_gain),
                self.to_body(msg.gyro_rad_s, self.gyro_gain))

    def imu_to_board(self, accel_m_s2: Vec3, gyro_rad_s: Vec3) -> tuple[Vec3, Vec3]:
        """Body-frame IMU vectors as the board would send them (emulators)."""
        return (self.to_board(accel_m_s2, self.accel_gain),
                self.to_board(gyro_rad_s, self.gyro_gain))


# --------------------------------------------------------------------------------------------
# tk3, host -> board


class Stream(Enum):
    """The four tk3 sensor streams and the command letter that sets their period."""

    IMU = b"i"
    MOTOR = b"m"
    BATTERY = b"b"
    MAG = b"c"


@dataclass(frozen=True, slots=True)
class Identify:
    CMD: ClassVar[bytes] = b"?"

    def encode(self) -> bytes:
        return self.CMD


@dataclass(frozen=True, slots=True)
class SetStreamPeriod:
    """Stream period in µs; 0 switches the stream off. Rate 500 Hz = period 2000 µs."""

    WIRE: ClassVar[struct.Struct] = struct.Struct(">I")
    stream: Stream
    period_us: int

    @classmethod
    def from_rate_hz(cls, stream: Stream, rate_hz: float) -> SetStreamPeriod:
        if not math.isfinite(rate_hz) or rate_hz < 0 or rate_hz > 2000:
            raise ValueError(f"stream rate {rate_hz!r} Hz outside 0..2000")
        return cls(stream, 0 if rate_hz == 0 else round(1e6 / rate_hz))

    def encode(self) -> bytes:
        return self.stream.value + self.WIRE.pack(self.period_us)


@dataclass(frozen=True, slots=True)
class StartMotors:
    """Start one motor (1-based id), or all of them with ``motor_id=None`` (old firmware)."""

    CMD: ClassVar[bytes] = b"g"
    motor_id: int | None = None

    def encode(self) -> bytes:
        return self.CMD if self.motor_id is None else self.CMD + bytes((self.motor_id,))


@dataclass(frozen=True, slots=True)
class StopMotors:
    CMD: ClassVar[bytes] = b"x"
    motor_id: int | None = None

    def encode(self) -> bytes:
        return self.CMD if self.motor_id is None else self.CMD + bytes((self.motor_id,))


@dataclass(frozen=True, slots=True)
class SpinRates:
    """Spin-rate set-points as signed half periods in µs, one per motor (see module doc)."""

    CMD: ClassVar[bytes] = b"w"
    half_periods_us: tuple[int, ...]

    @classmethod
    def from_hz(cls, speeds_hz: Sequence[float]) -> SpinRates:
        return cls(tuple(spin_hz_to_half_period(s) for s in speeds_hz))

    @property
    def speeds_hz(self) -> tuple[float, ...]:
        """Signed spin rates in Hz; the slowest-speed sentinel reads as ±15.26 Hz."""
        return tuple(half_period_to_spin_hz(p) for p in self.half_periods_us)

    def encode(self) -> bytes:
        return self.CMD + struct.pack(f">{len(self.half_periods_us)}h", *self.half_periods_us)


@dataclass(frozen=True, slots=True)
class Throttles:
    """Open-loop throttle per motor, raw −1023..1023 (% × 1023/100)."""

    CMD: ClassVar[bytes] = b"q"
    throttles_raw: tuple[int, ...]

    @classmethod
    def from_pct(cls, throttle_pct: Sequence[float]) -> Throttles:
        return cls(tuple(max(-1023, min(1023, int(p * 1023 / 100))) for p in throttle_pct))

    @property
    def throttle_pct(self) -> tuple[float, ...]:
        return tuple(t * 100.0 / 1023.0 for t in self.throttles_raw)

    def encode(self) -> bytes:
        return self.CMD + struct.pack(f">{len(self.throttles_raw)}h", *self.throttles_raw)


@dataclass(frozen=True, slots=True)
class Beep:
    CMD: ClassVar[bytes] = b"~"
    WIRE: ClassVar[struct.Struct] = struct.Struct(">H")
    freq_hz: int

    def encode(self) -> bytes:
        return self.CMD + self.WIRE.pack(self.freq_hz)


HostMessage = Identify | SetStreamPeriod | StartMotors | StopMotors | SpinRates | Throttles | Beep


_STREAM_OF_CMD: dict[bytes, Stream] = {s.value: s for s in Stream}


def decode_host_message(msg: bytes) -> HostMessage:
    """Decode a deframed host -> board tk3 message (what the emulated board receives)."""
    if not msg:
        raise MalformedMessageError(b"", "empty message")
    cmd, payload = msg[:1], msg[1:]
    n = len(payload)
    if cmd == b"w":             # first: 500-1000 of these a second
        if n % 2 or n == 0:
            raise MalformedMessageError(cmd, f"odd or empty payload of {n} bytes")
        return SpinRates(struct.unpack(f">{n // 2}h", payload))
    if cmd == b"?":
        return Identify()
    stream = _STREAM_OF_CMD.get(cmd)
    if stream is not None:
        if n != 4:
            raise MalformedMessageError(cmd, f"{n + 1} bytes, expected 5")
        return SetStreamPeriod(stream, SetStreamPeriod.WIRE.unpack(payload)[0])
    if cmd in (b"g", b"x"):
        if n > 1:
            raise MalformedMessageError(cmd, f"{n + 1} bytes, expected 1 or 2")
        motor = payload[0] if n else None
        return StartMotors(motor) if cmd == b"g" else StopMotors(motor)
    if cmd == b"q":
        if n % 2 or n == 0:
            raise MalformedMessageError(cmd, f"odd or empty payload of {n} bytes")
        return Throttles(struct.unpack(f">{n // 2}h", payload))
    if cmd == b"~":
        if n != 2:
            raise MalformedMessageError(cmd, f"{n + 1} bytes, expected 3")
        return Beep(Beep.WIRE.unpack(payload)[0])
    raise MalformedMessageError(cmd, "unknown command")


# --------------------------------------------------------------------------------------------
# tk3, board -> host


@dataclass(frozen=True, slots=True)
class ImuMessage:
    """tk3 ``I``: one IMU sample in the *board* frame, SI units (×1e-3 on the wire)."""

    CMD: ClassVar[bytes] = b"I"
    WIRE: ClassVar[struct.Struct] = struct.Struct(">B3h3h")
    seq: int
    accel_m_s2: Vec3
    gyro_rad_s: Vec3

    @classmethod
    def decode(cls, payload: bytes) -> ImuMessage:
        seq, ax, ay, az, gx, gy, gz = cls.WIRE.unpack(payload)
        return cls(seq, (ax * 1e-3, ay * 1e-3, az * 1e-3), (gx * 1e-3, gy * 1e-3, gz * 1e-3))

    def encode(self) -> bytes:
        a, g = self.accel_m_s2, self.gyro_rad_s
        return self.CMD + self.WIRE.pack(
            self.seq & 0xFF, _s16(a[0] * 1e3), _s16(a[1] * 1e3), _s16(a[2] * 1e3),
            _s16(g[0] * 1e3), _s16(g[1] * 1e3), _s16(g[2] * 1e3))


@dataclass(frozen=True, slots=True)
class MagMessage:
    """tk3 ``C``: magnetic field in the board frame, tesla (×1e-8 on the wire)."""

    CMD: ClassVar[bytes] = b"C"
    WIRE: ClassVar[struct.Struct] = struct.Struct(">B3h")
    seq: int
    field_t: Vec3

    @classmethod
    def decode(cls, payload: bytes) -> MagMessage:
        seq, x, y, z = cls.WIRE.unpack(payload)
        return cls(seq, (x * 1e-8, y * 1e-8, z * 1e-8))

    def encode(self) -> bytes:
        f = self.field_t
        return self.CMD + self.WIRE.pack(self.seq & 0xFF, _s16(f[0] * 1e8), _s16(f[1] * 1e8),
                                         _s16(f[2] * 1e8))


@dataclass(frozen=True, slots=True)
class MotorMessage:
    """tk3 ``M``: state of one motor (1-based ``motor_id``)."""

    CMD: ClassVar[bytes] = b"M"
    WIRE: ClassVar[struct.Struct] = struct.Struct(">BBhhH")
    EMERGENCY: ClassVar[int] = 0x80
    SPINNING: ClassVar[int] = 0x20
    STARTING: ClassVar[int] = 0x10
    seq: int
    motor_id: int
    emergency: bool
    spinning: bool
    starting: bool
    half_period_us: int
    """Measured signed half period (µs), as on the wire."""
    throttle_raw: int
    current_a: float

    @property
    def speed_hz(self) -> float:
        """Measured spin rate (Hz, signed by direction); 0 when the motor is not spinning."""
        return half_period_to_spin_hz(self.half_period_us) if self.spinning else 0.0

    @property
    def throttle_pct(self) -> float:
        return self.throttle_raw * 100.0 / 1023.0

    @classmethod
    def decode(cls, payload: bytes) -> MotorMessage:
        seq, state, period, throttle, current_ma = cls.WIRE.unpack(payload)
        return cls(seq, state & 0x0F, bool(state & cls.EMERGENCY), bool(state & cls.SPINNING),
                   bool(state & cls.STARTING), period, throttle, current_ma * 1e-3)

    def encode(self) -> bytes:
        return encode_motor_state(self.seq, self.motor_id, self.emergency, self.spinning,
                                  self.starting, self.half_period_us, self.throttle_raw,
                                  self.current_a)


def encode_motor_state(seq: int, motor_id: int, emergency: bool, spinning: bool,
                       starting: bool, half_period_us: int, throttle_raw: int,
                       current_a: float) -> bytes:
    """The ``M`` message (unframed) of :class:`MotorMessage`'s fields, without building one
    (an emulated board sends six every motor period)."""
    m = MotorMessage
    state = (motor_id & 0x0F) | (m.EMERGENCY if emergency else 0) \
        | (m.SPINNING if spinning else 0) | (m.STARTING if starting else 0)
    return m.CMD + m.WIRE.pack(seq & 0xFF, state, half_period_us, throttle_raw,
                               _u16(current_a * 1e3))


@dataclass(frozen=True, slots=True)
class BatteryMessage:
    CMD: ClassVar[bytes] = b"B"
    WIRE: ClassVar[struct.Struct] = struct.Struct(">BH")
    seq: int
    voltage_v: float

    @classmethod
    def decode(cls, payload: bytes) -> BatteryMessage:
        seq, mv = cls.WIRE.unpack(payload)
        return cls(seq, mv * 1e-3)

    def encode(self) -> bytes:
        return self.CMD + self.WIRE.pack(self.seq & 0xFF, _u16(self.voltage_v * 1e3))


@dataclass(frozen=True, slots=True)
class ClockRateMessage:
    CMD: ClassVar[bytes] = b"T"
    WIRE: ClassVar[struct.Struct] = struct.Struct(">BB")
    motor_id: int
    rate: int

    @classmethod
    def decode(cls, payload: bytes) -> ClockRateMessage:
        return cls(*cls.WIRE.unpack(payload))

    def encode(self) -> bytes:
        return self.CMD + self.WIRE.pack(self.motor_id, self.rate)


@dataclass(frozen=True, slots=True)
class IdentityMessage:
    """tk3 ``?`` reply: the firmware id, e.g. ``mkfl1.8``."""

    CMD: ClassVar[bytes] = b"?"
    firmware_id: str

    def encode(self) -> bytes:
        return self.CMD + self.firmware_id.encode("ascii")


@dataclass(frozen=True, slots=True)
class TextMessage:
    """tk3 ``N`` (info), ``A`` (warning) or ``E`` (error) text."""

    level: bytes
    text: str

    def encode(self) -> bytes:
        return self.level + self.text.encode("ascii", "replace")


BoardMessage = (ImuMessage | MagMessage | MotorMessage | BatteryMessage | ClockRateMessage
                | IdentityMessage | TextMessage)

BOARD_MESSAGES: dict[bytes, type[ImuMessage] | type[MagMessage] | type[MotorMessage]
                     | type[BatteryMessage] | type[ClockRateMessage]] = {
    b"I": ImuMessage, b"C": MagMessage, b"M": MotorMessage, b"B": BatteryMessage,
    b"T": ClockRateMessage,
}
"""Fixed-length board messages by command byte."""

BOARD_MESSAGE_BYTES: dict[bytes, int] = {
    cmd: cls.WIRE.size + 1 for cmd, cls in BOARD_MESSAGES.items()}
"""Their message lengths (command byte + payload), as the deframer checks them."""


def decode_board_message(msg: bytes) -> BoardMessage:
    """Decode a deframed board -> host tk3 message; wrong length or unknown cmd raises
    :class:`MalformedMessageError`."""
    cmd = msg[:1]
    cls = BOARD_MESSAGES.get(cmd)
    if cls is not None:
        if len(msg) != cls.WIRE.size + 1:
            raise MalformedMessageError(cmd, f"{len(msg)} bytes, expected {cls.WIRE.size + 1}")
        return cls.decode(msg[1:])
    if cmd == b"?":
        return IdentityMessage(msg[1:].decode("ascii", "replace"))
    if cmd in (b"N", b"A", b"E"):
        return TextMessage(cmd, msg[1:].decode("ascii", "replace"))
    raise MalformedMessageError(cmd, "unknown command")


# --------------------------------------------------------------------------------------------
# Stock MikroKopter (payloads of the base64 framing; little-endian)


def _need(cmd: bytes, data: bytes, size: int) -> bytes:
    if len(data) < size:
        raise MalformedMessageError(cmd, f"{len(data)} payload bytes, expected at least {size}")
    return data[:size]


@dataclass(frozen=True, slots=True)
class VersionRequest:
    CMD: ClassVar[bytes] = b"v"

    def payload(self) -> bytes:
        return b""


@dataclass(frozen=True, slots=True)
class VersionInfo:
    """Stock ``V`` reply (FC V2.x layout, 10 bytes)."""

    CMD: ClassVar[bytes] = b"V"
    WIRE: ClassVar[struct.Struct] = struct.Struct("<10B")
    sw_major: int
    sw_minor: int
    proto_major: int
    label_text_crc: int
    sw_patch: int
    hardware_error: tuple[int, int]
    hw_major: int
    bl_firmware: int
    flags: int

    @property
    def version(self) -> str:
        """Firmware version as HiSystems writes it, e.g. ``2.12a``."""
        return f"{self.sw_major}.{self.sw_minor:02d}{chr(ord('a') + self.sw_patch % 26)}"

    @classmethod
    def decode(cls, data: bytes) -> VersionInfo:
        v = cls.WIRE.unpack(_need(cls.CMD, data, cls.WIRE.size))
        return cls(v[0], v[1], v[2], v[3], v[4], (v[5], v[6]), v[7], v[8], v[9])

    def payload(self) -> bytes:
        return self.WIRE.pack(self.sw_major, self.sw_minor, self.proto_major, self.label_text_crc,
                              self.sw_patch, *self.hardware_error, self.hw_major,
                              self.bl_firmware, self.flags)


@dataclass(frozen=True, slots=True)
class _IntervalRequest:
    """A stock subscription: one ``u8`` interval in 10 ms steps (0 = off; renew within 4 s)."""

    CMD: ClassVar[bytes]
    interval_ms: int

    @classmethod
    def decode(cls, data: bytes) -> Self:
        return cls(_need(cls.CMD, data, 1)[0] * 10)

    def payload(self) -> bytes:
        return bytes((min(255, self.interval_ms // 10),))


@dataclass(frozen=True, slots=True)
class DebugRequest(_IntervalRequest):
    """Stock ``d``: send ``D`` every ``interval_ms``."""

    CMD: ClassVar[bytes] = b"d"


@dataclass(frozen=True, slots=True)
class DebugOut:
    """Stock ``D``: two status bytes and 32 raw ``s16`` analog values (indices in the spec)."""

    CMD: ClassVar[bytes] = b"D"
    WIRE: ClassVar[struct.Struct] = struct.Struct("<2B32h")
    VOLTAGE_INDEX: ClassVar[int] = 9
    status: tuple[int, int]
    analog: tuple[int, ...]

    @property
    def voltage_v(self) -> float:
        return self.analog[self.VOLTAGE_INDEX] * 0.1

    @classmethod
    def decode(cls, data: bytes) -> DebugOut:
        v = cls.WIRE.unpack(_need(cls.CMD, data, cls.WIRE.size))
        return cls((v[0], v[1]), tuple(v[2:]))

    def payload(self) -> bytes:
        return self.WIRE.pack(*self.status, *self.analog)


@dataclass(frozen=True, slots=True)
class Data3DRequest(_IntervalRequest):
    """Stock ``c``: send ``C`` every ``interval_ms``."""

    CMD: ClassVar[bytes] = b"c"


@dataclass(frozen=True, slots=True)
class Data3D:
    """Stock ``C`` (FC layout): nick, roll, compass angles (0.1° on the wire), centroid, AccZ."""

    CMD: ClassVar[bytes] = b"C"
    WIRE: ClassVar[struct.Struct] = struct.Struct("<3h3bH3b")
    angles_deg: Vec3
    centroid: tuple[int, int, int]
    acc_z_raw: int

    @classmethod
    def decode(cls, data: bytes) -> Data3D:
        v = cls.WIRE.unpack(_need(cls.CMD, data, cls.WIRE.size))
        return cls((v[0] * 0.1, v[1] * 0.1, v[2] * 0.1), (v[3], v[4], v[5]), v[6])

    def payload(self) -> bytes:
        a = self.angles_deg
        return self.WIRE.pack(_s16(a[0] * 10), _s16(a[1] * 10), _s16(a[2] * 10),
                              *self.centroid, self.acc_z_raw, 0, 0, 0)


@dataclass(frozen=True, slots=True)
class ExternControl:
    """Stock ``b`` (FC V2.x, 7 bytes): stick-level external control."""

    CMD: ClassVar[bytes] = b"b"
    WIRE: ClassVar[struct.Struct] = struct.Struct("<4b3B")
    VALID: ClassVar[int] = 0x01
    nick: int
    roll: int
    yaw: int
    gas: int
    frame: int
    config: int

    @classmethod
    def decode(cls, data: bytes) -> ExternControl:
        v = cls.WIRE.unpack(_need(cls.CMD, data, cls.WIRE.size))
        return cls(v[0], v[1], v[2], v[3], v[4], v[5])

    def payload(self) -> bytes:
        return self.WIRE.pack(self.nick, self.roll, self.yaw, self.gas, self.frame, self.config, 0)


@dataclass(frozen=True, slots=True)
class ExternControlAck:
    CMD: ClassVar[bytes] = b"B"
    frame: int

    @classmethod
    def decode(cls, data: bytes) -> ExternControlAck:
        return cls(_need(cls.CMD, data, 1)[0])

    def payload(self) -> bytes:
        return bytes((self.frame,))


@dataclass(frozen=True, slots=True)
class EngineTest:
    """Stock ``t``: raw 8-bit set-point per motor (16 motors, or the old 4-byte form).

    The firmware applies it only while disarmed and must be re-sent (it times out)."""

    CMD: ClassVar[bytes] = b"t"
    setpoints: tuple[int, ...]

    @classmethod
    def decode(cls, data: bytes) -> EngineTest:
        # The firmware tells the forms apart by frame length: > 20 chars (>= 4 groups, i.e.
        # >= 12 decoded bytes) is the 16-motor form, anything shorter the 4-byte one.
        if len(data) >= 12:
            return cls(tuple((data + bytes(16))[:16]))
        return cls(tuple(_need(cls.CMD, data, 4)))

    def payload(self) -> bytes:
        return bytes(self.setpoints)


@dataclass(frozen=True, slots=True)
class EngineTestAck:
    CMD: ClassVar[bytes] = b"T"

    def payload(self) -> bytes:
        return b""


StockMessage = (VersionRequest | VersionInfo | DebugRequest | DebugOut | Data3DRequest | Data3D
                | ExternControl | ExternControlAck | EngineTest | EngineTestAck)


def decode_stock_message(cmd: bytes, data: bytes) -> StockMessage:
    """Decode the payload of a stock frame (``data`` may be padded or over-decoded)."""
    if cmd == b"v":
        return VersionRequest()
    if cmd == b"V":
        return VersionInfo.decode(data)
    if cmd == b"d":
        return DebugRequest.decode(data)
    if cmd == b"D":
        return DebugOut.decode(data)
    if cmd == b"c":
        return Data3DRequest.decode(data)
    if cmd == b"C":
        return Data3D.decode(data)
    if cmd == b"b":
        return ExternControl.decode(data)
    if cmd == b"B":
        return ExternControlAck.decode(data)
    if cmd == b"t":
        return EngineTest.decode(data)
    if cmd == b"T":
        return EngineTestAck()
    raise MalformedMessageError(cmd, "unknown stock command")

"""MX-28T control table (Protocol 1.0 firmware, model 29) as data, shared by driver and emulator.

Wire facts (ROBOTIS e-Manual MX-28 and Protocol 1.0):
- 74-byte table: EEPROM 0..23, RAM 24..73, little-endian multi-byte registers;
- Goal/Present Position in 0.088 deg steps (4096 per servo turn); in multi-turn mode (CW = CCW
  Angle Limit = 4095) they are signed 16-bit, -28672..28672 (+-7 turns);
- Moving Speed / Present Speed in 0.114 rpm units, bit 10 of Present Speed/Load = CW direction;
- Present Load in ~0.1 % of the maximum torque, Present Voltage in 0.1 V, temperature in deg C;
- the status packet's error byte carries seven flags (:class:`ErrorBit`).

The tilt drive puts a 20:1 worm between the servo output and the tilt angle alpha:
``tilt_rad = k * servo_angle_rad`` with ``k = 0.05``; keep ``servo_angle_rad`` and ``tilt_rad``
apart. The helpers below convert between steps, servo angle and tilt.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import Enum, IntEnum, IntFlag

MODEL_MX28_P1 = 29
"""Model Number of an MX-28 with Protocol 1.0 firmware."""
MODEL_MX28_P2 = 30
"""Model Number of an MX-28 running the Protocol 2.0 firmware (different table: refused)."""

TABLE_SIZE = 74
STEPS_PER_TURN = 4096
RAD_PER_STEP = 2.0 * math.pi / STEPS_PER_TURN
SPEED_UNIT_RPM = 0.114
LOAD_UNIT_FRACTION = 0.001
VOLTAGE_UNIT_V = 0.1
NO_LOAD_SPEED_RPM = 55.0
"""The MX-28's top speed at 12 V: Moving Speed cannot make it faster."""
MULTI_TURN_LIMIT = 4095
MULTI_TURN_MIN_STEPS = -28672
MULTI_TURN_MAX_STEPS = 28672
BROADCAST_ID = 0xFE
MAX_ID = 0xFD

#: Baud Rate register value -> bit/s (the three remapped high rates, else 2 Mbit/s / (v + 1)).
_REMAPPED_BAUD = {250: 2_250_000, 251: 2_500_000, 252: 3_000_000}


def baud_from_register(value: int) -> int:
    """Bit rate (bit/s) selected by the Baud Rate register (4)."""
    return _REMAPPED_BAUD.get(value, round(2_000_000 / (value + 1)))


class Access(Enum):
    R = "R"
    RW = "RW"


class Reg(IntEnum):
    """Register addresses (Protocol 1.0 firmware; NOT the P2 addresses of the SDK examples)."""

    MODEL_NUMBER = 0
    FIRMWARE_VERSION = 2
    ID = 3
    BAUD_RATE = 4
    RETURN_DELAY_TIME = 5
    CW_ANGLE_LIMIT = 6
    CCW_ANGLE_LIMIT = 8
    TEMPERATURE_LIMIT = 11
    MIN_VOLTAGE_LIMIT = 12
    MAX_VOLTAGE_LIMIT = 13
    MAX_TORQUE = 14
    STATUS_RETURN_LEVEL = 16
    ALARM_LED = 17
    SHUTDOWN = 18
    MULTI_TURN_OFFSET = 20
    RESOLUTION_DIVIDER = 22
    TORQUE_ENABLE = 24
    LED = 25
    D_GAIN = 26
    I_GAIN = 27
    P_GAIN = 28
    GOAL_POSITION = 30
    MOVING_SPEED = 32
    TORQUE_LIMIT = 34
    PRESENT_POSITION = 36
    PRESENT_SPEED = 38
    PRESENT_LOAD = 40
    PRESENT_VOLTAGE = 42
    PRESENT_TEMPERATURE = 43
    REGISTERED = 44
    MOVING = 46
    LOCK = 47
    PUNCH = 48
    REALTIME_TICK = 50
    GOAL_ACCELERATION = 73


@dataclass(frozen=True, slots=True)
class Register:
    """One control-table entry. ``lo``/``hi`` bound what a WRITE may store (raw value)."""

    reg: Reg
    size: int
    access: Access
    lo: int
    hi: int
    initial: int
    signed: bool = False

    @property
    def address(self) -> int:
        return int(self.reg)

    @property
    def eeprom(self) -> bool:
        return self.address < EEPROM_END


EEPROM_END = 24

_R, _RW = Access.R, Access.RW

#: The MX-28 (P1) table. Goal Position's range depends on the mode: checked by the servo logic.
MX28_P1: tuple[Register, ...] = (
    Register(Reg.MODEL_NUMBER, 2, _R, 0, 0xFFFF, MODEL_MX28_P1),
    Register(Reg.FIRMWARE_VERSION, 1, _R, 0, 0xFF, 41),
    Register(Reg.ID, 1, _RW, 0, 253, 1),
    Register(Reg.BAUD_RATE, 1, _RW, 0, 254, 34),
    Register(Reg.RETURN_DELAY_TIME, 1, _RW, 0, 254, 250),
    Register(Reg.CW_ANGLE_LIMIT, 2, _RW, 0, 4095, 0),
    Register(Reg.CCW_ANGLE_LIMIT, 2, _RW, 0, 4095, 4095),
    Register(Reg.TEMPERATURE_LIMIT, 1, _RW, 0, 99, 80),
    Register(Reg.MIN_VOLTAGE_LIMIT, 1, _RW, 50, 160, 60),
    Register(Reg.MAX_VOLTAGE_LIMIT, 1, _RW, 50, 160, 160),
    Register(Reg.MAX_TORQUE, 2, _RW, 0, 1023, 1023),
    Register(Reg.STATUS_RETURN_LEVEL, 1, _RW, 0, 2, 2),
    Register(Reg.ALARM_LED, 1, _RW, 0, 0x7F, 0x24),
    Register(Reg.SHUTDOWN, 1, _RW, 0, 0x7F, 0x24),
    Register(Reg.MULTI_TURN_OFFSET, 2, _RW, -24576, 24576, 0, signed=True),
    Register(Reg.RESOLUTION_DIVIDER, 1, _RW, 1, 4, 1),
    Register(Reg.TORQUE_ENABLE, 1, _RW, 0, 1, 0),
    Register(Reg.LED, 1, _RW, 0, 1, 0),
    Register(Reg.D_GAIN, 1, _RW, 0, 254, 0),
    Register(Reg.I_GAIN, 1, _RW, 0, 254, 0),
    Register(Reg.P_GAIN, 1, _RW, 0, 254, 32),
    Register(Reg.GOAL_POSITION, 2, _RW, MULTI_TURN_MIN_STEPS, MULTI_TURN_MAX_STEPS, 0,
             signed=True),
    Register(Reg.MOVING_SPEED, 2, _RW, 0, 2047, 0),
    Register(Reg.TORQUE_LIMIT, 2, _RW, 0, 1023, 1023),
    Register(Reg.PRESENT_POSITION, 2, _R, MULTI_TURN_MIN_STEPS, MULTI_TURN_MAX_STEPS, 0,
             signed=True),
    Register(Reg.PRESENT_SPEED, 2, _R, 0, 2047, 0),
    Register(Reg.PRESENT_LOAD, 2, _R, 0, 2047, 0),
    Register(Reg.PRESENT_VOLTAGE, 1, _R, 0, 255, 120),
    Register(Reg.PRESENT_TEMPERATURE, 1, _R, 0, 255, 25),
    Register(Reg.REGISTERED, 1, _R, 0, 1, 0),
    Register(Reg.MOVING, 1, _R, 0, 1, 0),
    Register(Reg.LOCK, 1, _RW, 0, 1, 0),
    Register(Reg.PUNCH, 2, _RW, 0, 1023, 0),
    Register(Reg.REALTIME_TICK, 2, _R, 0, 0xFFFF, 0),
    Register(Reg.GOAL_ACCELERATION, 1, _RW, 0, 254, 0),
)

BY_ADDRESS: dict[int, Register] = {r.address: r for r in MX28_P1}

#: The block the driver polls in one READ: Present Position (36) .. Moving (46), 11 bytes.
STATE_BLOCK_ADDRESS = int(Reg.PRESENT_POSITION)
STATE_BLOCK_LENGTH = int(Reg.MOVING) - int(Reg.PRESENT_POSITION) + 1


class Instruction(IntEnum):
    PING = 0x01
    READ = 0x02
    WRITE = 0x03
    REG_WRITE = 0x04
    ACTION = 0x05
    RESET = 0x06
    SYNC_WRITE = 0x83
    BULK_READ = 0x92


class ErrorBit(IntFlag):
    """The status packet's error byte (and the Alarm LED / Shutdown masks)."""

    NONE = 0
    VOLTAGE = 0x01
    ANGLE_LIMIT = 0x02
    OVERHEATING = 0x04
    RANGE = 0x08
    CHECKSUM = 0x10
    OVERLOAD = 0x20
    INSTRUCTION = 0x40


ALL_ERROR_BITS = ErrorBit(0x7F)


class Mode(Enum):
    """Operating mode selected by the angle limits (P1 has no Operating Mode register)."""

    JOINT = "joint"
    WHEEL = "wheel"
    MULTI_TURN = "multi-turn"


def mode_from_limits(cw_limit: int, ccw_limit: int) -> Mode:
    if cw_limit == MULTI_TURN_LIMIT and ccw_limit == MULTI_TURN_LIMIT:
        return Mode.MULTI_TURN
    if cw_limit == 0 and ccw_limit == 0:
        return Mode.WHEEL
    return Mode.JOINT


def to_signed16(raw: int) -> int:
    """Two's complement of a 16-bit register (the SDK hands them back unsigned)."""
    raw &= 0xFFFF
    return raw - 0x10000 if raw & 0x8000 else raw


def to_unsigned16(value: int) -> int:
    return value & 0xFFFF


def signed_magnitude_11(raw: int) -> int:
    """Present Speed / Load: bits 0..9 magnitude, bit 10 set = CW (negative here)."""
    magnitude = raw & 0x3FF
    return -magnitude if raw & 0x400 else magnitude


def encode_signed_magnitude_11(value: int) -> int:
    magnitude = min(abs(value), 0x3FF)
    return magnitude | (0x400 if value < 0 else 0)


def moving_speed_for_rate(servo_rate_rad_s: float) -> int:
    """Largest Moving Speed value whose speed does not exceed ``servo_rate_rad_s`` (>= 1;
    0 would mean 'no speed control')."""
    rpm = abs(servo_rate_rad_s) * 60.0 / (2.0 * math.pi)
    return max(1, min(1023, math.floor(rpm / SPEED_UNIT_RPM + 1e-9)))


def speed_rad_s(units: int) -> float:
    """Servo output speed (rad/s) of a Moving/Present Speed magnitude in 0.114 rpm units."""
    return units * SPEED_UNIT_RPM * 2.0 * math.pi / 60.0

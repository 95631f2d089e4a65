"""Dynamixel MX-28T tilt servo (Protocol 1.0 through dynamixel-sdk): control table, packet
codec and the :class:`TiltServo` device served from its own process."""

from drivers.dynamixel.control_table import ErrorBit, Mode, Reg
from drivers.dynamixel.device import (
    ServoCommError,
    ServoError,
    ServoHealth,
    ServoIdentity,
    ServoIdentityError,
    ServoState,
    TiltServo,
    TiltServoConfig,
    parse_servo_uri,
    probe_servo,
)

__all__ = [
    "ErrorBit",
    "Mode",
    "Reg",
    "ServoCommError",
    "ServoError",
    "ServoHealth",
    "ServoIdentity",
    "ServoIdentityError",
    "ServoState",
    "TiltServo",
    "TiltServoConfig",
    "parse_servo_uri",
    "probe_servo",
]

"""MikroKopter Flight-Ctrl driver: tk3 and stock framings, message codecs, the FlightCtrl device.

- :mod:`.framing_tk3`: the LAAS tk3 framing of the 500 Hz flight link;
- :mod:`.framing_stock`: the stock HiSystems framing (identification, bench tests);
- :mod:`.messages`: one frozen dataclass per message, and :class:`~.messages.ImuAxes`, the one
  place mapping the board's IMU axes and scales to the body frame;
- :mod:`.device`: :class:`~.device.FlightCtrl`, reader thread, mailboxes, link statistics.
"""

from drivers.mikrokopter.device import (
    BatterySample,
    BoardIdentity,
    FlightCtrl,
    FlightCtrlConfig,
    FlightCtrlError,
    FlightCtrlIdentityError,
    ImuSample,
    LinkHealth,
    LinkStats,
    MagSample,
    MotorsSnapshot,
    MotorStartError,
    MotorState,
    MotorStatus,
    StockFirmwareError,
    StreamStats,
    probe,
)
from drivers.mikrokopter.messages import ImuAxes

__all__ = [
    "BatterySample",
    "BoardIdentity",
    "FlightCtrl",
    "FlightCtrlConfig",
    "FlightCtrlError",
    "FlightCtrlIdentityError",
    "ImuAxes",
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

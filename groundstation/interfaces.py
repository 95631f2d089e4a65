"""The small interfaces the 500 Hz loop depends on. The real drivers implement them on hardware
and on the emulated backend alike (the loop never sees a simulator or a hardware class).

- :class:`ImuLink`: the Flight-Ctrl as the loop uses it: IMU samples in, spin rates out,
  motors started/stopped, snapshots of motors, battery and link health
  (:class:`drivers.mikrokopter.device.FlightCtrl`).
- :class:`TiltLink`: the tilt servo: a goal tilt in, the newest measurement out, and in a
  lockstep flight one synchronous service cycle on request
  (:class:`drivers.dynamixel.device.TiltServo`).
- :class:`PoseLink`: the motion capture: the newest pose and the stream statistics; a lockstep
  loop takes the datagrams off the socket itself as its IMU sample arrives (``receive()``) and
  decodes them after its motor command (``handle_received()``)
  (:class:`drivers.mocap.natnet_client.NatNetClient`).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol, runtime_checkable

from drivers.dynamixel.device import ServoState
from drivers.mikrokopter.device import BatterySample, ImuSample, LinkStats, MotorsSnapshot
from drivers.mocap.pose import MocapStats, PoseSample


@runtime_checkable
class ImuLink(Protocol):
    def wait_next(self, timeout_s: float) -> ImuSample | None: ...

    def send_rotor_speeds_hz(self, speeds_hz: Sequence[float]) -> None: ...

    def request_motor_start(self) -> None: ...

    def stop_motors(self) -> None: ...

    def motors(self) -> MotorsSnapshot: ...

    def battery(self) -> BatterySample | None: ...

    def link_stats(self) -> LinkStats: ...

    @property
    def rx_errors(self) -> int: ...

    @property
    def imu_anomalies(self) -> int: ...

    @property
    def imu_motion_missed(self) -> int: ...


@runtime_checkable
class TiltLink(Protocol):
    def set_tilt(self, tilt_rad: float) -> None: ...

    def latest(self, now_s: float | None = None) -> ServoState: ...

    def begin_cycle(self, timeout_s: float | None = None) -> None: ...

    def finish_cycle(self, timeout_s: float) -> ServoState: ...


@runtime_checkable
class PoseLink(Protocol):
    def latest(self) -> PoseSample | None: ...

    def stats(self) -> MocapStats: ...

    def receive(self) -> int: ...

    def handle_received(self) -> int: ...

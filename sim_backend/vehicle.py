"""What the device emulators need from the simulated vehicle, and a vehicle clamped on a bench.

Frames and conventions used by every emulator:
- world frame W: z up (gravity is ``-g e3``, as in the paper); body frame B: x towards
  propeller 1, z up along the rotor axes at zero tilt;
- ``q_wb`` is the body -> world rotation as a Hamilton quaternion ``(w, x, y, z)``;
- the IMU measures the body angular rate and the specific force in B (at rest, level:
  ``accel_m_s2 = (0, 0, +g)``), with the sensor model's noise and biases applied;
- rotor speeds are in Hz (revolutions per second), positive, six of them, propeller order of
  the paper; a speed of 0 is a stopped motor;
- the tilt is the synchronised tilt angle alpha in radians (servo side, before the Cardan chain).

The full flying simulator (``sim_backend.simulator``) and :class:`BenchVehicle` both implement
:class:`EmulatedVehicle`; emulators only talk to this interface, so they run against either.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Protocol, runtime_checkable

import numpy as np

from controller.values import tick_value

GRAVITY_M_S2 = 9.81

Vec3 = tuple[float, float, float]


@tick_value
class ImuReading:
    """One IMU sample from the sensor model, body frame."""

    t_s: float
    gyro_rad_s: Vec3
    accel_m_s2: Vec3


@tick_value
class PoseReading:
    """The vehicle's pose at ``t_s`` (true pose; MoCap emulators add their own noise)."""

    t_s: float
    pos_w_m: Vec3
    q_wb: tuple[float, float, float, float]


@runtime_checkable
class EmulatedVehicle(Protocol):
    """The simulated vehicle as the device emulators see it. Not thread-safe: one owner."""

    def now_s(self) -> float:
        """Simulated time in seconds."""
        ...

    def advance(self, dt_s: float) -> None:
        """Integrate the physics forward by ``dt_s`` seconds."""
        ...

    def command_rotor_speeds_hz(self, speeds_hz: Sequence[float]) -> None:
        """Set the six BL-Ctrl speed set-points (Hz); 0 stops a motor."""
        ...

    def rotor_speeds_hz(self) -> tuple[float, ...]:
        """The six measured rotor speeds (Hz)."""
        ...

    def motor_currents_a(self) -> tuple[float, ...]:
        """The six motor currents (A)."""
        ...

    def read_imu(self) -> ImuReading:
        """Sample the IMU model at the current time."""
        ...

    def command_tilt_rad(self, tilt_rad: float) -> None:
        """Set the servo's goal tilt angle alpha (rad); the servo moves at its own rate."""
        ...

    def tilt_rad(self) -> float:
        """The servo-side tilt angle alpha (rad) as the servo encoder sees it."""
        ...

    def true_pose(self) -> PoseReading:
        """The true pose at the current time."""
        ...

    def battery_voltage_v(self) -> float:
        """Battery voltage under the present load (V)."""
        ...


class BenchVehicle:
    """A FAST-Hex clamped level on a test bench: motors spin, nothing flies.

    What a lab sees when bench-testing the electronics: the IMU reads gravity plus noise and a
    constant bias, rotors follow their set-points with a first-order lag, the tilt follows its
    goal at the tilt-rate limit, and the battery sags with the motor current. Seeded, so two
    benches with the same seed produce the same samples.
    """

    def __init__(
        self,
        *,
        seed: int = 0,
        pos_w_m: Vec3 = (0.0, 0.0, 0.0),
        rotor_time_constant_s: float = 0.03,
        max_tilt_rate_rad_s: float = math.radians(10.0),
        max_tilt_rad: float = math.radians(35.0),
        gyro_noise_rad_s: float = 0.005,
        accel_noise_m_s2: float = 0.05,
        battery_open_circuit_v: float = 16.4,
        battery_resistance_ohm: float = 0.02,
    ) -> None:
        self._rng = np.random.default_rng(seed)
        self._t_s = 0.0
        self._pos = pos_w_m
        self._tau = rotor_time_constant_s
        self._cmd_hz = np.zeros(6)
        self._speed_hz = np.zeros(6)
        self._tilt_goal = 0.0
        self._tilt = 0.0
        self._tilt_rate = max_tilt_rate_rad_s
        self._max_tilt = max_tilt_rad
        self._gyro_sigma = gyro_noise_rad_s
        self._accel_sigma = accel_noise_m_s2
        self._gyro_bias = self._rng.normal(0.0, 0.01, 3)
        self._accel_bias = self._rng.normal(0.0, 0.05, 3)
        self._v_oc = battery_open_circuit_v
        self._r_int = battery_resistance_ohm

    def now_s(self) -> float:
        return self._t_s

    def advance(self, dt_s: float) -> None:
        if dt_s <= 0.0:
            return
        self._t_s += dt_s
        self._speed_hz += (self._cmd_hz - self._speed_hz) * (1.0 - math.exp(-dt_s / self._tau))
        step = self._tilt_rate * dt_s
        self._tilt += max(-step, min(step, self._tilt_goal - self._tilt))

    def command_rotor_speeds_hz(self, speeds_hz: Sequence[float]) -> None:
        if len(speeds_hz) != 6:
            raise ValueError(f"expected 6 rotor speeds, got {len(speeds_hz)}")
        self._cmd_hz = np.clip(np.asarray(speeds_hz, dtype=float), 0.0, None)

    def rotor_speeds_hz(self) -> tuple[float, ...]:
        return tuple(float(s) for s in self._speed_hz)

    def motor_currents_a(self) -> tuple[float, ...]:
        # About 0.2 A idle, ~8 A at 100 Hz for a 12" propeller on an MK3638: cubic in speed.
        return tuple(float(0.2 * (s > 0.5) + 8.0 * (s / 100.0) ** 3) for s in self._speed_hz)

    def read_imu(self) -> ImuReading:
        gyro = self._gyro_bias + self._rng.normal(0.0, self._gyro_sigma, 3)
        accel = np.array([0.0, 0.0, GRAVITY_M_S2]) + self._accel_bias \
            + self._rng.normal(0.0, self._accel_sigma, 3)
        return ImuReading(self._t_s, (float(gyro[0]), float(gyro[1]), float(gyro[2])),
                          (float(accel[0]), float(accel[1]), float(accel[2])))

    def command_tilt_rad(self, tilt_rad: float) -> None:
        self._tilt_goal = min(max(tilt_rad, 0.0), self._max_tilt)

    def tilt_rad(self) -> float:
        return self._tilt

    def true_pose(self) -> PoseReading:
        return PoseReading(self._t_s, self._pos, (1.0, 0.0, 0.0, 0.0))

    def battery_voltage_v(self) -> float:
        return self._v_oc - self._r_int * sum(self.motor_currents_a())

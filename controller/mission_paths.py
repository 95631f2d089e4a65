"""Closed-form kinematics of the mission paths: position, velocity and acceleration (world frame)
and yaw with its rate, exact at any time. Pure floats, no numpy (evaluated every control tick).

- :func:`min_jerk`, :func:`envelope`, :func:`envelope_integral`: the quintic smoothstep, the
  fade-in/fade-out envelope made of two of them, and its integral (a progress variable whose
  rate is the envelope: a circle's angle, a ramp's distance);
- :class:`CirclePath`, :class:`LissajousPath`, :class:`RampPath`, :class:`WaypointsPath`.

Every path answers ``eval(t_s) -> (pos_w_m, vel_w_m_s, acc_w_m_s2, yaw_rad, yaw_rate_rad_s)``
for ``t_s`` in ``[0, duration_s]`` (segment time).
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Sequence
from dataclasses import dataclass

Vec3 = tuple[float, float, float]
PathSample = tuple[Vec3, Vec3, Vec3, float, float]

#: peak |ds/dtau| and |d2s/dtau2| of the quintic smoothstep s(tau) = 10 tau^3 - 15 tau^4 + 6 tau^5
MIN_JERK_PEAK_RATE = 1.875
MIN_JERK_PEAK_ACCEL = 5.7735


def min_jerk(tau: float) -> tuple[float, float, float]:
    """s, ds/dtau, d2s/dtau2 of the quintic 10t^3 - 15t^4 + 6t^5 on [0, 1] (clamped outside)."""
    if tau <= 0.0:
        return 0.0, 0.0, 0.0
    if tau >= 1.0:
        return 1.0, 0.0, 0.0
    t2 = tau * tau
    return (t2 * tau * (10.0 - 15.0 * tau + 6.0 * t2),
            30.0 * t2 * (1.0 - 2.0 * tau + t2),
            60.0 * tau * (1.0 - 3.0 * tau + 2.0 * t2))


def _min_jerk_integral(tau: float) -> float:
    """int_0^tau s: 2.5 t^4 - 3 t^5 + t^6 (0.5 at tau = 1)."""
    tau = min(max(tau, 0.0), 1.0)
    t4 = tau ** 4
    return t4 * (2.5 - 3.0 * tau + tau * tau)


def envelope(t: float, dur: float, fade_in: float, fade_out: float
             ) -> tuple[float, float, float]:
    """Amplitude envelope e, e', e'': minimum-jerk fade in over ``fade_in`` s, out over the last
    ``fade_out`` s of ``dur`` (either 0: no fade on that side)."""
    e, de, dde = 1.0, 0.0, 0.0
    if fade_in > 0.0:
        s, ds, dds = min_jerk(t / fade_in)
        e, de, dde = s, ds / fade_in, dds / (fade_in * fade_in)
    if fade_out > 0.0:
        s, ds, dds = min_jerk((dur - t) / fade_out)
        ds, dds = -ds / fade_out, dds / (fade_out * fade_out)
        e, de, dde = e * s, de * s + e * ds, dde * s + 2.0 * de * ds + e * dds
    return e, de, dde


def envelope_integral(t: float, dur: float, fade_in: float, fade_out: float) -> float:
    """``int_0^t e`` for non-overlapping fades (``fade_in + fade_out <= dur``): each fade
    covers half its length, so the total is ``dur - (fade_in + fade_out) / 2``."""
    t = min(max(t, 0.0), dur)
    if fade_in > 0.0 and t < fade_in:
        return fade_in * _min_jerk_integral(t / fade_in)
    total = 0.5 * fade_in + (t - fade_in)
    start_out = dur - fade_out
    if fade_out > 0.0 and t > start_out:
        u = (dur - t) / fade_out
        total = 0.5 * fade_in + (start_out - fade_in) + fade_out * (0.5 - _min_jerk_integral(u))
    return total


def _plane_axes(plane: str) -> tuple[int, int, int]:
    """World indices of the plane's first and second axis and of its normal."""
    return {"xy": (0, 1, 2), "xz": (0, 2, 1), "yz": (1, 2, 0)}[plane]


@dataclass(frozen=True)
class CirclePath:
    """``p = c + r (cos th, sin th)`` in a coordinate plane; the angular rate
    ``th' = dir w e(t)`` follows the fade envelope, so speed and tangential acceleration start
    and end at zero; ``th = th0 + dir w int_0^t e``."""

    centre_w_m: Vec3
    radius_m: float
    omega_rad_s: float
    direction: float  # +1: counter-clockwise seen from the plane's normal (+z for xy)
    start_angle_rad: float
    plane: str
    duration_s: float
    fade_in_s: float
    fade_out_s: float
    yaw_rad: float

    def eval(self, t_s: float) -> PathSample:
        e, de, _ = envelope(t_s, self.duration_s, self.fade_in_s, self.fade_out_s)
        w = self.direction * self.omega_rad_s
        th = self.start_angle_rad + w * envelope_integral(t_s, self.duration_s, self.fade_in_s,
                                                          self.fade_out_s)
        dth, ddth = w * e, w * de
        c, s, r = math.cos(th), math.sin(th), self.radius_m
        i, j, _ = _plane_axes(self.plane)
        p, v, a = list(self.centre_w_m), [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]
        p[i] += r * c
        p[j] += r * s
        v[i], v[j] = -r * s * dth, r * c * dth
        a[i] = -r * s * ddth - r * c * dth * dth
        a[j] = r * c * ddth - r * s * dth * dth
        return (p[0], p[1], p[2]), (v[0], v[1], v[2]), (a[0], a[1], a[2]), self.yaw_rad, 0.0


@dataclass(frozen=True)
class LissajousPath:
    """``p_k = c_k + A_k e(t) sin(2 pi f_k t + phi_k)`` per axis k, with a common fade envelope
    (both fades required, so the vehicle starts and ends at rest at ``c``)."""

    centre_w_m: Vec3
    amplitudes_m: Vec3
    omegas_rad_s: Vec3
    phases_rad: Vec3
    duration_s: float
    fade_in_s: float
    fade_out_s: float
    yaw_rad: float

    def eval(self, t_s: float) -> PathSample:
        e, de, dde = envelope(t_s, self.duration_s, self.fade_in_s, self.fade_out_s)
        p, v, a = list(self.centre_w_m), [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]
        for k in range(3):
            amp, w = self.amplitudes_m[k], self.omegas_rad_s[k]
            if amp == 0.0:
                continue
            sn, cs = math.sin(w * t_s + self.phases_rad[k]), math.cos(w * t_s + self.phases_rad[k])
            p[k] += amp * e * sn
            v[k] = amp * (de * sn + e * w * cs)
            a[k] = amp * (dde * sn + 2.0 * de * w * cs - e * w * w * sn)
        return (p[0], p[1], p[2]), (v[0], v[1], v[2]), (a[0], a[1], a[2]), self.yaw_rad, 0.0


@dataclass(frozen=True)
class RampPath:
    """Straight line from ``p0`` to ``p1`` (and yaw ``yaw0`` to ``yaw1``) at constant velocity;
    with ``smooth_s > 0`` the speed blends in and out along a minimum-jerk smoothstep over
    ``smooth_s`` at each end (progress ``sigma = int e / (T - smooth_s)``), so the acceleration
    is bounded (``V * 1.875 / smooth_s``) and continuous."""

    p0_w_m: Vec3
    p1_w_m: Vec3
    yaw0_rad: float
    yaw1_rad: float
    duration_s: float
    smooth_s: float

    @property
    def cruise_fraction_per_s(self) -> float:
        """d sigma / dt while cruising (1/s)."""
        return 1.0 / (self.duration_s - self.smooth_s)

    def eval(self, t_s: float) -> PathSample:
        k = self.cruise_fraction_per_s
        ts = self.smooth_s
        sig = k * envelope_integral(t_s, self.duration_s, ts, ts)
        e, de, _ = envelope(t_s, self.duration_s, ts, ts) if ts > 0.0 else (1.0, 0.0, 0.0)
        ds, dds = k * e, k * de
        p0, p1 = self.p0_w_m, self.p1_w_m
        d = (p1[0] - p0[0], p1[1] - p0[1], p1[2] - p0[2])
        dy = self.yaw1_rad - self.yaw0_rad
        return ((p0[0] + sig * d[0], p0[1] + sig * d[1], p0[2] + sig * d[2]),
                (ds * d[0], ds * d[1], ds * d[2]), (dds * d[0], dds * d[1], dds * d[2]),
                self.yaw0_rad + sig * dy, ds * dy)


@dataclass(frozen=True)
class _Leg:
    t0_s: float
    move_s: float
    p0_w_m: Vec3
    p1_w_m: Vec3
    yaw0_rad: float
    yaw1_rad: float


class WaypointsPath:
    """Rest-to-rest minimum-jerk legs through the waypoints, optionally dwelling at each.

    A leg of length d with yaw change dpsi takes the shortest time meeting every limit:
    ``T = max(1.875 d / v_max, sqrt(5.7735 d / a_max), 1.875 |dpsi| / yaw_rate_max)`` (the peak
    speed of a minimum-jerk move is 1.875 d / T, its peak acceleration 5.7735 d / T^2).
    """

    def __init__(self, p0_w_m: Vec3, yaw0_rad: float, points_w_m: Sequence[Vec3],
                 yaws_rad: Sequence[float | None], max_speed_m_s: float,
                 max_accel_m_s2: float, max_yaw_rate_rad_s: float, dwell_s: float,
                 min_leg_s: float) -> None:
        self.legs: list[_Leg] = []
        t, p, yaw = 0.0, p0_w_m, yaw0_rad
        for q, qyaw in zip(points_w_m, yaws_rad, strict=True):
            yaw1 = yaw if qyaw is None else qyaw
            d = math.dist(p, q)
            move = max(MIN_JERK_PEAK_RATE * d / max_speed_m_s,
                       math.sqrt(MIN_JERK_PEAK_ACCEL * d / max_accel_m_s2),
                       MIN_JERK_PEAK_RATE * abs(yaw1 - yaw) / max_yaw_rate_rad_s, min_leg_s)
            self.legs.append(_Leg(t, move, p, q, yaw, yaw1))
            t += move + dwell_s
            p, yaw = q, yaw1
        self.duration_s = t
        self.end_w_m, self.end_yaw_rad = p, yaw
        self._starts = [leg.t0_s for leg in self.legs]

    def eval(self, t_s: float) -> PathSample:
        leg = self.legs[max(0, bisect.bisect_right(self._starts, t_s) - 1)]
        s, ds, dds = min_jerk((t_s - leg.t0_s) / leg.move_s)
        ds, dds = ds / leg.move_s, dds / (leg.move_s * leg.move_s)
        p0, p1 = leg.p0_w_m, leg.p1_w_m
        d = (p1[0] - p0[0], p1[1] - p0[1], p1[2] - p0[2])
        dy = leg.yaw1_rad - leg.yaw0_rad
        return ((p0[0] + s * d[0], p0[1] + s * d[1], p0[2] + s * d[2]),
                (ds * d[0], ds * d[1], ds * d[2]), (dds * d[0], dds * d[1], dds * d[2]),
                leg.yaw0_rad + s * dy, ds * dy)

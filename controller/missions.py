"""Missions: full-pose reference trajectories p_r(t), v_r, a_r, R_r(t), w_r and alpha_r(t).

A mission file (``config/missions/*.yaml``, schema ``fasthex.mission``) lists segments played in
order, each starting where the previous one ended:

- ``hold``: stay (optionally at a new position / yaw: a jump, use ``goto`` for motion);
- ``goto``: minimum-jerk move to ``pos_w_m`` (and ``yaw_deg``);
- ``sine``: ``x_axis(t) = c + A e(t) sin(2 pi f t)`` on x, y or z, with a smooth amplitude
  envelope e(t) (``fade_in_s``/``fade_out_s``, quintic smoothstep) so that velocity starts and
  ends at zero; derivatives are exact;
- ``attitude_sine``: ``R_r = R_0 R_axis(A e(t) sin(2 pi f t))`` about body roll, pitch or yaw,
  with the matching body angular velocity;
- ``takeoff``: minimum-jerk climb to ``height_m``; ``land``: minimum-jerk descent to the start
  height minus ``sink_m`` (so the vehicle settles on its gear). Not measured by default.

Each segment may carry an ``alpha`` profile (times relative to the segment start):
``constant``, ``steps``, ``ramp`` or ``auto`` (:mod:`controller.tilt_planner`); without one a
segment keeps the previous segment's final alpha (or stays ``auto``).

Validation (before anything flies): positions lie in a sane workspace (:data:`WORKSPACE_M`),
every takeoff climbs above where it starts, alpha steps and ramps happen inside their segment,
and no segment asks for more than :data:`MAX_REF_SPEED_M_S` or :data:`MAX_REF_ACCEL_M_S2`. The
checks that need the vehicle or the session (tilt range, thrust, geofence) use
:func:`segment_extents_w_m`, :func:`explicit_alphas_deg` and :func:`peak_vertical_accel_m_s2`.
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass
from typing import Literal

from config.schema import ConfigValueError, spec
from controller.reference import (
    IDENTITY_Q,
    ZERO3,
    Quat,
    Reference,
    Vec3,
    quat_from_axis_angle,
    quat_mul,
    quat_to_rot,
)

MISSION_SCHEMA = "fasthex.mission"

#: |x|, |y|, |z| of any position (m): a lab or a field, not a planet (1e9 m is a typo)
WORKSPACE_M = 100.0
#: reference speed cap (m/s): the paper flies <= 1 m/s; beyond 10 m/s indoors is a typo
MAX_REF_SPEED_M_S = 10.0
#: reference acceleration cap (m/s^2): more than 1 g needs more than twice the hover thrust
#: sideways or down, which no multirotor with a 20 % margin has
MAX_REF_ACCEL_M_S2 = 9.81
#: angular-rate cap of an attitude reference (deg/s)
MAX_REF_RATE_DEG_S = 360.0
#: a takeoff must climb at least this much above where it starts (m)
MIN_TAKEOFF_CLIMB_M = 0.05
#: longest segment or timing (s): one hour, longer than any battery
MAX_SEGMENT_S = 3600.0
#: shortest segment (s): five ticks of the 500 Hz loop
MIN_SEGMENT_S = 0.01



# -- alpha profiles ---------------------------------------------------------------------------
@dataclass(frozen=True, kw_only=True)
class AlphaConstant:
    kind: Literal["constant"]
    value_deg: float = spec(ge=0.0, le=90.0, doc="tilt reference")


@dataclass(frozen=True, kw_only=True)
class AlphaSteps:
    kind: Literal["steps"]
    times_s: tuple[float, ...] = spec(ge=0.0, le=MAX_SEGMENT_S,
                                      doc="step instants from the segment start")
    values_deg: tuple[float, ...] = spec(ge=0.0, le=90.0, doc="value from each instant on")

    def __post_init__(self) -> None:
        if len(self.times_s) != len(self.values_deg) or not self.times_s:
            raise ConfigValueError("values_deg", "needs one value per entry of times_s")
        if any(b <= a for a, b in zip(self.times_s, self.times_s[1:], strict=False)):
            raise ConfigValueError("times_s", "must be strictly increasing")


@dataclass(frozen=True, kw_only=True)
class AlphaRamp:
    kind: Literal["ramp"]
    from_deg: float = spec(ge=0.0, le=90.0)
    to_deg: float = spec(ge=0.0, le=90.0)
    start_s: float = spec(0.0, ge=0.0, le=MAX_SEGMENT_S, doc="ramp start from the segment start")
    end_s: float = spec(gt=0.0, le=MAX_SEGMENT_S, doc="ramp end from the segment start")

    def __post_init__(self) -> None:
        if self.end_s <= self.start_s:
            raise ConfigValueError("end_s", f"must be after start_s ({self.start_s:g} s)")


@dataclass(frozen=True, kw_only=True)
class AlphaAuto:
    kind: Literal["auto"]
    # 50 N is more than the weight of any vehicle the project flies
    margin_n: float = spec(0.5, ge=0.0, le=50.0, doc="lateral force margin over the demand")
    # a minute of look-ahead is more than any segment needs; 0 = the demand now
    horizon_s: float = spec(4.0, ge=0.0, le=60.0, doc="look-ahead for the lateral demand")


AlphaProfile = AlphaConstant | AlphaSteps | AlphaRamp | AlphaAuto


# -- segments ---------------------------------------------------------------------------------
@dataclass(frozen=True, kw_only=True)
class HoldSegment:
    kind: Literal["hold"]
    duration_s: float = spec(ge=MIN_SEGMENT_S, le=MAX_SEGMENT_S)
    pos_w_m: tuple[float, float, float] | None = spec(None, ge=-WORKSPACE_M, le=WORKSPACE_M)
    yaw_deg: float | None = spec(None, ge=-360.0, le=360.0)
    measured: bool = True
    alpha: AlphaProfile | None = None


@dataclass(frozen=True, kw_only=True)
class GoToSegment:
    kind: Literal["goto"]
    duration_s: float = spec(ge=MIN_SEGMENT_S, le=MAX_SEGMENT_S)
    pos_w_m: tuple[float, float, float] = spec(ge=-WORKSPACE_M, le=WORKSPACE_M)
    yaw_deg: float | None = spec(None, ge=-360.0, le=360.0)
    measured: bool = True
    alpha: AlphaProfile | None = None


@dataclass(frozen=True, kw_only=True)
class SineSegment:
    kind: Literal["sine"]
    duration_s: float = spec(ge=MIN_SEGMENT_S, le=MAX_SEGMENT_S)
    axis: Literal["x", "y", "z"]
    amplitude_m: float = spec(ge=0.0, le=10.0)
    # 1 mHz (a 17-minute period) .. 10 Hz (beyond the position loop's bandwidth)
    frequency_hz: float = spec(ge=1e-3, le=10.0)
    fade_in_s: float = spec(0.0, ge=0.0, le=MAX_SEGMENT_S)
    fade_out_s: float = spec(0.0, ge=0.0, le=MAX_SEGMENT_S)
    measured: bool = True
    alpha: AlphaProfile | None = None

    def __post_init__(self) -> None:
        if self.fade_in_s + self.fade_out_s > self.duration_s:
            raise ConfigValueError("fade_in_s", "fade_in_s + fade_out_s exceed duration_s")
        w = 2.0 * math.pi * self.frequency_hz
        if self.amplitude_m * w > MAX_REF_SPEED_M_S:
            raise ConfigValueError("amplitude_m", f"peak speed A 2 pi f = "
                                   f"{self.amplitude_m * w:.3g} m/s; expected <= "
                                   f"{MAX_REF_SPEED_M_S:g} m/s")
        if self.amplitude_m * w * w > MAX_REF_ACCEL_M_S2:
            raise ConfigValueError("amplitude_m", f"peak acceleration A (2 pi f)^2 = "
                                   f"{self.amplitude_m * w * w:.3g} m/s^2; expected <= "
                                   f"{MAX_REF_ACCEL_M_S2:g} m/s^2")


@dataclass(frozen=True, kw_only=True)
class AttitudeSineSegment:
    kind: Literal["attitude_sine"]
    duration_s: float = spec(ge=MIN_SEGMENT_S, le=MAX_SEGMENT_S)
    axis: Literal["roll", "pitch", "yaw"]
    amplitude_deg: float = spec(ge=0.0, le=90.0)
    frequency_hz: float = spec(ge=1e-3, le=10.0)
    fade_in_s: float = spec(0.0, ge=0.0, le=MAX_SEGMENT_S)
    fade_out_s: float = spec(0.0, ge=0.0, le=MAX_SEGMENT_S)
    measured: bool = True
    alpha: AlphaProfile | None = None

    def __post_init__(self) -> None:
        if self.fade_in_s + self.fade_out_s > self.duration_s:
            raise ConfigValueError("fade_in_s", "fade_in_s + fade_out_s exceed duration_s")
        rate = self.amplitude_deg * 2.0 * math.pi * self.frequency_hz
        if rate > MAX_REF_RATE_DEG_S:
            raise ConfigValueError("amplitude_deg", f"peak angular rate A 2 pi f = {rate:.3g} "
                                   f"deg/s; expected <= {MAX_REF_RATE_DEG_S:g} deg/s")


@dataclass(frozen=True, kw_only=True)
class TakeoffSegment:
    kind: Literal["takeoff"]
    duration_s: float = spec(ge=MIN_SEGMENT_S, le=600.0)
    height_m: float = spec(gt=-WORKSPACE_M, le=WORKSPACE_M,
                           doc="target height of O_B above the world origin")
    measured: bool = False
    alpha: AlphaProfile | None = None


@dataclass(frozen=True, kw_only=True)
class LandSegment:
    kind: Literal["land"]
    duration_s: float = spec(ge=MIN_SEGMENT_S, le=600.0)
    sink_m: float = spec(0.05, ge=0.0, le=1.0, doc="aim this far below the start height")
    measured: bool = False
    alpha: AlphaProfile | None = None


Segment = (HoldSegment | GoToSegment | SineSegment | AttitudeSineSegment | TakeoffSegment
           | LandSegment)


@dataclass(frozen=True, kw_only=True)
class MissionSpec:
    """A mission file."""

    name: str
    description: str = ""
    start_pos_w_m: tuple[float, float, float] = spec(ge=-WORKSPACE_M, le=WORKSPACE_M,
                                                     doc="O_B at rest on the ground")
    start_yaw_deg: float = spec(0.0, ge=-360.0, le=360.0)
    segments: tuple[Segment, ...] = spec()

    def __post_init__(self) -> None:
        if not self.segments:
            raise ConfigValueError("segments", "a mission needs at least one segment")
        if len(self.segments) > 1000:
            raise ConfigValueError("segments", "expected at most 1000 segments")
        starts = [c.p0 for c in Mission(self)._segments]
        for i, (seg, p0) in enumerate(zip(self.segments, starts, strict=True)):
            key = f"segments[{i}]"
            if isinstance(seg, TakeoffSegment) and seg.height_m < p0[2] + MIN_TAKEOFF_CLIMB_M:
                raise ConfigValueError(
                    f"{key}.height_m", f"must be above where the takeoff starts (z = "
                    f"{p0[2]:g} m) by >= {MIN_TAKEOFF_CLIMB_M:g} m, got {seg.height_m:g}")
            _check_alpha_timing(seg, key)
            _check_min_jerk_move(seg, key, p0, self.start_pos_w_m[2])


def _check_alpha_timing(seg: Segment, key: str) -> None:
    prof = seg.alpha
    if isinstance(prof, AlphaSteps) and prof.times_s[-1] >= seg.duration_s:
        raise ConfigValueError(f"{key}.alpha.times_s", f"a step at {prof.times_s[-1]:g} s "
                               f"never happens in a segment of {seg.duration_s:g} s")
    if isinstance(prof, AlphaRamp) and prof.end_s > seg.duration_s:
        raise ConfigValueError(f"{key}.alpha.end_s", f"the ramp ends after its segment "
                               f"({seg.duration_s:g} s), got {prof.end_s:g}")


def _check_min_jerk_move(seg: Segment, key: str, p0: Vec3, ground_z: float) -> None:
    """Peak speed 1.875 d/T and acceleration 5.77 d/T^2 of a minimum-jerk move of length d."""
    if isinstance(seg, GoToSegment):
        target, field = seg.pos_w_m, "pos_w_m"
    elif isinstance(seg, TakeoffSegment):
        target, field = (p0[0], p0[1], seg.height_m), "height_m"
    elif isinstance(seg, LandSegment):
        target, field = (p0[0], p0[1], ground_z - seg.sink_m), "duration_s"
    else:
        return
    d = math.dist(p0, target)
    t = seg.duration_s
    speed, accel = 1.875 * d / t, 5.7735 * d / (t * t)
    if speed > MAX_REF_SPEED_M_S or accel > MAX_REF_ACCEL_M_S2:
        raise ConfigValueError(
            f"{key}.{field}", f"a {d:.3g} m move in {t:g} s peaks at {speed:.3g} m/s and "
            f"{accel:.3g} m/s^2; expected <= {MAX_REF_SPEED_M_S:g} m/s and "
            f"{MAX_REF_ACCEL_M_S2:g} m/s^2 (a longer duration_s)")


def segment_extents_w_m(spec_: MissionSpec) -> list[tuple[Vec3, Vec3]]:
    """Per segment, the corners (min, max) of the box its reference position stays in."""
    out: list[tuple[Vec3, Vec3]] = []
    for c in Mission(spec_)._segments:
        pts = [c.p0, c.p1]
        if isinstance(c.seg, SineSegment):
            i = _AXES[c.seg.axis]
            for sign in (-1.0, 1.0):
                p = list(c.p0)
                p[i] += sign * c.seg.amplitude_m
                pts.append((p[0], p[1], p[2]))
        lo = (min(p[0] for p in pts), min(p[1] for p in pts), min(p[2] for p in pts))
        hi = (max(p[0] for p in pts), max(p[1] for p in pts), max(p[2] for p in pts))
        out.append((lo, hi))
    return out


def peak_vertical_accel_m_s2(spec_: MissionSpec) -> list[float]:
    """Per segment, the largest |z''| of its reference (m/s^2): 5.77 dz/T^2 for a minimum-jerk
    move (as much up as down), A w^2 (1 + fades) for a sine along z, 0 otherwise."""
    out: list[float] = []
    for c in Mission(spec_)._segments:
        seg = c.seg
        if isinstance(seg, GoToSegment | TakeoffSegment | LandSegment):
            out.append(5.7735 * abs(c.p1[2] - c.p0[2]) / seg.duration_s**2)
        elif isinstance(seg, SineSegment) and seg.axis == "z":
            w = 2.0 * math.pi * seg.frequency_hz
            # the envelope's own derivatives add to A w^2 while it fades (bounded by 2x here)
            fading = seg.fade_in_s > 0.0 or seg.fade_out_s > 0.0
            out.append(seg.amplitude_m * w * w * (2.0 if fading else 1.0))
        else:
            out.append(0.0)
    return out


def explicit_alphas_deg(spec_: MissionSpec) -> list[tuple[str, float]]:
    """Every alpha value a mission file writes down, with its key path (``auto`` has none)."""
    out: list[tuple[str, float]] = []
    for i, seg in enumerate(spec_.segments):
        key, prof = f"segments[{i}].alpha", seg.alpha
        if isinstance(prof, AlphaConstant):
            out.append((f"{key}.value_deg", prof.value_deg))
        elif isinstance(prof, AlphaSteps):
            out += [(f"{key}.values_deg[{j}]", v) for j, v in enumerate(prof.values_deg)]
        elif isinstance(prof, AlphaRamp):
            out += [(f"{key}.from_deg", prof.from_deg), (f"{key}.to_deg", prof.to_deg)]
    return out


# -- runtime ----------------------------------------------------------------------------------
def _min_jerk(tau: float) -> tuple[float, float, float]:
    """s, ds/dtau, d2s/dtau2 of the quintic 10t^3 - 15t^4 + 6t^5 on [0, 1]."""
    if tau <= 0.0:
        return 0.0, 0.0, 0.0
    if tau >= 1.0:
        return 1.0, 0.0, 0.0
    t2 = tau * tau
    return (t2 * tau * (10.0 - 15.0 * tau + 6.0 * t2),
            30.0 * t2 * (1.0 - 2.0 * tau + t2),
            60.0 * tau * (1.0 - 3.0 * tau + 2.0 * t2))


def _envelope(t: float, dur: float, fade_in: float, fade_out: float
              ) -> tuple[float, float, float]:
    """Amplitude envelope e, e', e'' (fade in, then out, both minimum-jerk)."""
    e, de, dde = 1.0, 0.0, 0.0
    if fade_in > 0.0:
        s, ds, dds = _min_jerk(t / fade_in)
        e, de, dde = s, ds / fade_in, dds / (fade_in * fade_in)
    if fade_out > 0.0:
        s, ds, dds = _min_jerk((dur - t) / fade_out)
        ds, dds = -ds / fade_out, dds / (fade_out * fade_out)
        e, de, dde = e * s, de * s + e * ds, dde * s + 2.0 * de * ds + e * dds
    return e, de, dde


_AXES = {"x": 0, "y": 1, "z": 2, "roll": 0, "pitch": 1, "yaw": 2}
_UNIT = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))


def _yaw_q(yaw_rad: float) -> Quat:
    return quat_from_axis_angle((0.0, 0.0, 1.0), yaw_rad)


class _Compiled:
    """One segment with its start time, start pose and resolved alpha profile."""

    def __init__(self, seg: Segment, t0: float, p0: Vec3, yaw0: float, ground_z: float,
                 alpha: AlphaProfile) -> None:
        self.seg, self.t0, self.p0, self.yaw0 = seg, t0, p0, yaw0
        self.duration = seg.duration_s
        self.alpha = alpha
        self.p1, self.yaw1 = p0, yaw0
        if isinstance(seg, HoldSegment):
            self.p1 = seg.pos_w_m if seg.pos_w_m is not None else p0
            self.yaw1 = math.radians(seg.yaw_deg) if seg.yaw_deg is not None else yaw0
            self.p0, self.yaw0 = self.p1, self.yaw1
        elif isinstance(seg, GoToSegment):
            self.p1 = seg.pos_w_m
            self.yaw1 = math.radians(seg.yaw_deg) if seg.yaw_deg is not None else yaw0
        elif isinstance(seg, TakeoffSegment):
            self.p1 = (p0[0], p0[1], seg.height_m)
        elif isinstance(seg, LandSegment):
            self.p1 = (p0[0], p0[1], ground_z - seg.sink_m)
        elif isinstance(seg, SineSegment):
            end = self._eval(self.duration)
            self.p1 = end[0]

    def _eval(self, t: float) -> tuple[Vec3, Vec3, Vec3, Quat, Vec3]:
        seg = self.seg
        p0 = self.p0
        if isinstance(seg, GoToSegment | TakeoffSegment | LandSegment):
            s, ds, dds = _min_jerk(t / self.duration)
            ds, dds = ds / self.duration, dds / (self.duration * self.duration)
            d = (self.p1[0] - p0[0], self.p1[1] - p0[1], self.p1[2] - p0[2])
            dy = self.yaw1 - self.yaw0
            return ((p0[0] + s * d[0], p0[1] + s * d[1], p0[2] + s * d[2]),
                    (ds * d[0], ds * d[1], ds * d[2]), (dds * d[0], dds * d[1], dds * d[2]),
                    _yaw_q(self.yaw0 + s * dy), (0.0, 0.0, ds * dy))
        if isinstance(seg, SineSegment | AttitudeSineSegment):
            w = 2.0 * math.pi * seg.frequency_hz
            e, de, dde = _envelope(t, self.duration, seg.fade_in_s, seg.fade_out_s)
            sn, cs = math.sin(w * t), math.cos(w * t)
            x = e * sn
            dx = de * sn + e * w * cs
            ddx = dde * sn + 2.0 * de * w * cs - e * w * w * sn
            i = _AXES[seg.axis]
            if isinstance(seg, SineSegment):
                a = seg.amplitude_m
                p, v, acc = list(p0), [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]
                p[i] += a * x
                v[i] = a * dx
                acc[i] = a * ddx
                return ((p[0], p[1], p[2]), (v[0], v[1], v[2]), (acc[0], acc[1], acc[2]),
                        _yaw_q(self.yaw0), ZERO3)
            a = math.radians(seg.amplitude_deg)
            q = quat_mul(_yaw_q(self.yaw0), quat_from_axis_angle(_UNIT[i], a * x))
            om = [0.0, 0.0, 0.0]
            om[i] = a * dx
            return p0, ZERO3, ZERO3, q, (om[0], om[1], om[2])
        return p0, ZERO3, ZERO3, _yaw_q(self.yaw0), ZERO3

    def alpha_rad(self, t: float) -> float | None:
        prof = self.alpha
        if isinstance(prof, AlphaConstant):
            return math.radians(prof.value_deg)
        if isinstance(prof, AlphaSteps):
            i = bisect.bisect_right(prof.times_s, t) - 1
            return math.radians(prof.values_deg[max(i, 0)])
        if isinstance(prof, AlphaRamp):
            f = min(max((t - prof.start_s) / (prof.end_s - prof.start_s), 0.0), 1.0)
            return math.radians(prof.from_deg + f * (prof.to_deg - prof.from_deg))
        return None


class Mission:
    """A compiled mission: ``reference(t)`` at any time (held at the final pose afterwards)."""

    def __init__(self, spec_: MissionSpec) -> None:
        self.spec = spec_
        self.name = spec_.name
        p, yaw = spec_.start_pos_w_m, math.radians(spec_.start_yaw_deg)
        t = 0.0
        prev_alpha: AlphaProfile = AlphaConstant(kind="constant", value_deg=0.0)
        self._segments: list[_Compiled] = []
        for seg in spec_.segments:
            alpha = seg.alpha
            if alpha is None:
                if isinstance(prev_alpha, AlphaAuto):
                    alpha = prev_alpha
                else:
                    last = self._segments[-1].alpha_rad(self._segments[-1].duration) \
                        if self._segments else 0.0
                    alpha = AlphaConstant(kind="constant", value_deg=math.degrees(last or 0.0))
            c = _Compiled(seg, t, p, yaw, spec_.start_pos_w_m[2], alpha)
            self._segments.append(c)
            t += seg.duration_s
            p, yaw, prev_alpha = c.p1, c.yaw1, alpha
        self.duration_s = t
        self._starts = [c.t0 for c in self._segments]

    @property
    def start_pos_w_m(self) -> Vec3:
        return self.spec.start_pos_w_m

    @property
    def start_q_wb(self) -> Quat:
        return _yaw_q(math.radians(self.spec.start_yaw_deg)) if self.spec.start_yaw_deg \
            else IDENTITY_Q

    def segment_index(self, t_s: float) -> int:
        return max(0, min(bisect.bisect_right(self._starts, t_s) - 1, len(self._segments) - 1))

    def segment_bounds_s(self, index: int) -> tuple[float, float]:
        c = self._segments[index]
        return c.t0, c.t0 + c.duration

    def measured_interval_s(self) -> tuple[float, float] | None:
        """First and last instant of the measured segments (the experiment proper)."""
        meas = [c for c in self._segments if c.seg.measured]
        return (meas[0].t0, meas[-1].t0 + meas[-1].duration) if meas else None

    def auto_profile(self, t_s: float) -> AlphaAuto | None:
        prof = self._segments[self.segment_index(t_s)].alpha
        return prof if isinstance(prof, AlphaAuto) else None

    def reference(self, t_s: float) -> Reference:
        i = self.segment_index(t_s)
        c = self._segments[i]
        tl = min(max(t_s - c.t0, 0.0), c.duration)
        p, v, a, q, w = c._eval(tl)
        return Reference(t_s, p, v, a, q, w, c.alpha_rad(tl), i, c.seg.measured)

    def lateral_demand_n(self, t_s: float, horizon_s: float, mass_kg: float,
                         gravity_m_s2: float, step_s: float = 0.1) -> float:
        """Largest lateral body-frame force ``|(R_r^T m (a_r + g e3))_xy|`` (N) the reference
        needs over ``[t_s, t_s + horizon_s]``, sampled every ``step_s``."""
        worst = 0.0
        n = max(1, int(horizon_s / step_s) + 1)
        for k in range(n):
            ref = self.reference(t_s + k * step_s)
            r = quat_to_rot(ref.q_wr)
            fx, fy = mass_kg * ref.acc_w_m_s2[0], mass_kg * ref.acc_w_m_s2[1]
            fz = mass_kg * (ref.acc_w_m_s2[2] + gravity_m_s2)
            bx = r[0] * fx + r[3] * fy + r[6] * fz
            by = r[1] * fx + r[4] * fy + r[7] * fz
            worst = max(worst, math.sqrt(bx * bx + by * by))
        return worst

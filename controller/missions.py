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
- ``circle``, ``lissajous`` (figure eight), ``waypoints``, ``ramp``, ``trajectory`` (a CSV
  file): see each class and :mod:`controller.mission_paths` / :mod:`controller.trajectory_csv`;
- ``takeoff``: minimum-jerk climb to ``height_m``; ``land``: minimum-jerk descent to the start
  height minus ``sink_m`` (so the vehicle settles on its gear). Not measured by default.

Any segment may carry an ``attitude:`` block (:class:`AttitudeBlock`): constant roll/pitch/yaw
offsets blended in and out, and/or a body-axis sine, played on top of the segment's own
attitude while it translates.

Each segment may carry an ``alpha`` profile (times relative to the segment start):
``constant``, ``steps``, ``ramp`` or ``auto`` (:mod:`controller.tilt_planner`); without one a
segment keeps the previous segment's final alpha (or stays ``auto``).

``accept_lateral_shortfall: true`` on a segment says that it asks for more lateral force than
its tilt gives on purpose (the paper's Exp. 2a/2b at low tilt show R_d leaving R_r): the
pre-flight check (:mod:`controller.preflight`) then reports its spans as accepted instead of
warning.

Validation (before anything flies): positions lie in a sane workspace (:data:`WORKSPACE_M`),
every takeoff climbs above where it starts, alpha steps and ramps happen inside their segment,
and no segment asks for more than :data:`MAX_REF_SPEED_M_S` or :data:`MAX_REF_ACCEL_M_S2` (the
new kinds and attitude blocks: checked on the reference sampled every 10 ms). The
checks that need the vehicle or the session (tilt range, thrust, geofence) use
:func:`segment_extents_w_m`, :func:`explicit_alphas_deg` and :func:`peak_vertical_accel_m_s2`.
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Literal

from config.schema import ConfigValueError, spec
from controller.mission_paths import (
    MIN_JERK_PEAK_ACCEL,
    MIN_JERK_PEAK_RATE,
    CirclePath,
    LissajousPath,
    PathSample,
    RampPath,
    WaypointsPath,
    envelope,
    min_jerk,
)
from controller.reference import (
    IDENTITY_Q,
    ZERO3,
    Quat,
    Reference,
    Vec3,
    euler_zyx_from_rot,
    quat_from_axis_angle,
    quat_from_euler_zyx,
    quat_mul,
    quat_to_rot,
)
from controller.trajectory_csv import (
    Limits,
    TrajectoryTable,
    load_trajectory_csv,
    resolve_trajectory_path,
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
#: fastest touchdown of a ``land`` (m/s, the reference's descent rate where it passes the
#: start height). The impact is not seen by the estimator: the tk3 ``I`` frame clips it at
#: 32.767 m/s^2 and the driver drops a one-sample spike, so the estimate keeps descending at the
#: touchdown speed while MoCap shows the vehicle stopped, and the controller lifts the vehicle
#: off again. Measured with the UKF on the short hover (paper-calibrated): a 0.42 m/s touchdown
#: ended every emulated flight (6 seeds) in the "MoCap and IMU disagree" failsafe after a hop
#: to 0.37 m; in ``fasthex simulate`` a 0.25 m/s one came down again at 0.78-0.86 m/s (5 seeds),
#: a 0.21 m/s one at up to 0.44 m/s, a 0.18 m/s one at no more than 0.19 m/s. The shipped
#: missions touch down at 0.12-0.17 m/s.
MAX_TOUCHDOWN_SPEED_M_S = 0.18
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


# -- attitude on top of any segment -----------------------------------------------------------
@dataclass(frozen=True, kw_only=True)
class AttitudeSine:
    """``R_axis(A e(t) sin(2 pi f t))`` about a body axis (the ``attitude_sine`` motion)."""

    axis: Literal["roll", "pitch", "yaw"]
    amplitude_deg: float = spec(ge=0.0, le=90.0)
    frequency_hz: float = spec(ge=1e-3, le=10.0)
    fade_in_s: float = spec(0.0, ge=0.0, le=MAX_SEGMENT_S)
    fade_out_s: float = spec(0.0, ge=0.0, le=MAX_SEGMENT_S)


@dataclass(frozen=True, kw_only=True)
class AttitudeBlock:
    """An attitude reference played on top of a segment's own (``attitude:`` on any segment).

    ``R_r = R_segment Rz(e yaw) Ry(e pitch) Rx(e roll) R_sine``: constant ZYX offsets, blended
    in over the first ``blend_s`` and out over the last ``blend_s`` (minimum jerk, ``e`` from 0
    to 1 and back; 0 = a step at both ends), then an optional body-axis sine. The segment's
    translation is unchanged: the controller's lateral force does the moving, the tilt supplies
    it (see the pre-flight check in :mod:`controller.preflight`).
    """

    roll_deg: float = spec(0.0, ge=-90.0, le=90.0)
    pitch_deg: float = spec(0.0, ge=-80.0, le=80.0)
    yaw_deg: float = spec(0.0, ge=-360.0, le=360.0)
    blend_s: float = spec(1.0, ge=0.0, le=MAX_SEGMENT_S, doc="offset blend at each end")
    sine: AttitudeSine | None = None


AttitudeEval = tuple[Quat, Vec3]


# -- segments ---------------------------------------------------------------------------------
@dataclass(frozen=True, kw_only=True)
class HoldSegment:
    kind: Literal["hold"]
    duration_s: float = spec(ge=MIN_SEGMENT_S, le=MAX_SEGMENT_S)
    pos_w_m: tuple[float, float, float] | None = spec(None, ge=-WORKSPACE_M, le=WORKSPACE_M)
    yaw_deg: float | None = spec(None, ge=-360.0, le=360.0)
    measured: bool = True
    accept_lateral_shortfall: bool = False
    alpha: AlphaProfile | None = None
    attitude: AttitudeBlock | None = None


@dataclass(frozen=True, kw_only=True)
class GoToSegment:
    kind: Literal["goto"]
    duration_s: float = spec(ge=MIN_SEGMENT_S, le=MAX_SEGMENT_S)
    pos_w_m: tuple[float, float, float] = spec(ge=-WORKSPACE_M, le=WORKSPACE_M)
    yaw_deg: float | None = spec(None, ge=-360.0, le=360.0)
    measured: bool = True
    accept_lateral_shortfall: bool = False
    alpha: AlphaProfile | None = None
    attitude: AttitudeBlock | None = None


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
    accept_lateral_shortfall: bool = False
    alpha: AlphaProfile | None = None
    attitude: AttitudeBlock | None = None

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
    accept_lateral_shortfall: bool = False
    alpha: AlphaProfile | None = None
    attitude: AttitudeBlock | None = None

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
    accept_lateral_shortfall: bool = False
    alpha: AlphaProfile | None = None
    attitude: AttitudeBlock | None = None


@dataclass(frozen=True, kw_only=True)
class LandSegment:
    kind: Literal["land"]
    duration_s: float = spec(ge=MIN_SEGMENT_S, le=600.0)
    sink_m: float = spec(0.05, ge=0.0, le=1.0, doc="aim this far below the start height")
    measured: bool = False
    accept_lateral_shortfall: bool = False
    alpha: AlphaProfile | None = None
    attitude: AttitudeBlock | None = None


@dataclass(frozen=True, kw_only=True)
class CircleSegment:
    """A circle through the segment's start point in a coordinate plane; the angular rate fades
    in and out (minimum jerk), so the vehicle starts and ends at rest."""

    kind: Literal["circle"]
    duration_s: float = spec(ge=MIN_SEGMENT_S, le=MAX_SEGMENT_S)
    centre_w_m: tuple[float, float, float] | None = spec(
        None, ge=-WORKSPACE_M, le=WORKSPACE_M,
        doc="centre; the radius and start angle then follow from the start point")
    radius_m: float | None = spec(None, gt=0.0, le=WORKSPACE_M,
                                  doc="without centre_w_m: the centre lies at start_angle_deg")
    start_angle_deg: float = spec(180.0, ge=-360.0, le=360.0,
                                  doc="angle of the start point seen from the centre")
    period_s: float | None = spec(None, gt=0.0, le=MAX_SEGMENT_S, doc="one turn at full rate")
    speed_m_s: float | None = spec(None, gt=0.0, le=MAX_REF_SPEED_M_S, doc="or: path speed")
    plane: Literal["xy", "xz", "yz"] = "xy"
    # ccw turns from the plane's first axis towards its second (x to y, x to z, y to z)
    direction: Literal["ccw", "cw"] = "ccw"
    fade_in_s: float = spec(2.0, gt=0.0, le=MAX_SEGMENT_S)
    fade_out_s: float = spec(2.0, gt=0.0, le=MAX_SEGMENT_S)
    measured: bool = True
    accept_lateral_shortfall: bool = False
    alpha: AlphaProfile | None = None
    attitude: AttitudeBlock | None = None

    def __post_init__(self) -> None:
        if (self.period_s is None) == (self.speed_m_s is None):
            raise ConfigValueError("period_s", "give exactly one of period_s and speed_m_s")
        if (self.centre_w_m is None) == (self.radius_m is None):
            raise ConfigValueError("radius_m", "give exactly one of centre_w_m and radius_m")
        if self.fade_in_s + self.fade_out_s > self.duration_s:
            raise ConfigValueError("fade_in_s", "fade_in_s + fade_out_s exceed duration_s")


@dataclass(frozen=True, kw_only=True)
class LissajousSegment:
    """``p_k = p0_k + A_k e(t) sin(2 pi f_k t + phase_k)`` on x, y, z at once around the start
    point, with a fade envelope e (both fades required: rest at both ends). A figure eight:
    ``amplitudes_m: [A, B, 0]``, ``frequencies_hz: [f, 2 f, 0]``."""

    kind: Literal["lissajous"]
    duration_s: float = spec(ge=MIN_SEGMENT_S, le=MAX_SEGMENT_S)
    amplitudes_m: tuple[float, float, float] = spec(ge=0.0, le=10.0)
    frequencies_hz: tuple[float, float, float] = spec(ge=0.0, le=10.0)
    phases_deg: tuple[float, float, float] = spec((0.0, 0.0, 0.0), ge=-360.0, le=360.0)
    fade_in_s: float = spec(2.0, gt=0.0, le=MAX_SEGMENT_S)
    fade_out_s: float = spec(2.0, gt=0.0, le=MAX_SEGMENT_S)
    measured: bool = True
    accept_lateral_shortfall: bool = False
    alpha: AlphaProfile | None = None
    attitude: AttitudeBlock | None = None

    def __post_init__(self) -> None:
        if self.fade_in_s + self.fade_out_s > self.duration_s:
            raise ConfigValueError("fade_in_s", "fade_in_s + fade_out_s exceed duration_s")


@dataclass(frozen=True, kw_only=True)
class WaypointsSegment:
    """Through each point in turn along rest-to-rest minimum-jerk legs, each as short as the
    speed, acceleration and yaw-rate limits allow (the segment's duration follows)."""

    kind: Literal["waypoints"]
    points_w_m: tuple[tuple[float, float, float], ...] = spec(ge=-WORKSPACE_M, le=WORKSPACE_M)
    yaw_deg: tuple[float, ...] | None = spec(None, ge=-360.0, le=360.0,
                                              doc="heading at each point (default: keep)")
    max_speed_m_s: float = spec(1.0, gt=0.0, le=MAX_REF_SPEED_M_S)
    max_accel_m_s2: float = spec(1.0, gt=0.0, le=MAX_REF_ACCEL_M_S2)
    max_yaw_rate_deg_s: float = spec(45.0, gt=0.0, le=MAX_REF_RATE_DEG_S)
    dwell_s: float = spec(0.0, ge=0.0, le=MAX_SEGMENT_S, doc="rest at each point")
    measured: bool = True
    accept_lateral_shortfall: bool = False
    alpha: AlphaProfile | None = None
    attitude: AttitudeBlock | None = None

    def __post_init__(self) -> None:
        if not 1 <= len(self.points_w_m) <= 1000:
            raise ConfigValueError("points_w_m", "expected 1 to 1000 points")
        if self.yaw_deg is not None and len(self.yaw_deg) != len(self.points_w_m):
            raise ConfigValueError("yaw_deg", "expected one heading per point")


@dataclass(frozen=True, kw_only=True)
class RampSegment:
    """A straight move to ``pos_w_m`` and/or a turn to ``yaw_deg`` at constant rate over
    ``duration_s``; ``smooth_s`` blends the rate in and out at each end (minimum jerk) so the
    acceleration stays bounded (0: the velocity steps, as a pure linear ramp does)."""

    kind: Literal["ramp"]
    duration_s: float = spec(ge=MIN_SEGMENT_S, le=MAX_SEGMENT_S)
    pos_w_m: tuple[float, float, float] | None = spec(None, ge=-WORKSPACE_M, le=WORKSPACE_M)
    yaw_deg: float | None = spec(None, ge=-360.0, le=360.0)
    smooth_s: float = spec(0.0, ge=0.0, le=MAX_SEGMENT_S)
    measured: bool = True
    accept_lateral_shortfall: bool = False
    alpha: AlphaProfile | None = None
    attitude: AttitudeBlock | None = None

    def __post_init__(self) -> None:
        if self.pos_w_m is None and self.yaw_deg is None:
            raise ConfigValueError("pos_w_m", "a ramp needs pos_w_m, yaw_deg or both")
        if 2.0 * self.smooth_s >= self.duration_s:
            raise ConfigValueError("smooth_s", f"2 smooth_s must be shorter than duration_s "
                                   f"({self.duration_s:g} s)")


@dataclass(frozen=True, kw_only=True)
class TrajectorySegment:
    """A trajectory from a CSV file (format in :mod:`controller.trajectory_csv`), read and
    checked when the mission is loaded; its duration is the file's time span. ``origin:
    start`` shifts the positions so the first row is where the segment starts; ``world`` takes
    them as they are (the first row must then be where the previous segment ends)."""

    kind: Literal["trajectory"]
    file: str = spec(doc="CSV file, relative to the mission file")
    origin: Literal["start", "world"] = "start"
    measured: bool = True
    accept_lateral_shortfall: bool = False
    alpha: AlphaProfile | None = None
    attitude: AttitudeBlock | None = None
    table: TrajectoryTable = field(init=False, compare=False, repr=False)

    def __post_init__(self) -> None:
        if not self.file.strip():
            raise ConfigValueError("file", "expected a CSV file name")
        limits = Limits(MAX_REF_SPEED_M_S, MAX_REF_ACCEL_M_S2, MAX_REF_RATE_DEG_S)
        # frozen: the table is derived from `file` once, at load time
        object.__setattr__(self, "table",
                           load_trajectory_csv(resolve_trajectory_path(self.file), limits))


Segment = (HoldSegment | GoToSegment | SineSegment | AttitudeSineSegment | TakeoffSegment
           | LandSegment | CircleSegment | LissajousSegment | WaypointsSegment | RampSegment
           | TrajectorySegment)


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
        compiled = Mission(self)._segments
        for i, c in enumerate(compiled):
            seg, p0, key = c.seg, c.p0, f"segments[{i}]"
            if isinstance(seg, TakeoffSegment) and seg.height_m < p0[2] + MIN_TAKEOFF_CLIMB_M:
                raise ConfigValueError(
                    f"{key}.height_m", f"must be above where the takeoff starts (z = "
                    f"{p0[2]:g} m) by >= {MIN_TAKEOFF_CLIMB_M:g} m, got {seg.height_m:g}")
            _check_alpha_timing(seg, c.duration, key)
            _check_min_jerk_move(seg, key, p0, self.start_pos_w_m[2])
            _check_attitude_block(seg, c.duration, key)
            if isinstance(seg, _SAMPLED_KINDS) or seg.attitude is not None:
                _check_sampled_limits(c, key)


#: how far below the start height a reference in the air may dip (rounding of paths) (m)
BELOW_GROUND_TOLERANCE_M = 1e-3


def check_ends_on_ground(spec_: MissionSpec) -> None:
    """A mission to fly ends on the ground: a ``land``, then at most ``hold`` segments (on the
    ground). A mission that ended in the air would leave the vehicle hovering at its last
    reference (the ground station lands it by itself only as a failsafe) and ``simulate``
    stops the motors there; a segment after a ``land`` other than a hold would climb from the
    ground after the flight was taken for over. In the air the reference stays above the
    ground (the start height). Checked where mission files are loaded to fly or simulate: a
    mission spec alone may be a fragment (e.g. to test one segment kind)."""
    lands = [i for i, seg in enumerate(spec_.segments) if isinstance(seg, LandSegment)]
    if not lands:
        last = len(spec_.segments) - 1
        raise ConfigValueError(
            f"segments[{last}]", f"the mission ends in the air (z = "
            f"{Mission(spec_)._segments[-1].p1[2]:g} m): "
            "expected a land segment at its end (then only hold segments)")
    for i in range(lands[-1] + 1, len(spec_.segments)):
        seg = spec_.segments[i]
        if not isinstance(seg, HoldSegment):
            raise ConfigValueError(
                f"segments[{i}].kind", f"a {seg.kind} after the land: expected only hold "
                "segments after the mission's last land (the vehicle is on the ground)")
    # in the air, the reference stays above the floor (the start height, where the vehicle
    # rests): one under it drives the vehicle into the ground mid-mission (simulate counted
    # the touchdowns and still said ok; fly ended in a failsafe)
    ground_z = spec_.start_pos_w_m[2]
    on_ground = True    # from the start, and after a land until the next take-off
    for i, (seg, (lo, _)) in enumerate(zip(spec_.segments, segment_extents_w_m(spec_),
                                          strict=True)):
        if isinstance(seg, TakeoffSegment):
            on_ground = False
            continue   # it climbs from where it rests (after a land: its sink_m under)
        if isinstance(seg, LandSegment):
            on_ground = True
            continue
        if on_ground and isinstance(seg, HoldSegment):
            continue
        if lo[2] < ground_z - BELOW_GROUND_TOLERANCE_M:
            field_name = {"takeoff": "height_m", "sine": "amplitude_m"}.get(seg.kind,
                                                                            "pos_w_m")
            raise ConfigValueError(
                f"segments[{i}].{field_name}", f"the reference reaches z = {lo[2]:.3g} m, "
                f"below the ground (the start height, z = {ground_z:g} m)")


def _check_alpha_timing(seg: Segment, duration_s: float, key: str) -> None:
    prof = seg.alpha
    if isinstance(prof, AlphaSteps) and prof.times_s[-1] >= duration_s:
        raise ConfigValueError(f"{key}.alpha.times_s", f"a step at {prof.times_s[-1]:g} s "
                               f"never happens in a segment of {duration_s:g} s")
    if isinstance(prof, AlphaRamp) and prof.end_s > duration_s:
        raise ConfigValueError(f"{key}.alpha.end_s", f"the ramp ends after its segment "
                               f"({duration_s:g} s), got {prof.end_s:g}")


def _check_min_jerk_move(seg: Segment, key: str, p0: Vec3, ground_z: float) -> None:
    """Peak speed 1.875 d/T and acceleration 5.77 d/T^2 of a minimum-jerk move of length d."""
    if isinstance(seg, GoToSegment):
        target, name = seg.pos_w_m, "pos_w_m"
    elif isinstance(seg, TakeoffSegment):
        target, name = (p0[0], p0[1], seg.height_m), "height_m"
    elif isinstance(seg, LandSegment):
        target, name = (p0[0], p0[1], ground_z - seg.sink_m), "duration_s"
    else:
        return
    d = math.dist(p0, target)
    t = seg.duration_s
    speed, accel = MIN_JERK_PEAK_RATE * d / t, MIN_JERK_PEAK_ACCEL * d / (t * t)
    if speed > MAX_REF_SPEED_M_S or accel > MAX_REF_ACCEL_M_S2:
        raise ConfigValueError(
            f"{key}.{name}", f"a {d:.3g} m move in {t:g} s peaks at {speed:.3g} m/s and "
            f"{accel:.3g} m/s^2; expected <= {MAX_REF_SPEED_M_S:g} m/s and "
            f"{MAX_REF_ACCEL_M_S2:g} m/s^2 (a longer duration_s)")
    if isinstance(seg, LandSegment):
        touchdown = touchdown_speed_m_s(p0[2] - ground_z, seg.sink_m, t)
        if touchdown > MAX_TOUCHDOWN_SPEED_M_S:
            raise ConfigValueError(
                f"{key}.duration_s", f"this land touches down (passes the start height) at "
                f"{touchdown:.3f} m/s; expected <= {MAX_TOUCHDOWN_SPEED_M_S:g} m/s, as the "
                f"estimator does not see a harder impact (a longer duration_s or a smaller "
                f"sink_m)")


def touchdown_speed_m_s(height_m: float, sink_m: float, duration_s: float) -> float:
    """Descent rate (m/s) of a ``land`` from ``height_m`` above the start height, aiming
    ``sink_m`` below it in ``duration_s``, where it passes the start height (0 when it
    starts at or below it, or aims no lower)."""
    if height_m <= 0.0 or sink_m <= 0.0:
        return 0.0
    d = height_m + sink_m
    lo, hi = 0.0, 1.0  # min_jerk(tau) = height / d: s is increasing on [0, 1]
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if min_jerk(mid)[0] < height_m / d else (lo, mid)
    return d / duration_s * min_jerk(0.5 * (lo + hi))[1]


def _check_attitude_block(seg: Segment, duration_s: float, key: str) -> None:
    blk = seg.attitude
    if blk is None:
        return
    if 2.0 * blk.blend_s > duration_s:
        raise ConfigValueError(f"{key}.attitude.blend_s", f"2 blend_s exceed the segment "
                               f"({duration_s:.3g} s)")
    if blk.sine is not None and blk.sine.fade_in_s + blk.sine.fade_out_s > duration_s:
        raise ConfigValueError(f"{key}.attitude.sine.fade_in_s", f"fade_in_s + fade_out_s "
                               f"exceed the segment ({duration_s:.3g} s)")


#: the segment kinds whose limits are checked on the reference itself (sampled)
_SAMPLED_KINDS = (CircleSegment, LissajousSegment, RampSegment)
#: sampling step of those checks and of the extents (s): 10 ms moves < 0.1 m at the speed cap
_SAMPLE_S = 0.01


def _samples(c: _Compiled) -> list[float]:
    n = max(2, math.ceil(c.duration / _SAMPLE_S) + 1)
    return [c.duration * k / (n - 1) for k in range(n)]


def _check_sampled_limits(c: _Compiled, key: str) -> None:
    """Speed, acceleration and angular rate of the reference within the module's caps."""
    what = {CircleSegment: "period_s", LissajousSegment: "amplitudes_m",
            RampSegment: "duration_s"}.get(type(c.seg), "duration_s")
    for t in _samples(c):
        _, v, a, _, w = c.eval(t)
        speed, accel = math.hypot(*v), math.hypot(*a)
        rate = math.degrees(math.hypot(*w))
        if speed > MAX_REF_SPEED_M_S * (1.0 + 1e-9):
            raise ConfigValueError(f"{key}.{what}", f"the reference reaches {speed:.3g} m/s at "
                                   f"{t:.3g} s into the segment; expected <= "
                                   f"{MAX_REF_SPEED_M_S:g} m/s")
        if accel > MAX_REF_ACCEL_M_S2 * (1.0 + 1e-9):
            raise ConfigValueError(f"{key}.{what}", f"the reference reaches {accel:.3g} m/s^2 at "
                                   f"{t:.3g} s into the segment; expected <= "
                                   f"{MAX_REF_ACCEL_M_S2:g} m/s^2")
        if rate > MAX_REF_RATE_DEG_S * (1.0 + 1e-9):
            where = "attitude" if c.seg.attitude is not None else what
            raise ConfigValueError(f"{key}.{where}", f"the reference turns at {rate:.3g} deg/s "
                                   f"at {t:.3g} s into the segment; expected <= "
                                   f"{MAX_REF_RATE_DEG_S:g} deg/s")


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
        elif c.path is not None or c.table is not None:
            pts += [c.eval(t)[0] for t in _samples(c)]
        lo = (min(p[0] for p in pts), min(p[1] for p in pts), min(p[2] for p in pts))
        hi = (max(p[0] for p in pts), max(p[1] for p in pts), max(p[2] for p in pts))
        out.append((lo, hi))
    return out


def peak_vertical_accel_m_s2(spec_: MissionSpec) -> list[float]:
    """Per segment, the largest |z''| of its reference (m/s^2): 5.77 dz/T^2 for a minimum-jerk
    move (as much up as down), A w^2 (1 + fades) for a sine along z, sampled on the paths of
    the other moving kinds, 0 otherwise."""
    out: list[float] = []
    for c in Mission(spec_)._segments:
        seg = c.seg
        if isinstance(seg, GoToSegment | TakeoffSegment | LandSegment):
            out.append(MIN_JERK_PEAK_ACCEL * abs(c.p1[2] - c.p0[2]) / seg.duration_s**2)
        elif isinstance(seg, SineSegment) and seg.axis == "z":
            w = 2.0 * math.pi * seg.frequency_hz
            # the envelope's own derivatives add to A w^2 while it fades (bounded by 2x here)
            fading = seg.fade_in_s > 0.0 or seg.fade_out_s > 0.0
            out.append(seg.amplitude_m * w * w * (2.0 if fading else 1.0))
        elif c.path is not None or c.table is not None:
            out.append(max(abs(c.eval(t)[2][2]) for t in _samples(c)))
        else:
            out.append(0.0)
    return out


def explicit_alphas_deg(spec_: MissionSpec) -> list[tuple[str, float]]:
    """Every alpha value a mission file writes down, with its key path (``auto`` has none); a
    trajectory's ``alpha_deg`` column counts with the key of its ``file``."""
    out: list[tuple[str, float]] = []
    for i, seg in enumerate(spec_.segments):
        key, prof = f"segments[{i}].alpha", seg.alpha
        if isinstance(prof, AlphaConstant):
            out.append((f"{key}.value_deg", prof.value_deg))
        elif isinstance(prof, AlphaSteps):
            out += [(f"{key}.values_deg[{j}]", v) for j, v in enumerate(prof.values_deg)]
        elif isinstance(prof, AlphaRamp):
            out += [(f"{key}.from_deg", prof.from_deg), (f"{key}.to_deg", prof.to_deg)]
        elif prof is None and isinstance(seg, TrajectorySegment) and seg.table.alpha_deg:
            col = seg.table.alpha_deg
            out += [(f"segments[{i}].file", min(col)), (f"segments[{i}].file", max(col))]
    return out


# -- runtime ----------------------------------------------------------------------------------
_AXES = {"x": 0, "y": 1, "z": 2, "roll": 0, "pitch": 1, "yaw": 2}
_UNIT = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
#: a circle's given centre must lie in the start point's plane, a world-frame trajectory must
#: start where the previous segment ends, within this (m)
_JOIN_TOLERANCE_M = 0.01


def _yaw_q(yaw_rad: float) -> Quat:
    return quat_from_axis_angle((0.0, 0.0, 1.0), yaw_rad)


def _rot_t(q: Quat, v: Vec3) -> Vec3:
    """``R(q)^T v``: a vector of the parent frame in the rotated one."""
    r = quat_to_rot(q)
    return (r[0] * v[0] + r[3] * v[1] + r[6] * v[2], r[1] * v[0] + r[4] * v[1] + r[7] * v[2],
            r[2] * v[0] + r[5] * v[1] + r[8] * v[2])


def _zyx_body_rate(roll: float, pitch: float, droll: float, dpitch: float, dyaw: float
                   ) -> Vec3:
    """Body angular velocity of ``Rz(yaw) Ry(pitch) Rx(roll)`` for the given angle rates."""
    sr, cr, sp, cp = math.sin(roll), math.cos(roll), math.sin(pitch), math.cos(pitch)
    return (droll - dyaw * sp, dpitch * cr + dyaw * sr * cp, -dpitch * sr + dyaw * cr * cp)


def _circle(seg: CircleSegment, p0: Vec3, yaw0: float, key: str) -> CirclePath:
    i, j, k = {"xy": (0, 1, 2), "xz": (0, 2, 1), "yz": (1, 2, 0)}[seg.plane]
    if seg.centre_w_m is not None:
        c = seg.centre_w_m
        if abs(c[k] - p0[k]) > _JOIN_TOLERANCE_M:
            raise ConfigValueError(f"{key}.centre_w_m", f"the centre must lie in the {seg.plane} "
                                   f"plane of the start point ({'xyz'[k]} = {p0[k]:g} m)")
        radius = math.hypot(p0[i] - c[i], p0[j] - c[j])
        if radius < 1e-3:
            raise ConfigValueError(f"{key}.centre_w_m", "the centre is the start point; "
                                   "expected a radius of at least 1 mm")
        start = math.atan2(p0[j] - c[j], p0[i] - c[i])
        centre = (c[0], c[1], c[2])
    else:
        assert seg.radius_m is not None
        radius, start = seg.radius_m, math.radians(seg.start_angle_deg)
        cl = list(p0)
        cl[i] -= radius * math.cos(start)
        cl[j] -= radius * math.sin(start)
        centre = (cl[0], cl[1], cl[2])
    omega = (2.0 * math.pi / seg.period_s if seg.period_s is not None
             else (seg.speed_m_s or 0.0) / radius)
    return CirclePath(centre, radius, omega, 1.0 if seg.direction == "ccw" else -1.0, start,
                      seg.plane, seg.duration_s, seg.fade_in_s, seg.fade_out_s, yaw0)


class _Compiled:
    """One segment with its start time, start pose, duration and resolved alpha profile."""

    def __init__(self, seg: Segment, t0: float, p0: Vec3, yaw0: float, ground_z: float,
                 alpha: AlphaProfile, key: str) -> None:
        self.seg, self.t0, self.p0, self.yaw0 = seg, t0, p0, yaw0
        self.alpha = alpha
        self.p1, self.yaw1 = p0, yaw0
        self.path: CirclePath | LissajousPath | RampPath | WaypointsPath | None = None
        self.table: TrajectoryTable | None = None
        self.offset_w_m: Vec3 = ZERO3
        if isinstance(seg, WaypointsSegment):
            yaws = [None] * len(seg.points_w_m) if seg.yaw_deg is None else \
                [math.radians(y) for y in seg.yaw_deg]
            path = WaypointsPath(p0, yaw0, seg.points_w_m, yaws, seg.max_speed_m_s,
                                 seg.max_accel_m_s2, math.radians(seg.max_yaw_rate_deg_s),
                                 seg.dwell_s, MIN_SEGMENT_S)
            self.path, self.duration = path, path.duration_s
        elif isinstance(seg, TrajectorySegment):
            self.table, self.duration = seg.table, max(seg.table.duration_s, MIN_SEGMENT_S)
            first = seg.table.first_w_m
            if seg.origin == "start":
                self.offset_w_m = (p0[0] - first[0], p0[1] - first[1], p0[2] - first[2])
            elif math.dist(first, p0) > _JOIN_TOLERANCE_M:
                raise ConfigValueError(f"{key}.origin", f"the file's first row is at "
                                       f"{_fmt(first)} m but the segment starts at {_fmt(p0)} m; "
                                       "expected a goto there first, or origin: start")
        else:
            self.duration = seg.duration_s
        if isinstance(seg, CircleSegment):
            self.path = _circle(seg, p0, yaw0, key)
        elif isinstance(seg, LissajousSegment):
            self.path = LissajousPath(
                p0, seg.amplitudes_m, _vec(2.0 * math.pi * f for f in seg.frequencies_hz),
                _vec(math.radians(ph) for ph in seg.phases_deg), seg.duration_s,
                seg.fade_in_s, seg.fade_out_s, yaw0)
        elif isinstance(seg, RampSegment):
            self.path = RampPath(p0, p0 if seg.pos_w_m is None else seg.pos_w_m, yaw0,
                                 yaw0 if seg.yaw_deg is None else math.radians(seg.yaw_deg),
                                 seg.duration_s, seg.smooth_s)
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
            self.p1 = self._base(self.duration)[0]
        elif self.path is not None:
            end = self.path.eval(self.duration)
            self.p1, self.yaw1 = end[0], end[3]
        elif self.table is not None:
            self.p1 = self._base(self.duration)[0]
            if self.table.has_attitude:
                self.yaw1 = euler_zyx_from_rot(quat_to_rot(self._base(self.duration)[3]))[2]

    def _base(self, t: float) -> tuple[Vec3, Vec3, Vec3, Quat, Vec3]:
        """The segment's own reference (without its ``attitude`` block)."""
        seg = self.seg
        p0 = self.p0
        if self.path is not None:
            sample: PathSample = self.path.eval(t)
            p, v, a, yaw, dyaw = sample
            return p, v, a, _yaw_q(yaw), (0.0, 0.0, dyaw)
        if self.table is not None:
            p, v, a = self.table.eval(t)
            o = self.offset_w_m
            p = (p[0] + o[0], p[1] + o[1], p[2] + o[2])
            if self.table.has_attitude:
                q, w = self.table.attitude(t)
                return p, v, a, q, w
            return p, v, a, _yaw_q(self.yaw0), ZERO3
        if isinstance(seg, GoToSegment | TakeoffSegment | LandSegment):
            s, ds, dds = min_jerk(t / self.duration)
            ds, dds = ds / self.duration, dds / (self.duration * self.duration)
            d = (self.p1[0] - p0[0], self.p1[1] - p0[1], self.p1[2] - p0[2])
            dy = self.yaw1 - self.yaw0
            return ((p0[0] + s * d[0], p0[1] + s * d[1], p0[2] + s * d[2]),
                    (ds * d[0], ds * d[1], ds * d[2]), (dds * d[0], dds * d[1], dds * d[2]),
                    _yaw_q(self.yaw0 + s * dy), (0.0, 0.0, ds * dy))
        if isinstance(seg, SineSegment | AttitudeSineSegment):
            om = 2.0 * math.pi * seg.frequency_hz
            e, de, dde = envelope(t, self.duration, seg.fade_in_s, seg.fade_out_s)
            sn, cs = math.sin(om * t), math.cos(om * t)
            x = e * sn
            dx = de * sn + e * om * cs
            ddx = dde * sn + 2.0 * de * om * cs - e * om * om * sn
            i = _AXES[seg.axis]
            if isinstance(seg, SineSegment):
                amp = seg.amplitude_m
                pl, vl, al = list(p0), [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]
                pl[i] += amp * x
                vl[i] = amp * dx
                al[i] = amp * ddx
                return ((pl[0], pl[1], pl[2]), (vl[0], vl[1], vl[2]), (al[0], al[1], al[2]),
                        _yaw_q(self.yaw0), ZERO3)
            amp = math.radians(seg.amplitude_deg)
            q = quat_mul(_yaw_q(self.yaw0), quat_from_axis_angle(_UNIT[i], amp * x))
            wl = [0.0, 0.0, 0.0]
            wl[i] = amp * dx
            return p0, ZERO3, ZERO3, q, (wl[0], wl[1], wl[2])
        return p0, ZERO3, ZERO3, _yaw_q(self.yaw0), ZERO3

    def eval(self, t: float) -> tuple[Vec3, Vec3, Vec3, Quat, Vec3]:
        """p, v, a (world), q_wr and the body angular velocity at segment time ``t``."""
        p, v, a, q, w = self._base(t)
        blk = self.seg.attitude
        if blk is None:
            return p, v, a, q, w
        # R_r = R_base R_off(e angles) R_sine: body rates compose as R_child^T w_parent + w_child
        if blk.roll_deg or blk.pitch_deg or blk.yaw_deg:
            b = blk.blend_s
            e, de, _ = envelope(t, self.duration, b, b) if b > 0.0 else (1.0, 0.0, 0.0)
            r0, p0_, y0 = (math.radians(blk.roll_deg), math.radians(blk.pitch_deg),
                           math.radians(blk.yaw_deg))
            q_off = quat_from_euler_zyx(e * r0, e * p0_, e * y0)
            w_off = _zyx_body_rate(e * r0, e * p0_, de * r0, de * p0_, de * y0)
            w = _rot_t(q_off, w)
            w = (w[0] + w_off[0], w[1] + w_off[1], w[2] + w_off[2])
            q = quat_mul(q, q_off)
        sine = blk.sine
        if sine is not None:
            om = 2.0 * math.pi * sine.frequency_hz
            e, de, _ = envelope(t, self.duration, sine.fade_in_s, sine.fade_out_s)
            amp = math.radians(sine.amplitude_deg)
            th = amp * e * math.sin(om * t)
            dth = amp * (de * math.sin(om * t) + e * om * math.cos(om * t))
            axis = _UNIT[_AXES[sine.axis]]
            q_s = quat_from_axis_angle(axis, th)
            w = _rot_t(q_s, w)
            w = (w[0] + dth * axis[0], w[1] + dth * axis[1], w[2] + dth * axis[2])
            q = quat_mul(q, q_s)
        return p, v, a, q, w

    def alpha_rad(self, t: float) -> float | None:
        if self.table is not None and self.seg.alpha is None and self.table.alpha_deg:
            return self.table.alpha_rad(t)
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


def _vec(values: Iterable[float]) -> Vec3:
    x, y, z = values
    return (x, y, z)


def _fmt(v: Vec3) -> str:
    return "(" + ", ".join(f"{c:.3g}" for c in v) + ")"


class Mission:
    """A compiled mission: ``reference(t)`` at any time (held at the final pose afterwards)."""

    def __init__(self, spec_: MissionSpec) -> None:
        self.spec = spec_
        self.name = spec_.name
        p, yaw = spec_.start_pos_w_m, math.radians(spec_.start_yaw_deg)
        t = 0.0
        prev_alpha: AlphaProfile = AlphaConstant(kind="constant", value_deg=0.0)
        self._segments: list[_Compiled] = []
        for i, seg in enumerate(spec_.segments):
            alpha = seg.alpha
            if alpha is None:
                if isinstance(prev_alpha, AlphaAuto):
                    alpha = prev_alpha
                else:
                    last = self._segments[-1].alpha_rad(self._segments[-1].duration) \
                        if self._segments else 0.0
                    alpha = AlphaConstant(kind="constant", value_deg=math.degrees(last or 0.0))
            c = _Compiled(seg, t, p, yaw, spec_.start_pos_w_m[2], alpha, f"segments[{i}]")
            if c.table is not None and seg.alpha is None and c.table.alpha_deg:
                # the file's alpha column drives the tilt; what follows inherits its last value
                alpha = AlphaConstant(kind="constant", value_deg=c.table.alpha_deg[-1])
            self._segments.append(c)
            t += c.duration
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

    def segment_kind(self, index: int) -> str:
        return self._segments[index].seg.kind

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
        p, v, a, q, w = c.eval(tl)
        return Reference(t_s, p, v, a, q, w, c.alpha_rad(tl), i, c.seg.measured)

    def lateral_demand_n(self, t_s: float, horizon_s: float, mass_kg: float,
                         gravity_m_s2: float, step_s: float = 0.1) -> float:
        """Largest lateral body-frame force ``|(R_r^T m (a_r + g e3))_xy|`` (N) the reference
        needs over ``[t_s, t_s + horizon_s]``, sampled every ``step_s``."""
        worst = 0.0
        n = max(1, int(horizon_s / step_s) + 1)
        for k in range(n):
            worst = max(worst, lateral_force_n(self.reference(t_s + k * step_s), mass_kg,
                                               gravity_m_s2))
        return worst


def lateral_force_n(ref: Reference, mass_kg: float, gravity_m_s2: float) -> float:
    """``|(R_r^T m (a_r + g e3))_xy|`` (N): the lateral body force the reference needs to hold
    its attitude while following its acceleration."""
    r = quat_to_rot(ref.q_wr)
    fx, fy = mass_kg * ref.acc_w_m_s2[0], mass_kg * ref.acc_w_m_s2[1]
    fz = mass_kg * (ref.acc_w_m_s2[2] + gravity_m_s2)
    bx = r[0] * fx + r[3] * fy + r[6] * fz
    by = r[1] * fx + r[4] * fy + r[7] * fz
    return math.sqrt(bx * bx + by * by)

"""Pre-flight check of a mission against the vehicle: where does the reference need more lateral
force than the planned tilt gives?

The lateral body force a reference needs is ``|(R_r^T m (a_r + g e3))_xy|``
(:func:`controller.missions.lateral_force_n`): the horizontal acceleration, and the weight seen
sideways when R_r is not level. The controller can produce at most its bound ``r_xy(alpha)``
(:class:`controller.model.LateralBound`, the fitted inscribed radius times the conservative
scale, zero inside the dead zone) at the tilt it flies; beyond that, position priority tilts R_d
away from R_r (paper Sec. IV-C). The tilt is planned as in flight: the mission's alpha profile
through the :class:`~controller.tilt_planner.TiltPlanner` (rate limit, range, ``auto`` with its
look-ahead), sampled every ``step_s``; the servo's lag behind the command is not modelled.

The result lists the spans where demand exceeds the bound, merged per segment, each with its
peak; spans in segments marked ``accept_lateral_shortfall`` are flagged ``accepted``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from controller.missions import Mission, lateral_force_n
from controller.model import LateralBound, VehicleModel
from controller.params import VehicleParams
from controller.tilt_planner import TiltPlanner

#: sampling step of the check (s): 20 ms resolves the 0.1 s auto updates and any sane motion
CHECK_STEP_S = 0.02
#: demand above the bound by less than this (N) is not reported (float noise, 0 vs 0 at hover)
TOLERANCE_N = 0.01
#: spans of one segment closer than this (s) are reported as one (the peaks of one sine)
MERGE_GAP_S = 1.0


@dataclass(frozen=True)
class LateralShortfall:
    """One span (mission time, s) where the reference needs more lateral force than the
    controller's bound at the planned tilt."""

    start_s: float
    end_s: float
    segment: int
    kind: str
    peak_demand_n: float
    bound_at_peak_n: float
    alpha_at_peak_deg: float
    accepted: bool

    def describe(self) -> str:
        return (f"{self.start_s:.2f}-{self.end_s:.2f} s (segment {self.segment}, {self.kind}): "
                f"needs up to {self.peak_demand_n:.2f} N lateral force, the bound at the planned "
                f"alpha = {self.alpha_at_peak_deg:.1f} deg is {self.bound_at_peak_n:.2f} N")


def lateral_force_shortfalls(mission: Mission, params: VehicleParams, *,
                             model: VehicleModel | None = None,
                             tilt_override_rad: float | None = None,
                             step_s: float = CHECK_STEP_S) -> list[LateralShortfall]:
    """The spans where ``lateral demand > r_xy(planned alpha) + TOLERANCE_N``."""
    from controller.pipeline import AUTO_UPDATE_PERIOD_S

    bound = LateralBound.for_model(model if model is not None else VehicleModel(params))
    planner = TiltPlanner(params, capability=bound)
    out: list[LateralShortfall] = []
    open_: dict[str, float] | None = None
    seg_open = -1
    next_auto = 0.0
    n = math.floor(mission.duration_s / step_s) + 1

    def close(end_s: float) -> None:
        assert open_ is not None
        spec_seg = mission.spec.segments[seg_open]
        out.append(LateralShortfall(open_["t0"], end_s, seg_open, spec_seg.kind,
                                    open_["peak"], open_["bound"], open_["alpha"],
                                    spec_seg.accept_lateral_shortfall))

    for k in range(n):
        t = k * step_s
        ref = mission.reference(t)
        alpha_ref = ref.alpha_rad if tilt_override_rad is None else tilt_override_rad
        demand_ahead, margin = None, 0.0
        if alpha_ref is None:
            auto = mission.auto_profile(t)
            margin = auto.margin_n if auto is not None else 0.0
            if t >= next_auto:
                next_auto = t + AUTO_UPDATE_PERIOD_S
                demand_ahead = mission.lateral_demand_n(
                    t, auto.horizon_s if auto is not None else 0.0, params.mass_kg,
                    params.gravity_m_s2)
        alpha = planner.step(t, alpha_ref, demand_ahead, margin)
        demand = lateral_force_n(ref, params.mass_kg, params.gravity_m_s2)
        available = bound.radius_n(alpha)
        short = demand > available + TOLERANCE_N
        if open_ is not None and (not short or ref.segment != seg_open):
            close(t)
            open_ = None
        if short:
            if open_ is None:
                open_, seg_open = {"t0": t, "peak": -1.0, "bound": 0.0, "alpha": 0.0}, \
                    ref.segment
            if demand > open_["peak"]:
                open_.update(peak=demand, bound=available, alpha=math.degrees(alpha))
    if open_ is not None:
        close(mission.duration_s)
    return _merged(out)


def _merged(spans: list[LateralShortfall]) -> list[LateralShortfall]:
    out: list[LateralShortfall] = []
    for s in spans:
        prev = out[-1] if out else None
        if prev is not None and prev.segment == s.segment and s.start_s - prev.end_s < MERGE_GAP_S:
            peak = s if s.peak_demand_n > prev.peak_demand_n else prev
            out[-1] = LateralShortfall(prev.start_s, s.end_s, s.segment, s.kind,
                                       peak.peak_demand_n, peak.bound_at_peak_n,
                                       peak.alpha_at_peak_deg, s.accepted)
        else:
            out.append(s)
    return out


def shortfall_warnings(shortfalls: list[LateralShortfall], mission_name: str) -> list[str]:
    """Warning lines for the spans not accepted by the mission (empty: nothing to say)."""
    bad = [s for s in shortfalls if not s.accepted]
    if not bad:
        return []
    return [f"warning: mission {mission_name!r} needs more lateral force than the planned tilt "
            "gives; R_d will leave R_r (position keeps priority) during:"] + \
        [f"  {s.describe()}" for s in bad]

"""One in-process simulated flight and its summary: what ``fasthex simulate`` prints and what a
campaign (``fasthex sweep``, ``fasthex tune``) records per run.

:func:`simulate_flight` flies a mission with :func:`sim_backend.closed_loop.fly_mission` and
returns one flat dictionary whose keys carry their units (listed in
:mod:`groundstation.commands.simulate`), plus, when the scenario schedules disturbances, the
recovery metrics of each (:func:`groundstation.metrics.disturbance_metrics`).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Literal

from controller.missions import Mission
from controller.params import VehicleParams
from sim_backend.closed_loop import CrashLimits
from sim_backend.disturbances import DisturbancePreset
from sim_backend.scenario import Scenario

Estimator = Literal["truth", "ukf"]
#: the rest on the ground before the UKF's mission clock starts (its initialisation)
UKF_PREROLL_S = 1.0


def simulate_flight(params: VehicleParams, mission: Mission, preset: DisturbancePreset, *,
                    seed: int = 0, scenario: Scenario | None = None,
                    estimator: Estimator = "truth", duration_s: float | None = None,
                    tilt_override_rad: float | None = None,
                    crash_limits: CrashLimits | None = None,
                    log_path: str | Path | None = None) -> dict[str, Any]:
    """Fly ``mission`` once; the summary dictionary (verdict, crash, metrics per phase)."""
    from groundstation.metrics import disturbance_metrics, flight_metrics
    from groundstation.record import RecordWriter
    from sim_backend.closed_loop import StateSource, UkfStateSource, fly_mission

    source: StateSource | None = None
    preroll_s = 0.0
    if estimator == "ukf":
        source, preroll_s = UkfStateSource(params.mass_kg, params.gravity_m_s2), UKF_PREROLL_S
    writer = RecordWriter(None if log_path is None else str(log_path),
                          {"mission": mission.name, "vehicle": params.name,
                           "preset": preset.name, "seed": seed, "estimator": estimator,
                           "scenario": None if scenario is None else scenario.name})
    try:
        result = fly_mission(params, mission, preset, seed=seed, sink=writer,
                             duration_s=duration_s, tilt_override_rad=tilt_override_rad,
                             state_source=source, preroll_s=preroll_s,
                             crash_limits=crash_limits, scenario=scenario)
    finally:
        record = writer.close()
    out: dict[str, Any] = {
        "mission": mission.name, "vehicle": params.name, "preset": preset.name,
        "scenario": None if scenario is None else scenario.name, "seed": seed,
        "estimator": estimator, "sim_time_s": result.sim_time_s,
        "wall_time_s": result.wall_time_s, "sim_s_per_wall_s": result.realtime_factor,
        "touchdowns": len(result.touchdown_speeds_m_s),
        "max_touchdown_speed_m_s": max(result.touchdown_speeds_m_s, default=0.0),
        "verdict": "ok" if result.crash is None else "crash",
        "crash_reason": None if result.crash is None else result.crash.reason,
        "crash_kind": None if result.crash is None else result.crash.kind,
        "crash_t_s": None if result.crash is None else result.crash.t_s,
    }
    out.update(flight_metrics(record.rows, min_spin_hz=params.rotors.min_spin_hz,
                              max_spin_hz=params.rotors.max_spin_hz))
    if scenario is not None and scenario.disturbances:
        # a step is judged while it pushes (its removal is a disturbance of its own); a pulse,
        # gust or ramp until the next event, as the recovery follows its end
        out.update(disturbance_metrics(record.rows, [
            (e.start_s, e.end_s if e.kind == "step" else math.inf)
            for e in scenario.disturbances]))
    return out

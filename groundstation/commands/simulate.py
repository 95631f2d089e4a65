"""``fasthex simulate``: fly a mission in the in-process simulator, faster than real time.

The controller is fed the simulator's true state plus the preset's estimation noise, or with
``--estimator ukf`` the project's UKF fed with the simulated IMU and MoCap (the seam:
``sim_backend.closed_loop.StateSource``). Prints a summary table per phase (or, with
``--json``, one JSON object whose keys carry their units: ``_mm``, ``_deg``, ``_hz``, ``_s``,
``_frac``) and optionally writes the flight record (``--log``, format in
:mod:`groundstation.record`).

The flight ends 0.5 s after the mission (the motors are off from its end); ``--duration``
only shortens it.

``--scenario NAME|FILE`` flies a scenario (:mod:`sim_backend.scenario`): the simulator's plant
overrides, scheduled disturbances and faults, timed in mission seconds; the same file an emulated
session names in ``backend.scenario``.

JSON keys: ``mission``, ``vehicle``, ``preset``, ``scenario`` (``null``: none), ``seed``,
``estimator``, ``sim_time_s``,
``wall_time_s``, ``sim_s_per_wall_s`` (simulated seconds per wall second), ``touchdowns``,
``max_touchdown_speed_m_s``, and for each phase ``all`` / ``udt`` / ``mdt``:
``<phase>_ticks``, ``<phase>_duration_s``, ``<phase>_pos_err_mean_mm``,
``<phase>_pos_err_max_mm``, ``<phase>_{roll,pitch,yaw}_err_mean_deg``,
``<phase>_rd_dev_mean_deg``, ``<phase>_rd_dev_max_deg``, ``<phase>_inner_err_mean_deg``,
``<phase>_spin_min_hz``, ``<phase>_spin_max_hz``, ``<phase>_spin_saturated_frac``,
``<phase>_internal_force_loss_mean_frac`` (1 - eta_f); ``all_spin_within_limits`` (1 or 0).
With a scenario that schedules disturbances, for each (``i`` its place in the file)
``dist<i>_peak_err_mm``, ``dist<i>_recovery_s`` (back under 10 mm; ``null`` when it never came
back) and ``dist<i>_recovered`` (1 or 0), as :func:`groundstation.metrics.disturbance_metrics`.
Counts (``*_ticks``, ``touchdowns``) and ``sim_s_per_wall_s`` carry their unit in the name.
Phases as in :mod:`groundstation.metrics`.

Before flying, the pre-flight lateral-force check (:mod:`controller.preflight`) prints a
warning on stderr listing the time spans where the mission needs more lateral force than the
planned tilt gives.

Verdict: ``verdict`` is ``"ok"`` or ``"crash"``, with ``crash_reason`` (text, ``null`` when ok),
``crash_kind`` (``impact``, ``workspace``, ``non-finite``) and ``crash_t_s``. A crash is a
touchdown faster than ``--max-touchdown-speed`` (default
:data:`sim_backend.closed_loop.SAFE_TOUCHDOWN_SPEED_M_S`, 1.0 m/s, derived there), the vehicle
outside the workspace box (default: a session's default geofence), or a non-finite true state or
estimate; the flight ends at the crash and the command exits 1 with the reason on stderr.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from sim_backend.closed_loop import CrashLimits

NAME = "simulate"
HELP = "fly a mission in the in-process simulator and print tracking metrics"

DEFAULT_MISSION = "exp1-hover-tilt-steps"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("mission", nargs="?", default=DEFAULT_MISSION,
                        help=f"mission name or YAML file (default {DEFAULT_MISSION})")
    parser.add_argument("--vehicle", default="fasthex", help="vehicle name or YAML file")
    from groundstation.cli import seed_arg

    parser.add_argument("--seed", type=seed_arg, default=0,
                        help="random seed, 0 .. 2^32-1 (default 0)")
    parser.add_argument("--preset", default="paper-calibrated",
                        help="disturbance preset name or YAML file (ideal, paper-calibrated)")
    parser.add_argument("--scenario", default=None, metavar="NAME|FILE",
                        help="scenario: plant overrides, scheduled disturbances and faults "
                        "(times in mission seconds)")
    parser.add_argument("--duration", type=float, default=None, metavar="S",
                        help="stop after S simulated seconds; only shortens the flight "
                        "(default and longest: the whole mission and 0.5 s after it, the "
                        "motors off)")
    parser.add_argument("--tilt-deg", type=float, default=None, metavar="DEG",
                        help="fly at this constant tilt instead of the mission's alpha profile")
    parser.add_argument("--estimator", choices=("truth", "ukf"), default="truth",
                        help="what the controller acts on: the true state plus the preset's "
                        "estimation noise (default), or the UKF fed with the simulated IMU and "
                        "MoCap (after a 1 s rest on the ground to initialise)")
    parser.add_argument("--max-touchdown-speed", type=float, default=None, metavar="M_S",
                        help="fastest safe vertical speed at ground contact (default 1.0 m/s); "
                        "faster is a crash")
    parser.add_argument("--workspace", type=float, nargs=6, default=None,
                        metavar=("XMIN", "YMIN", "ZMIN", "XMAX", "YMAX", "ZMAX"),
                        help="workspace box in m, world frame (default: the session default "
                        "geofence); leaving it is a crash")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--log", default=None, metavar="FILE",
                        help="write the flight record (missing folders created, as fly does)")


def simulate(args: argparse.Namespace) -> dict[str, Any]:
    """Run the flight described by ``args``; return the summary dictionary."""
    from controller.missions import Mission
    from groundstation.cli import UserError
    from groundstation.configs import (
        load_disturbances,
        load_mission,
        load_scenario,
        load_vehicle,
        preflight_warnings,
    )
    from groundstation.simulation import simulate_flight

    params = load_vehicle(args.vehicle)
    lines: dict[str, int] = {}
    spec = load_mission(args.mission, vehicle=params, lines=lines)  # checked against it
    mission = Mission(spec)
    preset = load_disturbances(args.preset)
    scenario = None
    if getattr(args, "scenario", None):
        scenario = load_scenario(args.scenario, vehicle=params,
                                 mission_duration_s=mission.duration_s)
    if args.duration is not None and not args.duration > 0.0:
        raise UserError(f"--duration must be positive, got {args.duration}")
    limits = _crash_limits(args)
    if limits.workspace_min_w_m is not None and limits.workspace_max_w_m is not None:
        # as fly checks it against the geofence: a reference that leaves the box is a plan's
        # error, not a crash to fly into
        from config import find_config
        from groundstation.session_config import check_mission_in_box

        box = ("the --workspace box" if args.workspace is not None
               else "the default workspace (a session's default geofence)")
        check_mission_in_box(spec, limits.workspace_min_w_m, limits.workspace_max_w_m, box,
                             str(find_config("missions", args.mission)), lines)
    tilt = None if args.tilt_deg is None else math.radians(args.tilt_deg)
    lo_deg, hi_deg = params.tilt.min_tilt_deg, params.tilt.max_tilt_deg
    if args.tilt_deg is not None and not lo_deg <= args.tilt_deg <= hi_deg:
        raise UserError(f"--tilt-deg {args.tilt_deg:g}: outside the tilt range of vehicle "
                        f"{params.name!r} ({lo_deg:g} .. {hi_deg:g} deg)")
    for line in preflight_warnings(mission, params, tilt_override_rad=tilt):
        print(line, file=sys.stderr)
    if args.log:
        _check_log(Path(args.log))
    return simulate_flight(params, mission, preset, seed=args.seed, scenario=scenario,
                           estimator=args.estimator, duration_s=args.duration,
                           tilt_override_rad=tilt, crash_limits=limits, log_path=args.log)


def _check_log(log: Path) -> None:
    """Create the record's folder as ``fly`` does and the file itself: a bad path fails before
    the flight, not after it."""
    from groundstation.cli import UserError
    from groundstation.commands.fly import make_record_folder

    make_record_folder(log)
    try:
        log.open("wb").close()
    except OSError as exc:
        raise UserError(f"--log {log}: cannot write the flight record ({exc.strerror}); "
                        "expected a file path") from None


def _crash_limits(args: argparse.Namespace) -> CrashLimits:
    from groundstation.cli import UserError
    from groundstation.session_config import SafetyConfig
    from sim_backend.closed_loop import SAFE_TOUCHDOWN_SPEED_M_S, CrashLimits

    speed = (SAFE_TOUCHDOWN_SPEED_M_S if args.max_touchdown_speed is None
             else args.max_touchdown_speed)
    if not (math.isfinite(speed) and speed > 0.0):
        raise UserError(f"--max-touchdown-speed must be a positive speed in m/s, got {speed}")
    if args.workspace is None:
        safety = SafetyConfig()
        lo, hi = safety.geofence_min_m, safety.geofence_max_m
    else:
        w = [float(v) for v in args.workspace]
        lo, hi = (w[0], w[1], w[2]), (w[3], w[4], w[5])
        if not all(math.isfinite(a) and math.isfinite(b) and a < b
                   for a, b in zip(lo, hi, strict=True)):
            raise UserError("--workspace needs XMIN YMIN ZMIN XMAX YMAX ZMAX with each minimum "
                             f"below its maximum, got {' '.join(f'{v:g}' for v in args.workspace)}")
    return CrashLimits(max_touchdown_speed_m_s=speed, workspace_min_w_m=lo, workspace_max_w_m=hi)


_ROWS = (
    ("ticks", "ticks", "{:.0f}"),
    ("duration", "duration_s", "{:.1f}"),
    ("mean |e_p| [mm]", "pos_err_mean_mm", "{:.2f}"),
    ("max |e_p| [mm]", "pos_err_max_mm", "{:.2f}"),
    ("mean |e_roll| [deg]", "roll_err_mean_deg", "{:.3f}"),
    ("mean |e_pitch| [deg]", "pitch_err_mean_deg", "{:.3f}"),
    ("mean |e_yaw| [deg]", "yaw_err_mean_deg", "{:.3f}"),
    ("mean angle(R_r,R_d) [deg]", "rd_dev_mean_deg", "{:.3f}"),
    ("mean angle(R_d,R_B) [deg]", "inner_err_mean_deg", "{:.3f}"),
    ("spin min [Hz]", "spin_min_hz", "{:.1f}"),
    ("spin max [Hz]", "spin_max_hz", "{:.1f}"),
    ("saturated ticks [%]", "spin_saturated_frac", "{:.2%}"),
    ("internal-force loss [%]", "internal_force_loss_mean_frac", "{:.2%}"),
)


def format_table(summary: dict[str, Any]) -> str:
    scenario = summary.get("scenario")
    lines = [f"{summary['mission']} on {summary['vehicle']}, preset {summary['preset']}, "
             + (f"scenario {scenario}, " if scenario else "")
             + f"seed {summary['seed']}, state from {summary['estimator']}",
             f"{'':28s}{'all':>12s}{'UDT':>12s}{'MDT':>12s}"]
    for label, key, fmt in _ROWS:
        cells = []
        for phase in ("all", "udt", "mdt"):
            v = summary.get(f"{phase}_{key}", math.nan)
            cells.append("-" if isinstance(v, float) and math.isnan(v) else fmt.format(v))
        lines.append(f"{label:28s}" + "".join(f"{c:>12s}" for c in cells))
    lines.append(f"touchdowns: {summary['touchdowns']} (fastest "
                 f"{summary['max_touchdown_speed_m_s']:.2f} m/s)")
    lines.append("verdict: " + ("ok" if summary["verdict"] == "ok"
                                else f"CRASH: {summary['crash_reason']}"))
    lines.append(f"simulated {summary['sim_time_s']:.1f} s in {summary['wall_time_s']:.1f} s "
                 f"wall: {summary['sim_s_per_wall_s']:.1f}x real time")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    summary = simulate(args)
    if args.json:
        from groundstation.metrics import rounded

        # rounded to each unit's resolution, as fly --json and report's metrics.json
        json.dump({k: rounded(k, v) for k, v in summary.items()}, sys.stdout)
        sys.stdout.write("\n")
    else:
        print(format_table(summary))
        if args.log:
            print(f"flight record: {args.log}")
    if summary["verdict"] != "ok":
        print(f"fasthex: simulate: CRASH: {summary['crash_reason']}", file=sys.stderr)
        return 1
    return 0

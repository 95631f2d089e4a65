"""The end-of-flight summary of ``fasthex fly`` as an operator reads it.

:func:`summary_text` turns the summary dictionary (the same one ``--json`` prints, see
``groundstation.commands.fly.flight_summary``) into short titled sections: the outcome, the
paper's tracking metrics per actuation phase in one table with units, the loop's timing, and
where the files are with the commands that open them. :func:`json_ready` rounds the same
dictionary for ``--json``: counts as integers, measurements to their resolution.
"""

from __future__ import annotations

import math
import re
import textwrap
from typing import Any

from groundstation.console import PLACEHOLDER
from groundstation.metrics import MDT_MIN_DEG, PHASES, SETTLE_S, UDT_MAX_DEG, rounded

#: the phases of groundstation.metrics as column titles (two lines each)
PHASE_TITLES = {"all": ("whole mission", "measured part"),
                "udt": ("UDT", f"tilt < {UDT_MAX_DEG:g} deg"),
                "mdt": ("MDT", f"tilt > {MDT_MIN_DEG:g} deg")}

#: metric rows: (label, unit shown, key without the phase prefix, scale, format)
METRIC_ROWS: tuple[tuple[str, str, str, float, str], ...] = (
    ("time scored", "s", "duration_s", 1.0, ".1f"),
    ("position error, mean", "mm", "pos_err_mean_mm", 1.0, ".2f"),
    ("position error, max", "mm", "pos_err_max_mm", 1.0, ".2f"),
    ("roll error, mean", "deg", "roll_err_mean_deg", 1.0, ".3f"),
    ("pitch error, mean", "deg", "pitch_err_mean_deg", 1.0, ".3f"),
    ("yaw error, mean", "deg", "yaw_err_mean_deg", 1.0, ".3f"),
    ("R_d off reference, mean *", "deg", "rd_dev_mean_deg", 1.0, ".3f"),
    ("R_d off reference, max *", "deg", "rd_dev_max_deg", 1.0, ".3f"),
    ("attitude loop error, mean **", "deg", "inner_err_mean_deg", 1.0, ".3f"),
    ("rotor spin, min", "Hz", "spin_min_hz", 1.0, ".1f"),
    ("rotor spin, max", "Hz", "spin_max_hz", 1.0, ".1f"),
    ("rotors saturated", "% ticks", "spin_saturated_frac", 100.0, ".2f"),
    ("force loss, mean ***", "%", "internal_force_loss_mean_frac", 100.0, ".1f"),
)

NOTES = (
    f"UDT: under-actuated (tilt < {UDT_MAX_DEG:g} deg); MDT: multi-directional thrust (tilt > "
    f"{MDT_MIN_DEG:g} deg). Both skip {SETTLE_S:g} s after entering the phase and after each "
    "tilt step; the whole mission is its measured part (take-off and landing excluded).",
    "*   R_d off reference: how far the controller tilts its desired attitude R_d from "
    "the reference to keep the position (the under-actuated trade-off; 0 when fully "
    "actuated).",
    "**  attitude loop error: actual attitude against R_d (the inner loop's tracking).",
    "*** force loss: 1 - eta_f, the internal force (thrust that cancels between tilted "
    "propellers).",
)


def json_ready(summary: dict[str, Any]) -> dict[str, Any]:
    """The summary for ``--json``: the same keys and values, rounded (see
    :func:`groundstation.metrics.rounded`)."""
    return {k: rounded(k, v) for k, v in summary.items()}


def _cell(value: Any, scale: float, fmt: str) -> str:
    if not isinstance(value, (int, float)) or not math.isfinite(value):
        return PLACEHOLDER
    return f"{value * scale:{fmt}}"


def metrics_table(summary: dict[str, Any]) -> list[str]:
    """The paper's metrics, one row per quantity (with its unit), one column per phase."""
    if "all_ticks" not in summary:
        return []
    label_w, unit_w, col_w = 29, 8, 14  # 79 columns: an 80-column terminal does not wrap
    head1 = " " * (label_w + unit_w) + "".join(f"{PHASE_TITLES[p][0]:>{col_w}}" for p in PHASES)
    head2 = " " * (label_w + unit_w) + "".join(f"{PHASE_TITLES[p][1]:>{col_w}}" for p in PHASES)
    lines = [head1, head2]
    for label, unit, key, scale, fmt in METRIC_ROWS:
        cells = "".join(f"{_cell(summary.get(f'{p}_{key}'), scale, fmt):>{col_w}}"
                        for p in PHASES)
        lines.append(f"{label:<{label_w}}{unit:<{unit_w}}{cells}")
    within = summary.get("all_spin_within_limits")
    if within is not None and not summary.get("all_ticks"):  # no tick to be within them
        lines.append("rotor spin limits: not scored (no measured tick)")
    elif within is not None:
        lines.append("rotor spin limits: " + ("respected on every tick" if within else
                                              "EXCEEDED (see the spin panel of the report)"))
    return lines


def _section(title: str) -> list[str]:
    return ["", title, "-" * len(title)]


def summary_text(summary: dict[str, Any], *, clock: str = "realtime",
                 rate_hz: float = 500.0, dashboard_mode: str = "off",
                 dashboard_file: str | None = None, extra: list[str] | None = None) -> str:
    """The summary as titled sections of plain text (see the module doc)."""
    s = summary
    record = s["record"]
    ticks, flight_s, wall_s = int(s["ticks"]), float(s["flight_time_s"]), float(s["wall_time_s"])
    speed = f", {flight_s / wall_s:.1f}x real time" if wall_s > 0 and clock == "lockstep" else ""
    title = f"Flight summary: {s['session']}"
    lines = [title, "=" * len(title)]
    lines.append(f"session ended: {s['end_reason']}")
    if "truth_touchdowns" in s:  # the emulated vehicle's truth
        n, fastest = int(s["truth_touchdowns"]), float(s["truth_touchdown_max_m_s"])
        where = "on the ground" if s["truth_landed"] else f"{s['truth_height_m']:.2f} m up"
        told = (f"{n} touchdown{'s' if n != 1 else ''}, the fastest at {fastest:.2f} m/s"
                if n else "no touchdown")
        lines.append(f"truth:         {told}; {where} at the end (the emulated vehicle)")
        if s.get("truth_crash"):
            lines.append(f"CRASH:         {s['truth_crash']}")
    lines.append(f"flown:         {flight_s:.1f} s of flight in {wall_s:.1f} s wall{speed}")
    # the ticks are the whole session's (preflight and arming too), not the flight's
    lines.append(f"loop:          {ticks} ticks in all ({ticks / rate_hz:.1f} s at "
                 f"{rate_hz:g} Hz, preflight included)")
    failed = [p for p in s.get("preflight", []) if not p["pass"]]
    n_pre = len(s.get("preflight", []))
    if n_pre:
        lines.append(f"preflight:     {n_pre - len(failed)} of {n_pre} checks passed"
                     + "".join(f"; FAILED {p['check']} ({p['value']})" for p in failed))
    faults = s.get("faults", [])
    lines.append(f"faults:        {len(faults) or 'none'}")
    lines += [f"  {f}" for f in faults]
    lines.append(f"estimator:     {s['poses_rejected']} MoCap poses rejected; fusion "
                 f"{s['fusion_delay_ms']:.1f} ms behind the newest IMU sample")
    lost = next((f for f in faults if "flight record lost" in f), None)
    if lost is not None:  # the ring's count says nothing once its reader is gone
        lines.append(f"telemetry:     record lost at {lost.split(': ', 1)[0]}: the rows after "
                     "it were not written")
    else:
        lines.append(f"telemetry:     {s['telemetry_dropped']} record rows dropped")
    lines += extra or []

    table = metrics_table(s)
    if table:
        lines += _section(f"Tracking, scored on the {s['state_source']}")
        lines += table
        lines += ["", *(textwrap.fill(n, 79, subsequent_indent="    ") for n in NOTES)]
    elif "state_source" in s:
        lines += ["", f"no metrics: {s['state_source']}"]

    period_ms = 1e3 / rate_hz
    lines += _section(f"Loop timing ({rate_hz:g} Hz, {period_ms:.2f} ms period)")
    lines.append(f"compute per tick:  p50 {s['compute_p50_ms']:.3f} ms, "
                 f"p99 {s['compute_p99_ms']:.3f} ms")
    if s.get("compute_mean_ms"):   # a summary written before the numerics were timed: no line
        lines.append(f"numerics alone:    mean {s['numerics_mean_ms']:.3f} ms of the mean "
                     f"{s['compute_mean_ms']:.3f} ms (UKF, controller)")
    lines.append(f"tick period:       p50 {s['period_p50_ms']:.3f} ms, "
                 f"jitter p99 {s['jitter_p99_ms']:.3f} ms")
    lines.append(f"IMU in -> w out:   p50 {s['latency_p50_ms']:.3f} ms, "
                 f"p99 {s['latency_p99_ms']:.3f} ms")
    misses = int(s["deadline_misses"])
    share = f" ({100 * misses / ticks:.2f} % of ticks)" if ticks else ""
    why = ("; lockstep: the simulated clock waits for the loop, so a late tick is not a fault"
           if clock == "lockstep" else "")
    lines.append(f"deadline misses:   {misses}{share}{why}")
    if s.get("imu_gap_max_ms", 0.0) > 0.0:
        lines.append(f"longest IMU gap:   {s['imu_gap_max_ms']:.1f} ms at "
                     f"{s['imu_gap_max_at_s']:.2f} s ({s['imu_waits_empty']} empty waits)")

    lines += _section("Files")
    lines.append(f"flight record:  {record}")
    lines.append(f"                figure and metrics: fasthex report {record}")
    lines.append(f"events:         {record}.events.txt")
    if dashboard_file:
        lines.append(f"dashboard:      {dashboard_file}")
        lines.append(f"                open it with: rerun {dashboard_file}")
    elif dashboard_mode in ("spawn", "serve"):
        lines.append(f"dashboard:      live viewer ({dashboard_mode}); nothing saved. "
                     f"Again: fasthex replay {record}")
    else:
        why = ("--rerun auto and no display" if dashboard_mode == "auto-headless"
               else "--rerun off")
        lines.append(f"dashboard:      none ({why}). To look at the flight: "
                     f"fasthex replay {record} (viewer), or --rerun save for a .rrd file")
    return "\n".join(_fit(line) for line in lines) + "\n"


_LABEL = re.compile(r"^[\w ().>-]+:\s+")


def _fit(line: str, width: int = 79) -> str:
    """A long ``label:  value`` line wrapped under its value (paths are never split)."""
    if len(line) <= width:
        return line
    m = _LABEL.match(line)
    indent = len(m.group(0)) if m and len(m.group(0)) < 24 else 4
    return textwrap.fill(line, width, subsequent_indent=" " * indent, break_long_words=False,
                         break_on_hyphens=False)

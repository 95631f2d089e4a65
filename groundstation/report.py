"""Static report of a flight record: the paper's "Plots of Experiment 1/2" figure and a metrics
table, for a lab notebook or a paper without a viewer.

The figure stacks eight panels over time, as in the paper's Fig. "Plots of Experiment 2-a/b":

1. actual vs reference position; 2. position tracking error; 3. reference attitude (Euler
angles); 4. desired and actual attitude; 5. attitude tracking error; 6. propeller spin rates with
their limits; 7. maximum (``r_xy``) vs actual (``|u_f xy|``) lateral force; 8. reference, commanded
and actual tilt angle alpha. The background is red while the vehicle is under-actuated
(alpha < :data:`groundstation.metrics.UDT_MAX_DEG`) and green while it is fully actuated.

The metrics are :func:`groundstation.metrics.flight_metrics` of the record, exactly the numbers
``fasthex simulate`` prints, written as ``metrics.json`` (NaN as null, like ``simulate --json``)
and as a markdown table ``metrics.md``.

:func:`panel_signals` derives the plotted signals from the record's rows; the live dashboard
(:mod:`groundstation.dashboard`) plots the same signals. Euler angles are ZYX (roll, pitch, yaw)
in degrees; the attitude error is the signed ZYX angles of ``R_r^T R_B``.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from groundstation.metrics import (
    MDT_MIN_DEG,
    PHASES,
    UDT_MAX_DEG,
    flight_metrics,
    quat_to_rot,
    rounded,
)

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

#: actuation states of the dashboard's state track
UDT, FULL, MDT = 0, 1, 2
FIGURE_NAME = "plots.png"
METRICS_JSON = "metrics.json"
METRICS_MD = "metrics.md"


def euler_zyx_deg(rot: FloatArray) -> FloatArray:
    """Roll, pitch, yaw (ZYX convention, degrees) of rotation matrices (N, 3, 3) -> (N, 3)."""
    roll = np.arctan2(rot[..., 2, 1], rot[..., 2, 2])
    pitch = -np.arcsin(np.clip(rot[..., 2, 0], -1.0, 1.0))
    yaw = np.arctan2(rot[..., 1, 0], rot[..., 0, 0])
    return np.degrees(np.stack([roll, pitch, yaw], -1))


def actuation_state(alpha_deg: FloatArray) -> IntArray:
    """0 = under-actuated (UDT), 1 = fully actuated below MDT, 2 = MDT, per tick."""
    state = np.full(alpha_deg.shape, FULL, dtype=np.int64)
    state[np.abs(alpha_deg) < UDT_MAX_DEG] = UDT
    state[np.abs(alpha_deg) > MDT_MIN_DEG] = MDT
    return state


@dataclass(frozen=True)
class PanelSignals:
    """The plotted signals of a block of record rows (SI units unless the name says)."""

    t_s: FloatArray
    pos_ref_w_m: FloatArray          # (N, 3)
    pos_w_m: FloatArray              # (N, 3)
    pos_err_mm: FloatArray           # (N, 3) actual - reference
    pos_err_norm_mm: FloatArray      # (N,)
    eul_ref_deg: FloatArray          # (N, 3) roll, pitch, yaw of R_r
    eul_des_deg: FloatArray          # of R_d
    eul_deg: FloatArray              # of R_B
    att_err_deg: FloatArray          # (N, 3) of R_r^T R_B
    spin_hz: FloatArray              # (N, 6) measured
    spin_cmd_hz: FloatArray          # (N, 6) commanded
    r_xy_n: FloatArray               # (N,) maximum lateral force
    lat_force_n: FloatArray          # (N,) |u_f xy|, the lateral force applied
    alpha_ref_deg: FloatArray        # NaN while the tilt planner is in auto mode
    alpha_cmd_deg: FloatArray
    alpha_deg: FloatArray
    actuation: IntArray              # UDT / FULL / MDT
    sat_count: IntArray              # rotors clamped this tick
    measured: npt.NDArray[np.bool_]


def panel_signals(rows: np.ndarray) -> PanelSignals:
    """Derive every plotted signal from record rows (vectorised, ~1 us per row)."""
    def f(name: str) -> FloatArray:
        return np.asarray(rows[name], dtype=np.float64)

    pos_ref, pos = f("pos_ref_w_m"), f("pos_w_m")
    err = 1000.0 * (pos - pos_ref)
    r_r, r_d, r_b = quat_to_rot(f("q_wr")), quat_to_rot(f("q_wd")), quat_to_rot(f("q_wb"))
    alpha_deg = np.degrees(f("alpha_rad"))
    sat = np.unpackbits(np.asarray(rows["sat_mask"], dtype=np.uint8)[:, None], axis=1)
    return PanelSignals(
        t_s=f("t_s"), pos_ref_w_m=pos_ref, pos_w_m=pos, pos_err_mm=err,
        pos_err_norm_mm=np.linalg.norm(err, axis=1),
        eul_ref_deg=euler_zyx_deg(r_r), eul_des_deg=euler_zyx_deg(r_d),
        eul_deg=euler_zyx_deg(r_b),
        att_err_deg=euler_zyx_deg(np.swapaxes(r_r, -1, -2) @ r_b),
        spin_hz=f("spin_hz"), spin_cmd_hz=f("spin_cmd_hz"), r_xy_n=f("r_xy_n"),
        lat_force_n=np.linalg.norm(f("u_f_b_n")[:, :2], axis=1),
        alpha_ref_deg=np.degrees(f("alpha_ref_rad")), alpha_cmd_deg=np.degrees(f("alpha_cmd_rad")),
        alpha_deg=alpha_deg, actuation=actuation_state(alpha_deg),
        sat_count=sat.sum(axis=1).astype(np.int64),
        measured=np.asarray(rows["measured"], dtype=bool))


def phase_spans(t_s: FloatArray, state: IntArray) -> list[tuple[float, float, int]]:
    """Maximal runs of equal ``state`` as (t_start, t_end, state); a run ends where the next
    begins, the last at the final tick."""
    if len(t_s) == 0:
        return []
    change = np.flatnonzero(np.diff(state)) + 1
    starts = np.concatenate([[0], change])
    ends = np.concatenate([change, [len(t_s) - 1]])
    return [(float(t_s[a]), float(t_s[b]), int(state[a])) for a, b in zip(starts, ends,
                                                                            strict=True)]


# -- metrics ---------------------------------------------------------------------------------
def record_metrics(rows: np.ndarray, metadata: dict[str, Any]) -> dict[str, float]:
    """:func:`flight_metrics` with the spin limits of the record's vehicle (as ``simulate``)."""
    from groundstation.configs import load_vehicle

    params = load_vehicle(str(metadata.get("vehicle", "fasthex")))
    return flight_metrics(rows, min_spin_hz=params.rotors.min_spin_hz,
                          max_spin_hz=params.rotors.max_spin_hz)


def metrics_json(metrics: dict[str, float]) -> dict[str, object]:
    """As ``fasthex simulate --json`` writes them: NaN -> None, counts as integers, values
    rounded to the resolution of their unit (:func:`groundstation.metrics.rounded`)."""
    return {k: rounded(k, v) for k, v in metrics.items()}


def _fmt(v: float) -> str:
    if math.isnan(v):
        return "-"
    if float(v).is_integer() and abs(v) >= 1:
        return f"{v:.0f}"
    return f"{v:.4g}"


def metrics_markdown(metrics: dict[str, float], title: str = "") -> str:
    """A markdown table: one row per quantity (unit in its name), one column per phase."""
    quantities = [k[len("all_"):] for k in metrics if k.startswith("all_")
                  and all(f"{p}_{k[len('all_'):]}" in metrics for p in PHASES)]
    lines = [f"## {title}", ""] if title else []
    lines += ["| quantity | all | UDT | MDT |", "|---|---:|---:|---:|"]
    for q in quantities:
        cells = " | ".join(_fmt(metrics[f"{p}_{q}"]) for p in PHASES)
        lines.append(f"| {q} | {cells} |")
    extra = [k for k in metrics if not any(k == f"{p}_{q}" for p in PHASES for q in quantities)]
    if extra:
        lines += ["", "| flight | value |", "|---|---:|"]
        lines += [f"| {k} | {_fmt(metrics[k])} |" for k in extra]
    return "\n".join(lines) + "\n"


# -- figure ----------------------------------------------------------------------------------
_AXIS_COLORS = ("tab:red", "tab:green", "tab:blue")
_SHADE = {UDT: ("#d62728", 0.12), FULL: ("#2ca02c", 0.10), MDT: ("#2ca02c", 0.10)}
#: room around the measured range of a panel whose limits it sets
_MARGIN = 0.15


def measured_limits(data: FloatArray, measured: npt.NDArray[np.bool_]
                    ) -> tuple[float, float] | None:
    """y-limits that show every sample of the measured part of the flight with a margin, or
    None when nothing was measured. The take-off and landing transients (a reference that
    starts from the ground, a touchdown) would otherwise set the scale and flatten the
    millimetre errors the panel is about."""
    rows = np.asarray(data, dtype=np.float64).reshape(len(measured), -1)[measured]
    finite = rows[np.isfinite(rows)]
    if finite.size == 0:
        return None
    lo, hi = float(finite.min()), float(finite.max())
    span = max(hi - lo, 1e-6)
    return lo - _MARGIN * span, hi + _MARGIN * span


def _limit_to_measured(ax: Any, t: FloatArray, data: FloatArray,
                       measured: npt.NDArray[np.bool_], unit: str) -> None:
    """Set the panel's y-limits by the measured part and annotate the largest excursion
    outside them (value and time), rather than let it set the scale. An excursion within half
    the measured span is simply shown (the limits grow to hold it)."""
    limits = measured_limits(data, measured)
    if limits is None:
        return
    lo, hi = limits
    values = np.asarray(data, dtype=np.float64).reshape(len(t), -1)
    finite = values[np.isfinite(values)]
    span = hi - lo
    if finite.size and finite.min() >= lo - 0.5 * span and finite.max() <= hi + 0.5 * span:
        ax.set_ylim(min(lo, float(finite.min())), max(hi, float(finite.max())))
        return
    ax.set_ylim(lo, hi)
    outside = np.where(np.isfinite(values), np.maximum(values - hi, lo - values), 0.0)
    worst = np.unravel_index(int(np.argmax(outside)), outside.shape)
    value, t_at = float(values[worst]), float(t[worst[0]])
    edge = hi if value > hi else lo
    ax.annotate(f"off scale: {value:.3g} {unit} at {t_at:.1f} s (not measured)",
                xy=(t_at, edge), xytext=(8, -12 if value > hi else 12),
                textcoords="offset points", fontsize=7, va="center",
                arrowprops={"arrowstyle": "->", "lw": 0.6})


def render_figure(rows: np.ndarray, path: str | Path, *, title: str = "",
                  min_spin_hz: float | None = None, max_spin_hz: float | None = None,
                  dpi: int = 110) -> Path:
    """Write the eight-panel figure of ``rows`` to ``path`` (PNG); returns the path."""
    fig = build_figure(rows, title=title, min_spin_hz=min_spin_hz, max_spin_hz=max_spin_hz)
    import matplotlib.pyplot as plt

    out = Path(path)
    fig.savefig(out, dpi=dpi)
    plt.close(fig)
    return out


def build_figure(rows: np.ndarray, *, title: str = "", min_spin_hz: float | None = None,
                 max_spin_hz: float | None = None) -> Any:
    """The eight-panel matplotlib figure of ``rows`` (Agg backend), for saving or checking."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch

    s = panel_signals(rows)
    t = s.t_s
    fig, axes = plt.subplots(8, 1, sharex=True, figsize=(12.0, 17.0), constrained_layout=True)
    xyz = ("x", "y", "z")
    rpy = (r"$\phi$", r"$\theta$", r"$\psi$")

    def lines(ax: Any, data: FloatArray, labels: tuple[str, ...], style: str = "-",
              **kw: Any) -> None:
        for i, lab in enumerate(labels):
            ax.plot(t, data[:, i], style, color=_AXIS_COLORS[i % 3], label=lab, lw=1.0, **kw)

    ax = axes[0]
    lines(ax, s.pos_w_m, tuple(f"$p_{a}$" for a in xyz))
    lines(ax, s.pos_ref_w_m, tuple(f"$p_{{{a},r}}$ (ref.)" for a in xyz), "--")
    ax.set_ylabel("position [m]")
    ax = axes[1]
    lines(ax, s.pos_err_mm, tuple(f"$e_{a}$" for a in xyz))
    ax.plot(t, s.pos_err_norm_mm, color="k", lw=0.8, label=r"$|e_p|$")
    ax.set_ylabel("pos. error [mm]")
    _limit_to_measured(ax, t, np.column_stack([s.pos_err_mm, s.pos_err_norm_mm]), s.measured,
                       "mm")
    lines(axes[2], s.eul_ref_deg, tuple(f"{a}$_r$" for a in rpy))
    axes[2].set_ylabel("ref. att. [deg]")
    ax = axes[3]
    lines(ax, s.eul_des_deg, tuple(f"{a}$_d$ (desired)" for a in rpy), "--")
    lines(ax, s.eul_deg, rpy)
    ax.set_ylabel("des./act. att. [deg]")
    _limit_to_measured(ax, t, np.column_stack([s.eul_des_deg, s.eul_deg]), s.measured, "deg")
    lines(axes[4], s.att_err_deg, tuple(f"$e_{{{a[1:-1]}}}$" for a in rpy))
    axes[4].set_ylabel("att. error [deg]")
    _limit_to_measured(axes[4], t, s.att_err_deg, s.measured, "deg")
    ax = axes[5]
    for i in range(s.spin_hz.shape[1]):
        ax.plot(t, s.spin_hz[:, i], lw=0.8, label=f"$w_{i + 1}$")
    for lim, name in ((min_spin_hz, "min"), (max_spin_hz, "max")):
        if lim is not None:
            ax.axhline(lim, color="k", ls=":", lw=1.0)
            ax.annotate(f"{name} {lim:g} Hz", xy=(1.0, lim), xycoords=("axes fraction", "data"),
                        xytext=(-4, 3 if name == "min" else -9), textcoords="offset points",
                        ha="right", fontsize=7)
    if min_spin_hz is not None or max_spin_hz is not None:
        ax.plot([], [], "k:", lw=1.0, label="spin limits")
    ax.set_ylabel("spin [Hz]")
    ax = axes[6]
    ax.plot(t, s.r_xy_n, color="k", lw=1.0, label=r"max $r_{xy}$")
    ax.plot(t, s.lat_force_n, color="tab:purple", lw=0.8, label=r"$|u_{f,xy}|$")
    ax.set_ylabel("lateral force [N]")
    ax = axes[7]
    ax.plot(t, s.alpha_ref_deg, "--", color="k", lw=1.0, label=r"$\alpha_r$ (ref.)")
    ax.plot(t, s.alpha_cmd_deg, ":", color="tab:orange", lw=1.0, label=r"$\alpha_{cmd}$")
    ax.plot(t, s.alpha_deg, color="tab:blue", lw=1.0, label=r"$\alpha$ (measured)")
    ax.set_ylabel("tilt [deg]")
    ax.set_xlabel("time [s]")
    spans = phase_spans(t, s.actuation)
    shading = [Patch(color=_SHADE[UDT][0], alpha=0.3,
                     label=f"under-actuated ($\\alpha$ < {UDT_MAX_DEG:g} deg)"),
               Patch(color=_SHADE[FULL][0], alpha=0.3, label="fully actuated")]
    for ax in axes:
        for a, b, state in spans:
            color, alpha = _SHADE[state]
            ax.axvspan(a, b, color=color, alpha=alpha, lw=0)
        ax.grid(True, lw=0.3)
        handles, labels = ax.get_legend_handles_labels()
        if ax is axes[0]:  # the background's meaning, once, at the top
            handles, labels = handles + shading, labels + [str(p.get_label()) for p in shading]
        # outside the plotting area, to the right: a legend never covers a trace
        ax.legend(handles, labels, loc="upper left", bbox_to_anchor=(1.005, 1.0), fontsize=7,
                  frameon=False, borderaxespad=0.0)
    if len(t):
        axes[-1].set_xlim(float(t[0]), float(t[-1]))
    head = (title + "\n") if title else ""
    fig.suptitle(head + "background: red while under-actuated, green while fully actuated; "
                 "error panels scaled to the measured part of the mission", fontsize=10)
    return fig


@dataclass(frozen=True)
class ReportFiles:
    figure: Path
    metrics_json: Path
    metrics_md: Path
    metrics: dict[str, float]


def write_report(record_path: str | Path, out_dir: str | Path) -> ReportFiles:
    """Figure + metrics (JSON, markdown) of a flight record into ``out_dir`` (created);
    :class:`~groundstation.record.RecordFormatError` for a record without rows."""
    from groundstation.configs import load_vehicle
    from groundstation.record import RecordFormatError, read_record

    record = read_record(record_path)
    if not len(record.rows):
        raise RecordFormatError(f"{record_path}: the record has no rows (a header only); "
                                "nothing to report")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    meta = record.metadata
    params = load_vehicle(str(meta.get("vehicle", "fasthex")))
    metrics = record_metrics(record.rows, meta)
    title = " / ".join(str(meta[k]) for k in ("mission", "vehicle", "preset") if k in meta)
    figure = render_figure(record.rows, out / FIGURE_NAME, title=title or Path(record_path).name,
                           min_spin_hz=params.rotors.min_spin_hz,
                           max_spin_hz=params.rotors.max_spin_hz)
    js = out / METRICS_JSON
    shown = metrics_json(metrics)
    js.write_text(json.dumps(shown, indent=1) + "\n", encoding="utf-8")
    md = out / METRICS_MD
    # the table shows the numbers of the JSON file, rounded alike
    md.write_text(metrics_markdown({k: float(v) if isinstance(v, (int, float)) else math.nan
                                    for k, v in shown.items()}, title or Path(record_path).name),
                  encoding="utf-8")
    return ReportFiles(figure, js, md, metrics)

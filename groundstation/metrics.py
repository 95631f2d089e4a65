"""Tracking metrics over a flight record, split by actuation phase (paper-notes item 13).

Phases, over the measured ticks of the mission (takeoff and landing excluded):

- ``all``: every measured tick;
- ``udt`` (under-actuated): measured tilt alpha < 1 deg;
- ``mdt`` (multi-directional thrust): alpha > 20 deg;

``udt`` and ``mdt`` skip the first 2 s after entering the phase and the 2 s after any step of
the alpha reference. Errors: position ``|p_B - p_r|`` on the recorded (true) state; attitude:
the absolute ZYX Euler angles of ``R_r^T R_B`` (against the reference, not R_d); the R_d
deviation is the geodesic angle of ``R_r^T R_d``; the inner-loop error that of ``R_d^T R_B``.
Internal-force loss is ``1 - eta_f`` of the commanded thrusts.

Every key carries its unit: ``<phase>_<quantity>_<unit>``, e.g. ``udt_pos_err_mean_mm``.
Pure functions of the record's rows; a phase without ticks gives NaN values and ``ticks = 0``.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]

UDT_MAX_DEG = 1.0
MDT_MIN_DEG = 20.0
SETTLE_S = 2.0
#: a change of the alpha reference larger than this between two ticks is a step
ALPHA_STEP_DEG = 0.5
PHASES = ("all", "udt", "mdt")


def quat_to_rot(q: npt.ArrayLike) -> FloatArray:
    """Rotation matrices (N, 3, 3) of quaternions (N, 4) (w, x, y, z), normalised first."""
    arr = np.asarray(q, dtype=float)
    arr = arr / np.linalg.norm(arr, axis=-1, keepdims=True)
    w, x, y, z = arr[..., 0], arr[..., 1], arr[..., 2], arr[..., 3]
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def euler_errors_rad(q_ref: npt.ArrayLike, q_body: npt.ArrayLike) -> FloatArray:
    """|roll|, |pitch|, |yaw| (N, 3) of ``R_r^T R_B`` (ZYX convention)."""
    e = np.swapaxes(quat_to_rot(q_ref), -1, -2) @ quat_to_rot(q_body)
    roll = np.arctan2(e[..., 2, 1], e[..., 2, 2])
    pitch = -np.arcsin(np.clip(e[..., 2, 0], -1.0, 1.0))
    yaw = np.arctan2(e[..., 1, 0], e[..., 0, 0])
    return np.abs(np.stack([roll, pitch, yaw], -1))


def geodesic_rad(q_a: npt.ArrayLike, q_b: npt.ArrayLike) -> FloatArray:
    """Angle (rad) of the rotation between two attitudes, per row."""
    a = np.asarray(q_a, dtype=float)
    b = np.asarray(q_b, dtype=float)
    dot = np.abs(np.sum(a * b, axis=-1)) / (np.linalg.norm(a, axis=-1)
                                            * np.linalg.norm(b, axis=-1))
    return np.asarray(2.0 * np.arccos(np.clip(dot, 0.0, 1.0)), dtype=float)


def _time_since_start(t: FloatArray, starts: BoolArray) -> FloatArray:
    """Time since the most recent tick flagged in ``starts`` (inf before the first)."""
    marks = np.where(starts, t, -np.inf)
    return np.asarray(t - np.maximum.accumulate(marks), dtype=float)


def phase_masks(rows: np.ndarray) -> dict[str, BoolArray]:
    """Boolean tick masks of the phases ``all``, ``udt`` and ``mdt``."""
    t = rows["t_s"].astype(float)
    measured = rows["measured"].astype(bool)
    alpha_deg = np.degrees(rows["alpha_rad"].astype(float))
    ref_deg = np.degrees(rows["alpha_ref_rad"].astype(float))
    jump = np.zeros(len(rows), dtype=bool)
    if len(rows) > 1:
        d = np.abs(np.diff(ref_deg))
        jump[1:] = np.nan_to_num(d, nan=0.0) > ALPHA_STEP_DEG
    since_step = _time_since_start(t, jump)
    out = {"all": measured}
    for name, in_phase in (("udt", alpha_deg < UDT_MAX_DEG), ("mdt", alpha_deg > MDT_MIN_DEG)):
        ph = in_phase & measured
        entered = ph & ~np.concatenate([[False], ph[:-1]])
        since_entry = _time_since_start(t, entered)
        out[name] = ph & (since_entry >= SETTLE_S) & (since_step >= SETTLE_S)
    return out


def flight_metrics(rows: np.ndarray, *, min_spin_hz: float | None = None,
                   max_spin_hz: float | None = None) -> dict[str, float]:
    """The summary metrics of a flight record's rows, per phase, with unit-suffixed keys."""
    masks = phase_masks(rows)
    pos_err = np.linalg.norm(rows["pos_w_m"].astype(float) - rows["pos_ref_w_m"].astype(float),
                             axis=1)
    eul = euler_errors_rad(rows["q_wr"], rows["q_wb"])
    rd_dev = geodesic_rad(rows["q_wr"], rows["q_wd"])
    inner = geodesic_rad(rows["q_wd"], rows["q_wb"])
    spins = rows["spin_cmd_hz"].astype(float)
    sat = rows["sat_mask"] > 0
    loss = 1.0 - rows["eta_f"].astype(float)
    out: dict[str, float] = {}
    for name in PHASES:
        m = masks[name]
        n = int(np.count_nonzero(m))
        out[f"{name}_ticks"] = float(n)
        dt = float(np.median(np.diff(rows["t_s"]))) if len(rows) > 1 else 0.0
        out[f"{name}_duration_s"] = n * dt

        def mean(x: FloatArray, mask: BoolArray = m) -> float:
            return float(np.mean(x[mask])) if mask.any() else math.nan

        out[f"{name}_pos_err_mean_mm"] = 1000.0 * mean(pos_err)
        out[f"{name}_pos_err_max_mm"] = 1000.0 * float(np.max(pos_err[m])) if n else math.nan
        for i, axis in enumerate(("roll", "pitch", "yaw")):
            out[f"{name}_{axis}_err_mean_deg"] = math.degrees(mean(eul[:, i]))
        out[f"{name}_rd_dev_mean_deg"] = math.degrees(mean(rd_dev))
        out[f"{name}_rd_dev_max_deg"] = math.degrees(float(np.max(rd_dev[m]))) if n else math.nan
        out[f"{name}_inner_err_mean_deg"] = math.degrees(mean(inner))
        out[f"{name}_spin_min_hz"] = float(np.min(spins[m])) if n else math.nan
        out[f"{name}_spin_max_hz"] = float(np.max(spins[m])) if n else math.nan
        out[f"{name}_spin_saturated_frac"] = mean(sat.astype(float))
        out[f"{name}_internal_force_loss_mean_frac"] = mean(loss)
    if min_spin_hz is not None and max_spin_hz is not None:
        s = spins[masks["all"]]
        out["all_spin_within_limits"] = float(bool(
            s.size == 0 or (np.min(s) >= min_spin_hz - 1e-3 and np.max(s) <= max_spin_hz + 1e-3)))
    return out


#: the resolution a value is worth printing to, by the unit at the end of its key: the
#: measurements behind them are no finer (MoCap ~0.1 mm, timing ~1 us, servo ~0.1 deg)
RESOLUTION_BY_UNIT: dict[str, int] = {  # decimal places
    "mm": 2, "m": 4, "m_s": 4, "deg": 3, "rad": 5, "s": 3, "ms": 3, "us": 0, "hz": 2,
    "frac": 4, "n": 3, "v": 3, "ppm": 1,
}


def rounded(key: str, value: object) -> object:
    """``value`` as it should appear in JSON: whole-number floats of unitless keys (counts,
    flags such as ``all_spin_within_limits``) and ``*_ticks`` as integers, other floats rounded
    to the resolution of the unit their key ends with (6 significant digits without one), NaN
    and infinities as None. Lists and dicts are rounded element by element."""
    if isinstance(value, dict):
        return {k: rounded(str(k), v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [rounded(key, v) for v in value]
    if isinstance(value, bool) or not isinstance(value, float):
        return value
    if not math.isfinite(value):
        return None
    unit = next((u for u in sorted(RESOLUTION_BY_UNIT, key=len, reverse=True)
                 if key.lower().endswith("_" + u)), None)
    if key.endswith("_ticks") or (unit is None and value.is_integer()):
        return int(value)
    if unit is None:
        return float(f"{value:.6g}")
    out = round(value, RESOLUTION_BY_UNIT[unit])
    return 0.0 if out == 0 else out  # no "-0.0"


#: position error a disturbance must bring the vehicle back under ("back under 10 mm")
RECOVERY_THRESHOLD_M = 0.010
#: trailing mean over which the error is judged: the MoCap and estimation noise (paper-
#: calibrated preset: about 5 mm mean, single ticks to 10 mm in a still hover) must not count
#: as "not recovered"; 0.2 s is short against the loop's ~1.5 s settling, long against the noise
RECOVERY_SMOOTHING_S = 0.2
#: how long the smoothed error must stay under the threshold to count as recovered
RECOVERY_HOLD_S = 0.5


def disturbance_metrics(rows: np.ndarray, windows_s: list[tuple[float, float]], *,
                        threshold_m: float = RECOVERY_THRESHOLD_M,
                        smoothing_s: float = RECOVERY_SMOOTHING_S,
                        hold_s: float = RECOVERY_HOLD_S) -> dict[str, float]:
    """How each scheduled disturbance moved the vehicle and how fast it came back.

    ``windows_s``: each event's (start, end) in mission seconds (the rows' ``t_s``; end
    ``inf``: to the end of the flight), in the scenario's order. Event ``i`` is judged from its
    start to its end or the next event's start, whichever comes first, on the position error
    ``|p_B - p_r|`` of the measured ticks:

    - ``dist<i>_peak_err_mm``: the largest error in that window;
    - ``dist<i>_recovery_s``: from the start to the first tick after the peak from which the
      error's trailing ``smoothing_s`` mean stays under ``threshold_m`` for ``hold_s``; NaN when
      it never does in the window (``dist<i>_recovered`` 0), 0 when it never left;
    - ``dist<i>_recovered``: 1 or 0;

    and ``calm_pos_err_mean_mm``, the mean error of the measured ticks before the first event
    (the still hover the disturbances are judged against; NaN when there are none).
    """
    out: dict[str, float] = {}
    t = rows["t_s"].astype(float)
    measured = rows["measured"].astype(bool)
    err = np.linalg.norm(rows["pos_w_m"].astype(float) - rows["pos_ref_w_m"].astype(float),
                         axis=1)
    dt = float(np.median(np.diff(t))) if len(t) > 1 else 0.002
    n_avg = max(1, round(smoothing_s / dt))
    csum = np.concatenate([[0.0], np.cumsum(err)])
    idx = np.arange(len(err))
    lo = np.maximum(idx + 1 - n_avg, 0)
    smooth = (csum[idx + 1] - csum[lo]) / (idx + 1 - lo)
    n_hold = max(1, round(hold_s / dt))
    order = sorted(range(len(windows_s)), key=lambda i: windows_s[i][0])
    first = windows_s[order[0]][0] if order else math.inf
    calm = measured & (t < first)
    out["calm_pos_err_mean_mm"] = 1000.0 * float(np.mean(err[calm])) if calm.any() else math.nan
    for rank, i in enumerate(order):
        start = windows_s[i][0]
        end = min(windows_s[i][1], windows_s[order[rank + 1]][0] if rank + 1 < len(order)
                  else math.inf)
        window = np.flatnonzero((t >= start) & (t < end) & measured)
        key = f"dist{i}"
        if window.size == 0:
            out[f"{key}_peak_err_mm"] = math.nan
            out[f"{key}_recovery_s"] = math.nan
            out[f"{key}_recovered"] = 0.0
            continue
        w_err = err[window]
        k_peak = int(np.argmax(w_err))
        out[f"{key}_peak_err_mm"] = 1000.0 * float(w_err[k_peak])
        if float(np.max(smooth[window])) < threshold_m:
            out[f"{key}_recovery_s"], out[f"{key}_recovered"] = 0.0, 1.0
            continue
        above = smooth[window] >= threshold_m
        # ticks from which the next n_hold (within the window) are all under the threshold
        run_under = np.zeros(window.size, dtype=int)
        count = 0
        for j in range(window.size - 1, -1, -1):
            count = 0 if above[j] else count + 1
            run_under[j] = count
        ok = np.flatnonzero((run_under >= n_hold) & (np.arange(window.size) >= k_peak))
        if ok.size == 0:
            out[f"{key}_recovery_s"], out[f"{key}_recovered"] = math.nan, 0.0
        else:
            out[f"{key}_recovery_s"] = float(t[window[ok[0]]] - start)
            out[f"{key}_recovered"] = 1.0
    return out

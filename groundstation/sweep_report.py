"""Plots and a summary of a sweep campaign's results table (``fasthex sweep report``).

Input: the Parquet table ``fasthex sweep CAMPAIGN.yaml`` writes, one row per simulated run. Its
schema metadata key ``fasthex.sweep`` holds ``{"campaign", "parameters", "metrics", "version":
1}``: the parameter columns (dotted config paths, float64, int64 or string) in campaign order and
the numeric metric columns (float64, NaN when not measured or when the run errored, the unit at the
end of the key). Every table also has ``run_id``, ``run_index``, ``campaign``, ``seed``,
``scenario`` (null = no scenario), ``verdict`` (``ok``, ``crash`` or ``error``), ``crash_reason``,
``error``, ``fasthex_version`` and ``wall_time_s``. ``scenario`` counts as a categorical parameter
when it takes more than one value. Runs of one point differ only in their seed.

Output, in the output directory (:func:`write_report` returns the paths):

- ``<metric>-vs-<parameter>.png`` for each metric and parameter: every ok run as a faint dot, the
  mean of the ok runs per distinct value (over seeds and the other parameters) as a line with
  the min-max band of those runs, crash and error runs as red crosses along the top. A numeric
  parameter with more than :data:`MAX_GRID_VALUES` distinct values (a random or Latin hypercube
  sweep) is averaged in :data:`N_BINS` bins instead; a categorical one is drawn as means with
  min-max whiskers. The x axis is logarithmic when every value is positive and they span more
  than :data:`LOG_DECADES` decades, spread over them (:func:`use_log_scale`).
- ``<metric>-map-<p1>-<p2>.png`` for each metric and pair of numeric parameters that both vary:
  the mean of the ok runs per cell, on the grid of distinct values (an axis with at most
  :data:`MAX_GRID_VALUES` of them) or in :data:`N_BINS` bins; hatched cells have no ok run;
  values are printed in the cells up to :data:`MAX_ANNOTATED` x :data:`MAX_ANNOTATED`.
- ``failures.png``: every run in the plane of the first two numeric parameters (completed with
  categorical ones, a strip when there is only one parameter), coloured by verdict.
- ``summary.txt``: run counts by verdict, the parameters, per metric the best and worst point
  (mean over its seeds), the crash reasons and error texts with their counts.
- ``index.html``: a static page with the summary and every figure (no script, no network).

Metrics default to ``all_pos_err_mean_mm`` and every ``dist*_recovery_s`` that an ok run
measured; any metric column of the metadata, and ``wall_time_s``, can be asked for. Only ok
runs with a finite value enter the means. The aggregation functions (:func:`grid_means`,
:func:`line_stats`, :func:`point_means`, :func:`verdict_counts`, ...) are pure and draw
nothing; the ``plot_*`` functions draw them. Problems the user can fix (a missing
file, a file that is not a sweep table, an unknown metric, no parameters) raise
:class:`ReportError`.
"""

from __future__ import annotations

import fnmatch
import html
import itertools
import json
import math
import re
from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from urllib.parse import quote

import numpy as np
import numpy.typing as npt
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq

from groundstation.metrics import RESOLUTION_BY_UNIT

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]
BoolArray = npt.NDArray[np.bool_]
ObjectArray = npt.NDArray[np.object_]

SWEEP_METADATA_KEY = b"fasthex.sweep"
SUPPORTED_VERSION = 1
VERDICTS = ("ok", "crash", "error")
REQUIRED_COLUMNS = ("run_id", "run_index", "campaign", "seed", "scenario", "verdict",
                    "crash_reason", "error", "fasthex_version", "wall_time_s")
#: the ``scenario`` column as a parameter, when it varies; null is shown as NO_SCENARIO
SCENARIO = "scenario"
NO_SCENARIO = "(none)"

DEFAULT_METRIC = "all_pos_err_mean_mm"
DEFAULT_METRIC_PATTERN = "dist*_recovery_s"
#: metrics where a larger value is the better one (everything else: smaller is better)
HIGHER_IS_BETTER = frozenset({"sim_s_per_wall_s"})

#: an axis with more distinct values than this is binned (a random or LHS sweep)
MAX_GRID_VALUES = 30
N_BINS = 12
#: heat maps print their values when both axes have at most this many cells
MAX_ANNOTATED = 10
#: a logarithmic axis when every value is positive and max / min exceeds 10 ** LOG_DECADES
LOG_DECADES = 1.5

DPI = 110
LINE_FIGSIZE = (7.5, 4.8)    # inches
MAP_FIGSIZE = (7.5, 6.0)
FAILURE_FIGSIZE = (7.5, 5.5)
FAILURES_NAME = "failures.png"
SUMMARY_NAME = "summary.txt"
INDEX_NAME = "index.html"

VERDICT_STYLE: Mapping[str, tuple[str, str, float]] = {  # colour, marker, size
    "ok": ("tab:green", "o", 70.0),
    "crash": ("tab:red", "X", 60.0),
    "error": ("tab:purple", "^", 50.0),
}


class ReportError(Exception):
    """A problem with the table or the request that the user can fix; the message says how."""


# -- the table -------------------------------------------------------------------------------
@dataclass(frozen=True)
class Parameter:
    """One swept quantity, one value per run: float64 (NaN = missing) when numeric, else str."""

    name: str
    numeric: bool
    integer: bool                    # an int64 column: values are printed without decimals
    values: npt.NDArray[Any]

    def distinct(self) -> list[float] | list[str]:
        """The distinct values present, sorted (missing ones left out)."""
        if self.numeric:
            v = self.values[np.isfinite(self.values)]
            return [float(x) for x in np.unique(v)]
        return sorted({str(x) for x in self.values})

    def format(self, value: float | str) -> str:
        """A value as the report prints it."""
        if isinstance(value, str):
            return value
        if not math.isfinite(value):
            return "-"
        if self.integer:
            return str(int(value))
        return f"{value:.6g}"


@dataclass(frozen=True)
class SweepTable:
    """A sweep results table, decoded: one entry per run in every array."""

    campaign: str
    parameters: tuple[Parameter, ...]    # campaign order, then ``scenario`` when it varies
    metrics: tuple[str, ...]             # the numeric metric columns
    verdict: ObjectArray                 # "ok", "crash" or "error"
    seed: IntArray
    crash_reason: tuple[str | None, ...]
    error: tuple[str | None, ...]
    metric_values: Mapping[str, FloatArray] = field(repr=False)

    @property
    def n_runs(self) -> int:
        return len(self.verdict)

    @property
    def ok(self) -> BoolArray:
        return np.asarray(self.verdict == "ok", dtype=bool)

    def parameter(self, name: str) -> Parameter:
        for p in self.parameters:
            if p.name == name:
                return p
        known = ", ".join(p.name for p in self.parameters) or "none"
        raise ReportError(f"unknown parameter {name!r}; the table's parameters: {known}")

    def metric(self, name: str) -> FloatArray:
        if name not in self.metric_values:
            raise ReportError(f"unknown metric {name!r}; available numeric metrics: "
                              f"{', '.join(self.metrics) or 'none'}")
        return self.metric_values[name]


def _floats(col: pa.ChunkedArray) -> FloatArray:
    return np.asarray(pc.fill_null(col.cast(pa.float64()), math.nan).to_numpy(),
                      dtype=np.float64)


def _strings(col: pa.ChunkedArray) -> list[str | None]:
    return [None if v is None else str(v) for v in col.to_pylist()]


def _is_numeric(t: pa.DataType) -> bool:
    return bool(pa.types.is_integer(t) or pa.types.is_floating(t))


def sweep_table(table: pa.Table, source: str = "table") -> SweepTable:
    """Decode and check an in-memory sweep table (``source`` names it in error messages)."""
    raw = (table.schema.metadata or {}).get(SWEEP_METADATA_KEY)
    if raw is None:
        raise ReportError(f"{source} is not a sweep table: its schema has no "
                          f"{SWEEP_METADATA_KEY.decode()!r} metadata "
                          "(write it with `fasthex sweep CAMPAIGN.yaml`)")
    try:
        meta = json.loads(raw)
    except ValueError as exc:
        raise ReportError(f"{source}: unreadable {SWEEP_METADATA_KEY.decode()!r} metadata "
                          f"({exc})") from None
    if not isinstance(meta, dict):
        raise ReportError(f"{source}: the sweep metadata is not a JSON object")
    if meta.get("version") != SUPPORTED_VERSION:
        raise ReportError(f"{source}: sweep table version {meta.get('version')!r}; this "
                          f"fasthex reads version {SUPPORTED_VERSION}")
    names = {k: meta.get(k) for k in ("parameters", "metrics")}
    for key, value in names.items():
        if not (isinstance(value, list) and all(isinstance(v, str) for v in value)):
            raise ReportError(f"{source}: the sweep metadata's {key!r} is not a list of "
                              "column names")
    params: list[str] = names["parameters"] or []
    metrics: list[str] = names["metrics"] or []
    missing = [c for c in (*REQUIRED_COLUMNS, *params, *metrics)
               if c not in table.column_names]
    if missing:
        raise ReportError(f"{source}: not a valid sweep table, missing column(s) "
                          f"{', '.join(dict.fromkeys(missing))}")
    not_numeric = [m for m in metrics if not _is_numeric(table.schema.field(m).type)]
    if not_numeric:
        raise ReportError(f"{source}: metric column(s) {', '.join(not_numeric)} are not numeric")

    verdict = np.array(_strings(table.column("verdict")), dtype=object)
    unknown = sorted({str(v) for v in verdict} - set(VERDICTS))
    if unknown:
        raise ReportError(f"{source}: unknown verdict(s) {', '.join(unknown)} "
                          f"(expected {', '.join(VERDICTS)})")
    parameters = []
    for name in params:
        col = table.column(name)
        if _is_numeric(col.type):
            parameters.append(Parameter(name, True, pa.types.is_integer(col.type), _floats(col)))
        else:
            values = ["(null)" if v is None else v for v in _strings(col)]
            parameters.append(Parameter(name, False, False, np.array(values, dtype=object)))
    scenario = np.array([NO_SCENARIO if v is None else v
                         for v in _strings(table.column(SCENARIO))], dtype=object)
    if len(set(scenario)) > 1 and SCENARIO not in params:
        parameters.append(Parameter(SCENARIO, False, False, scenario))
    campaign = meta.get("campaign")
    if not isinstance(campaign, str):
        campaign = next((c for c in _strings(table.column("campaign")) if c), "")
    # wall time is measured for every run: how the cost of a run varies is worth a plot too
    available = [*metrics, *(["wall_time_s"] if "wall_time_s" not in metrics else [])]
    return SweepTable(
        campaign=campaign, parameters=tuple(parameters), metrics=tuple(available),
        verdict=verdict,
        seed=np.asarray(pc.fill_null(table.column("seed"), -1).to_numpy(), dtype=np.int64),
        crash_reason=tuple(_strings(table.column("crash_reason"))),
        error=tuple(_strings(table.column("error"))),
        metric_values={m: _floats(table.column(m)) for m in available})


def read_sweep(path: str | Path) -> SweepTable:
    """Read and check a sweep table from a Parquet file."""
    p = Path(path)
    if not p.is_file():
        raise ReportError(f"{p}: no such file")
    try:
        table = pq.read_table(p)
    except (pa.ArrowException, OSError) as exc:
        raise ReportError(f"{p}: not a readable Parquet file ({exc})") from None
    return sweep_table(table, source=str(p))


def _as_sweep(table: SweepTable | pa.Table) -> SweepTable:
    return table if isinstance(table, SweepTable) else sweep_table(table)


# -- names and labels ------------------------------------------------------------------------
_UNIT_DISPLAY = {"hz": "Hz", "m_s": "m/s", "n": "N", "v": "V", "us": "µs", "frac": "fraction"}


def split_unit(key: str) -> tuple[str, str | None]:
    """``("all_pos_err_mean", "mm")`` of ``all_pos_err_mean_mm``: the unit a metric key ends
    with (one of :data:`groundstation.metrics.RESOLUTION_BY_UNIT`), None without one."""
    for unit in sorted(RESOLUTION_BY_UNIT, key=len, reverse=True):
        if key.lower().endswith("_" + unit) and len(key) > len(unit) + 1:
            return key[:-len(unit) - 1], unit
    return key, None


def metric_label(key: str) -> str:
    """An axis label: ``all_pos_err_mean_mm`` -> ``all pos err mean [mm]``; a ratio such as
    ``sim_s_per_wall_s`` -> ``sim per wall [s/s]``."""
    if "_per_" in key:
        num, den = key.split("_per_", 1)
        (a, u1), (b, u2) = split_unit(num), split_unit(den)
        if u1 and u2:
            units = f"{_UNIT_DISPLAY.get(u1, u1)}/{_UNIT_DISPLAY.get(u2, u2)}"
            return f"{a} per {b}".replace("_", " ") + f" [{units}]"
    stem, unit = split_unit(key)
    text = stem.replace("_", " ")
    return f"{text} [{_UNIT_DISPLAY.get(unit, unit)}]" if unit else text


def file_stem(*parts: str) -> str:
    """A file-system-safe name of ``parts`` joined by ``-`` (letters, digits, ``._-`` only)."""
    cleaned = [re.sub(r"[^A-Za-z0-9._]+", "_", p).strip("._") or "x" for p in parts]
    return "-".join(cleaned)[:120]


# -- aggregation (pure) ----------------------------------------------------------------------
def default_metrics(table: SweepTable | pa.Table) -> list[str]:
    """``all_pos_err_mean_mm`` and every ``dist*_recovery_s``, those that an ok run measured."""
    t = _as_sweep(table)
    wanted = [m for m in t.metrics
              if m == DEFAULT_METRIC or fnmatch.fnmatchcase(m, DEFAULT_METRIC_PATTERN)]
    return [m for m in wanted if np.isfinite(t.metric(m)[t.ok]).any()]


def resolve_metrics(table: SweepTable | pa.Table, metrics: Sequence[str] | None) -> list[str]:
    """The metrics to draw: ``metrics`` checked against the table (:class:`ReportError` naming
    the available ones otherwise), or :func:`default_metrics` when None or empty."""
    t = _as_sweep(table)
    if not metrics:
        return default_metrics(t)
    unknown = [m for m in metrics if m not in t.metrics]
    if unknown:
        raise ReportError(f"unknown metric(s) {', '.join(unknown)}; available numeric metrics: "
                          f"{', '.join(t.metrics) or 'none'}")
    return list(dict.fromkeys(metrics))


def use_log_scale(values: npt.ArrayLike) -> bool:
    """True when the finite values are all positive, span more than LOG_DECADES decades and
    are spread over them rather than over the linear range: the median of the distinct values
    lies in the lowest quarter of the range. A log-spaced grid (0.01, 0.1, 1, 10) or a
    log-uniform sample qualifies; 1, 2, ..., 100 or a uniform sample of (0, 1], whose smallest
    draw may be decades below the rest, does not."""
    v = np.unique(np.asarray(values, dtype=np.float64))
    v = v[np.isfinite(v)]
    if not (v.size > 1 and v[0] > 0 and math.log10(v[-1] / v[0]) > LOG_DECADES):
        return False
    return bool(np.median(v) < v[0] + 0.25 * (v[-1] - v[0]))


@dataclass(frozen=True)
class Axis:
    """How a parameter's runs fall into cells: one cell per distinct value (categories or at most
    MAX_GRID_VALUES numbers) or N_BINS bins of a numeric range."""

    parameter: Parameter
    labels: tuple[str, ...]      # one per cell
    centres: FloatArray          # data position of each cell (its index when categorical)
    edges: FloatArray | None     # bin edges when binned, else None
    log: bool
    index: IntArray              # per run: its cell, -1 when the value is missing

    @property
    def size(self) -> int:
        return len(self.labels)

    @property
    def binned(self) -> bool:
        return self.edges is not None

    @property
    def numeric(self) -> bool:
        return self.parameter.numeric


def make_axis(param: Parameter, max_values: int = MAX_GRID_VALUES, n_bins: int = N_BINS) -> Axis:
    """The cells of ``param``'s values (see :class:`Axis`)."""
    if not param.numeric:
        cats = param.distinct()
        lookup = {c: i for i, c in enumerate(cats)}
        index = np.array([lookup[str(v)] for v in param.values], dtype=np.int64)
        return Axis(param, tuple(str(c) for c in cats), np.arange(len(cats), dtype=np.float64),
                    None, False, index)
    v = param.values
    finite = np.isfinite(v)
    distinct = np.unique(v[finite])
    log = use_log_scale(distinct)
    index = np.full(len(v), -1, dtype=np.int64)
    if len(distinct) <= max_values:
        index[finite] = np.searchsorted(distinct, v[finite])
        return Axis(param, tuple(param.format(float(x)) for x in distinct),
                    distinct.astype(np.float64), None, log, index)
    lo, hi = float(distinct[0]), float(distinct[-1])
    edges = np.geomspace(lo, hi, n_bins + 1) if log else np.linspace(lo, hi, n_bins + 1)
    index[finite] = np.clip(np.searchsorted(edges, v[finite], side="right") - 1, 0, n_bins - 1)
    centres = np.sqrt(edges[:-1] * edges[1:]) if log else 0.5 * (edges[:-1] + edges[1:])
    labels = tuple(f"{a:.3g}–{b:.3g}" for a, b in itertools.pairwise(edges))
    return Axis(param, labels, centres, edges, log, index)


def _measured(t: SweepTable, metric: str) -> tuple[FloatArray, BoolArray]:
    """The metric's values and the runs that enter means: ok with a finite value."""
    y = t.metric(metric)
    return y, t.ok & np.isfinite(y)


@dataclass(frozen=True)
class LineStats:
    """A metric per cell of one parameter's axis, over the ok runs in the cell."""

    axis: Axis
    mean: FloatArray     # NaN where no ok run
    lo: FloatArray       # the smallest run value
    hi: FloatArray       # the largest
    count: IntArray      # ok runs with a value


def line_stats(table: SweepTable | pa.Table, metric: str, param: str) -> LineStats:
    """Mean, min and max of ``metric`` over the ok runs at each value (or bin) of ``param``,
    pooled over seeds and every other parameter."""
    t = _as_sweep(table)
    axis = make_axis(t.parameter(param))
    y, use = _measured(t, metric)
    use = use & (axis.index >= 0)
    n = axis.size
    count = np.bincount(axis.index[use], minlength=n).astype(np.int64)
    total = np.bincount(axis.index[use], weights=y[use], minlength=n)
    lo, hi = np.full(n, np.inf), np.full(n, -np.inf)
    np.minimum.at(lo, axis.index[use], y[use])
    np.maximum.at(hi, axis.index[use], y[use])
    empty = count == 0
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(empty, np.nan, total / np.maximum(count, 1))
    lo[empty] = hi[empty] = np.nan
    return LineStats(axis, mean, lo, hi, count)


@dataclass(frozen=True)
class Grid:
    """A metric over the cells of two parameters: ``mean[j, i]`` is at ``y`` cell j, ``x`` cell
    i."""

    x: Axis
    y: Axis
    mean: FloatArray     # (y.size, x.size), NaN where no ok run
    count: IntArray      # (y.size, x.size) ok runs with a value


def grid_means(table: SweepTable | pa.Table, metric: str, p1: str, p2: str) -> Grid:
    """Mean of ``metric`` over the ok runs in each cell of (``p1`` along x, ``p2`` along y),
    pooled over seeds and every other parameter; cells are distinct values on a grid sweep,
    bins on a random one (:func:`make_axis`)."""
    t = _as_sweep(table)
    x, yax = make_axis(t.parameter(p1)), make_axis(t.parameter(p2))
    v, use = _measured(t, metric)
    use = use & (x.index >= 0) & (yax.index >= 0)
    flat = yax.index[use] * x.size + x.index[use]
    cells = x.size * yax.size
    count = np.bincount(flat, minlength=cells).astype(np.int64)
    total = np.bincount(flat, weights=v[use], minlength=cells)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(count > 0, total / np.maximum(count, 1), np.nan)
    shape = (yax.size, x.size)
    return Grid(x, yax, mean.reshape(shape), count.reshape(shape))


@dataclass(frozen=True)
class PointMean:
    """One point of the campaign (a value of every parameter) and a metric over its seeds."""

    values: tuple[float | str, ...]   # one per table parameter, in order
    mean: float                       # over the ok runs with a value; NaN when none
    runs: int                         # runs at the point (every verdict)
    measured: int                     # ok runs with a value


def point_means(table: SweepTable | pa.Table, metric: str) -> list[PointMean]:
    """``metric`` averaged over the seeds of each point, every point of the table (sorted by
    parameter values)."""
    t = _as_sweep(table)
    if not t.parameters:
        return []
    codes = []
    for p in t.parameters:
        vals = p.values if p.numeric else np.asarray(p.values, dtype=str)
        codes.append(np.unique(vals, return_inverse=True)[1].reshape(-1))
    keys, first, inverse = np.unique(np.stack(codes, axis=1), axis=0, return_index=True,
                                     return_inverse=True)
    inverse = inverse.reshape(-1)
    y, use = _measured(t, metric)
    n = len(keys)
    runs = np.bincount(inverse, minlength=n)
    measured = np.bincount(inverse[use], minlength=n)
    total = np.bincount(inverse[use], weights=y[use], minlength=n)
    out = []
    for k in range(n):
        row = int(first[k])
        values = tuple(float(p.values[row]) if p.numeric else str(p.values[row])
                       for p in t.parameters)
        mean = float(total[k] / measured[k]) if measured[k] else math.nan
        out.append(PointMean(values, mean, int(runs[k]), int(measured[k])))
    return out


def extremes(table: SweepTable | pa.Table, metric: str) -> tuple[PointMean, PointMean] | None:
    """(best, worst) point by mean over seeds: the lowest mean is best except for
    :data:`HIGHER_IS_BETTER` metrics; None when no ok run measured ``metric``."""
    points = [p for p in point_means(table, metric) if p.measured]
    if not points:
        return None
    low = min(points, key=lambda p: p.mean)
    high = max(points, key=lambda p: p.mean)
    return (high, low) if metric in HIGHER_IS_BETTER else (low, high)


@dataclass(frozen=True)
class VerdictCounts:
    ok: int
    crash: int
    error: int

    @property
    def total(self) -> int:
        return self.ok + self.crash + self.error

    @property
    def failed(self) -> int:
        return self.crash + self.error


def verdict_counts(table: SweepTable | pa.Table) -> VerdictCounts:
    """How many runs ended ok, crashed or raised."""
    t = _as_sweep(table)
    c = Counter(str(v) for v in t.verdict)
    return VerdictCounts(c["ok"], c["crash"], c["error"])


def grouped_texts(table: SweepTable | pa.Table, verdict: str) -> list[tuple[str, int]]:
    """The error texts (``verdict="error"``) or crash reasons (``"crash"``) of the runs with
    that verdict, identical ones counted together, most frequent first."""
    t = _as_sweep(table)
    texts = t.error if verdict == "error" else t.crash_reason
    c = Counter((texts[i] or "(no text)").strip() for i in np.flatnonzero(t.verdict == verdict))
    return sorted(c.items(), key=lambda kv: (-kv[1], kv[0]))


# -- summary ---------------------------------------------------------------------------------
def _fmt(v: float) -> str:
    return f"{v:.4g}" if math.isfinite(v) else "-"


def _describe_point(t: SweepTable, p: PointMean) -> str:
    return ", ".join(f"{q.name}={q.format(v)}" for q, v in zip(t.parameters, p.values,
                                                                strict=True))


def _describe_parameter(p: Parameter) -> str:
    values = p.distinct()
    if not p.numeric:
        shown = ", ".join(str(v) for v in values[:8]) + (", ..." if len(values) > 8 else "")
        return f"categorical, {len(values)} value(s): {shown}"
    if not values:
        return "numeric, no value"
    kind = "log-spaced, " if use_log_scale(values) else ""
    span = (f" in [{p.format(values[0])}, {p.format(values[-1])}]" if len(values) > 1
            else f": {p.format(values[0])}")
    return f"numeric, {kind}{len(values)} value(s){span}"


def summary_text(table: SweepTable | pa.Table, metrics: Sequence[str],
                 notes: Sequence[str] = ()) -> str:
    """The report's text: campaign, counts by verdict, parameters, best and worst point of each
    metric, crash reasons and error texts with counts, and ``notes``."""
    t = _as_sweep(table)
    c = verdict_counts(t)
    lines = [f"campaign: {t.campaign or '(unnamed)'}",
             f"runs: {c.total} (ok {c.ok}, crash {c.crash}, error {c.error})"]
    points = point_means(t, metrics[0] if metrics else t.metrics[0]) if t.metrics else []
    if points:
        per = sorted({p.runs for p in points})
        runs_per = f"{per[0]}" if len(per) == 1 else f"{per[0]}-{per[-1]}"
        lines.append(f"points: {len(points)} ({runs_per} run(s) each), "
                     f"seeds: {len(np.unique(t.seed))}")
    lines += ["", "parameters:"]
    width = max((len(p.name) for p in t.parameters), default=0)
    lines += [f"  {p.name:<{width}}  {_describe_parameter(p)}" for p in t.parameters]
    if not t.parameters:
        lines.append("  (none)")
    lines += ["", "metrics (mean over the seeds of a point, ok runs only):"]
    for m in metrics:
        unit = split_unit(m)[1]
        u = f" {_UNIT_DISPLAY.get(unit, unit)}" if unit else ""
        found = extremes(t, m)
        lines.append(f"  {m}  ({metric_label(m)})")
        if found is None:
            lines.append("    no ok run measured it")
            continue
        best, worst = found
        order = "highest" if m in HIGHER_IS_BETTER else "lowest"
        other = "lowest" if m in HIGHER_IS_BETTER else "highest"
        for name, sense, p in (("best", order, best), ("worst", other, worst)):
            lines.append(f"    {name} ({sense}): {_fmt(p.mean)}{u} at {_describe_point(t, p)} "
                         f"({p.measured} of {p.runs} run(s) measured)")
    if not metrics:
        lines.append("  (none)")
    for verdict, title in (("crash", "crash reasons"), ("error", "errors")):
        groups = grouped_texts(t, verdict)
        if groups:
            lines += ["", f"{title}:"]
            for text, n in groups:
                body = text if len(text) <= 400 else text[:400] + " ..."
                lines.append(f"  {n} x " + body.replace("\n", "\n      "))
    if notes:
        lines += ["", "notes:"] + [f"  - {n}" for n in notes]
    return "\n".join(lines) + "\n"


# -- plotting --------------------------------------------------------------------------------
def _figure(size: tuple[float, float]) -> Any:
    """A figure of its own (no pyplot state), rendered by the Agg canvas."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=size, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _save(fig: Any, path: Path) -> Path:
    fig.savefig(path, dpi=DPI)
    return path


def _short(label: str, n: int = 22) -> str:
    return label if len(label) <= n else label[:n - 1] + "…"


def _run_positions(axis: Axis, jitter: float = 0.12) -> FloatArray:
    """Where each run goes along ``axis``: its value, or its category (spread a little so that
    the runs of one category do not hide each other); NaN when missing."""
    if axis.numeric:
        return np.asarray(axis.parameter.values, dtype=np.float64)
    rng = np.random.default_rng(0)
    pos = axis.index.astype(np.float64) + rng.uniform(-jitter, jitter, len(axis.index))
    pos[axis.index < 0] = np.nan
    return pos


def _category_ticks(ax: Any, axis: Axis, which: str) -> None:
    ticks = np.arange(axis.size)
    step = max(1, math.ceil(axis.size / 15))
    labels = [_short(lab) for lab in axis.labels]
    if which == "x":
        ax.set_xticks(ticks[::step], labels[::step], rotation=30 if axis.size > 4 else 0,
                      ha="right" if axis.size > 4 else "center", fontsize=8)
    else:
        ax.set_yticks(ticks[::step], labels[::step], fontsize=8)


def _failure_marks(ax: Any, t: SweepTable, x: FloatArray) -> bool:
    """Crash and error runs as red crosses along the top of the axes, at their x; whether
    there were any."""
    drawn = False
    for verdict, marker in (("crash", "x"), ("error", "+")):
        sel = (t.verdict == verdict) & np.isfinite(x)
        n = int(np.count_nonzero(t.verdict == verdict))
        if n:
            drawn = True
            ax.plot(x[sel], np.full(int(sel.sum()), 0.97), ls="none", marker=marker,
                    color="red", ms=8, mew=1.5, transform=ax.get_xaxis_transform(),
                    clip_on=False, label=f"{verdict} ({n}), at the top")
    return drawn


def plot_metric_vs_param(table: SweepTable | pa.Table, metric: str, param: str,
                         path: str | Path) -> Path:
    """One metric against one parameter (see the module docstring); writes a PNG."""
    t = _as_sweep(table)
    s = line_stats(t, metric, param)
    axis = s.axis
    y, use = _measured(t, metric)
    x = _run_positions(axis)
    fig = _figure(LINE_FIGSIZE)
    ax = fig.add_subplot()
    ax.scatter(x[use], y[use], s=12, color="tab:blue", alpha=0.3, lw=0,
               label=f"ok runs ({int(use.sum())})")
    have = s.count > 0
    what = "bin" if axis.binned else "value"
    if axis.numeric and int(have.sum()) > 1:
        ax.fill_between(axis.centres, s.lo, s.hi, color="tab:blue", alpha=0.15, lw=0,
                        label="min-max of the runs")
        ax.plot(axis.centres, s.mean, "-o", color="tab:blue", ms=4, lw=1.6,
                label=f"mean per {what}")
    else:
        err = np.vstack([s.mean - s.lo, s.hi - s.mean])[:, have]
        ax.errorbar(axis.centres[have], s.mean[have], yerr=err, fmt="o", color="tab:blue",
                    ms=6, capsize=5, lw=1.6, label=f"mean per {what}, min-max whiskers")
    if _failure_marks(ax, t, x):   # room above the data for the crosses
        lo, hi = ax.get_ylim()
        ax.set_ylim(lo, hi + 0.1 * (hi - lo))
    if axis.numeric:
        if axis.log:
            ax.set_xscale("log")
        if axis.size == 1:
            ax.set_xticks(axis.centres, axis.labels)
    else:
        _category_ticks(ax, axis, "x")
        ax.set_xlim(-0.6, axis.size - 0.4)
    ax.set_xlabel(param, fontsize=10)
    ax.set_ylabel(metric_label(metric), fontsize=10)
    ax.grid(True, lw=0.3)
    ax.legend(fontsize=8, loc="best", framealpha=0.8)
    binned = f", in {axis.size} bins" if axis.binned else ""
    ax.set_title(f"{metric_label(metric)} vs {param}{binned}\n"
                 f"mean over seeds and the other parameters — {t.campaign}", fontsize=10)
    return _save(fig, Path(path))


def _mesh_coords(axis: Axis) -> FloatArray:
    """Cell edges for a heat map: real bin edges when binned, else one unit cell per value."""
    if axis.edges is not None:
        return axis.edges
    return np.arange(axis.size + 1, dtype=np.float64) - 0.5


def _map_centres(axis: Axis) -> FloatArray:
    return axis.centres if axis.binned else np.arange(axis.size, dtype=np.float64)


def plot_heat_map(table: SweepTable | pa.Table, metric: str, p1: str, p2: str,
                  path: str | Path) -> Path:
    """The mean of a metric over the (``p1``, ``p2``) plane (see :func:`grid_means`); writes a
    PNG."""
    from matplotlib.patches import Rectangle

    t = _as_sweep(table)
    g = grid_means(t, metric, p1, p2)
    fig = _figure(MAP_FIGSIZE)
    ax = fig.add_subplot()
    xe, ye = _mesh_coords(g.x), _mesh_coords(g.y)
    ax.add_patch(Rectangle((xe[0], ye[0]), xe[-1] - xe[0], ye[-1] - ye[0], facecolor="0.93",
                           edgecolor="0.6", hatch="///", lw=0, zorder=0))
    data = np.ma.masked_invalid(g.mean)
    finite = g.mean[np.isfinite(g.mean)]
    vmin, vmax = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)
    if vmin == vmax:
        vmin, vmax = vmin - 0.5 * abs(vmin or 1.0), vmax + 0.5 * abs(vmax or 1.0)
    mesh = ax.pcolormesh(xe, ye, data, cmap="viridis", vmin=vmin, vmax=vmax, shading="flat",
                         zorder=1)
    bar = fig.colorbar(mesh, ax=ax)
    bar.set_label(metric_label(metric), fontsize=10)
    for axis, which in ((g.x, "x"), (g.y, "y")):
        if axis.binned:
            if axis.log:
                (ax.set_xscale if which == "x" else ax.set_yscale)("log")
        else:
            _category_ticks(ax, axis, which)
    ax.set_xlim(xe[0], xe[-1])
    ax.set_ylim(ye[0], ye[-1])
    if g.x.size <= MAX_ANNOTATED and g.y.size <= MAX_ANNOTATED:
        cmap, norm = mesh.get_cmap(), mesh.norm
        for (j, i), v in np.ndenumerate(g.mean):
            cx, cy = _map_centres(g.x)[i], _map_centres(g.y)[j]
            if math.isfinite(v):
                r, gg, b, _ = cmap(norm(v))
                color = "white" if 0.299 * r + 0.587 * gg + 0.114 * b < 0.5 else "black"
                ax.text(cx, cy, f"{v:.3g}", ha="center", va="center", fontsize=8, color=color)
            else:
                ax.text(cx, cy, "no value", ha="center", va="center", fontsize=6, color="0.3")
    ax.set_xlabel(p1 + (f" ({N_BINS} bins)" if g.x.binned else ""), fontsize=10)
    ax.set_ylabel(p2 + (f" ({N_BINS} bins)" if g.y.binned else ""), fontsize=10)
    ax.set_title(f"{metric_label(metric)}: mean over seeds and the other parameters\n"
                 f"hatched: no ok run measured it (failed, or never recovered) — {t.campaign}",
                 fontsize=10)
    return _save(fig, Path(path))


def failure_axes(table: SweepTable | pa.Table) -> list[str]:
    """The parameters of the failure map: the first two numeric ones that vary, completed with
    categorical ones, then with those of a single value (one parameter: a strip)."""
    t = _as_sweep(table)
    varies = [len(p.distinct()) > 1 for p in t.parameters]
    order = sorted(range(len(t.parameters)),
                   key=lambda i: (not varies[i], not t.parameters[i].numeric, i))
    return [t.parameters[i].name for i in order[:2]]


def plot_failures(table: SweepTable | pa.Table, path: str | Path) -> Path:
    """Every run in parameter space coloured by verdict, counts in the legend; writes a PNG."""
    t = _as_sweep(table)
    names = failure_axes(t)
    if not names:
        raise ReportError("the table has no parameter to draw the runs over")
    axes = [make_axis(t.parameter(n)) for n in names]
    c = verdict_counts(t)
    fig = _figure(FAILURE_FIGSIZE)
    ax = fig.add_subplot()
    x = _run_positions(axes[0])
    if len(axes) > 1:
        y = _run_positions(axes[1])
    else:   # a strip: one row per verdict
        y = np.array([VERDICTS.index(str(v)) for v in t.verdict], dtype=np.float64)
    for verdict in VERDICTS:   # failures last, inside the ring of an ok run at their point
        color, marker, size = VERDICT_STYLE[verdict]
        sel = t.verdict == verdict
        style = ({"facecolors": "none", "edgecolors": color, "lw": 1.2} if verdict == "ok"
                 else {"c": color, "lw": 0, "alpha": 0.9})
        ax.scatter(x[sel], y[sel], s=size, marker=marker,
                   label=f"{verdict} ({getattr(c, verdict)})", **style)
    for axis, which in zip(axes, ("x", "y"), strict=False):
        if axis.numeric:
            if axis.log:
                (ax.set_xscale if which == "x" else ax.set_yscale)("log")
        else:
            _category_ticks(ax, axis, which)
            (ax.set_xlim if which == "x" else ax.set_ylim)(-0.6, axis.size - 0.4)
    ax.set_xlabel(names[0], fontsize=10)
    if len(axes) > 1:
        ax.set_ylabel(names[1], fontsize=10)
    else:
        ax.set_yticks(range(len(VERDICTS)), list(VERDICTS))
        ax.set_ylim(-0.6, len(VERDICTS) - 0.4)
        ax.set_ylabel("verdict", fontsize=10)
    ax.grid(True, lw=0.3)
    ax.legend(fontsize=9, loc="upper left", bbox_to_anchor=(1.01, 1.0), frameon=False,
              title="verdict (runs)", title_fontsize=9)
    if c.failed:
        head = f"failures: {c.crash} crash, {c.error} error of {c.total} runs"
    else:
        head = f"no failures: all {c.total} runs ok"
    ax.set_title(f"{head}\n{t.campaign}", fontsize=10)
    return _save(fig, Path(path))


# -- the page --------------------------------------------------------------------------------
@dataclass(frozen=True)
class ReportFigure:
    """A written figure and its caption, under a section heading of the page."""

    path: Path
    section: str
    caption: str


_STYLE = ("body{font-family:sans-serif;max-width:1200px;margin:1em auto;padding:0 1em}"
          "figure{display:inline-block;vertical-align:top;margin:0.5em;max-width:48%}"
          "img{max-width:100%;border:1px solid #ccc}figcaption{font-size:0.85em}"
          "pre{background:#f5f5f5;padding:0.8em;overflow-x:auto}"
          ".note{background:#fff3cd;padding:0.5em;border:1px solid #e0c060}")


def index_html(campaign: str, summary: str, figures: Sequence[ReportFigure],
               notes: Sequence[str] = ()) -> str:
    """A static page: the notes, every figure (relative links) with its caption, the summary."""
    e = html.escape
    out = ["<!DOCTYPE html>", '<html lang="en"><head><meta charset="utf-8">',
           f"<title>sweep report: {e(campaign)}</title><style>{_STYLE}</style></head><body>",
           f"<h1>sweep report: {e(campaign)}</h1>"]
    out += [f'<p class="note">{e(n)}</p>' for n in notes]
    section = None
    for f in figures:
        if f.section != section:
            section = f.section
            out.append(f"<h2>{e(section)}</h2>")
        out.append(f'<figure><a href="{quote(f.path.name)}"><img src="{quote(f.path.name)}" '
                   f'alt="{e(f.caption)}"></a><figcaption>{e(f.caption)}</figcaption></figure>')
    out += ["<h2>summary</h2>", f"<pre>{e(summary)}</pre>", "</body></html>"]
    return "\n".join(out) + "\n"


# -- the report ------------------------------------------------------------------------------
def write_report(table_path: Path, out_dir: Path,
                 metrics: Sequence[str] | None = None) -> list[Path]:
    """Every figure, ``summary.txt`` and ``index.html`` of the sweep table at ``table_path``
    into ``out_dir`` (created); returns the files written, figures first. ``metrics``: the
    metric columns to plot (default: :func:`default_metrics`)."""
    t = read_sweep(table_path)
    if not t.parameters:
        raise ReportError(f"{table_path}: the campaign swept no parameter (and ran one "
                          "scenario): there is nothing to plot against")
    chosen = resolve_metrics(t, metrics)
    counts = verdict_counts(t)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    notes: list[str] = []
    if counts.ok == 0:
        notes.append(f"every run failed ({counts.crash} crash, {counts.error} error): no metric "
                     "plots, see the failure map and the errors below")
    else:
        if not chosen:
            notes.append("none of the default metrics (all_pos_err_mean_mm, dist*_recovery_s) "
                         "was measured; choose some with --metric from: " + ", ".join(t.metrics))
        empty = [m for m in chosen if not np.isfinite(t.metric(m)[t.ok]).any()]
        notes += [f"no ok run measured {m}: not plotted" for m in empty]
        chosen = [m for m in chosen if m not in empty]
    if counts.ok == 0:
        chosen = []
    constant = [p.name for p in t.parameters if p.numeric and len(p.distinct()) < 2]
    numeric = [p.name for p in t.parameters if p.numeric and p.name not in constant]
    if chosen and len(numeric) < 2:
        notes.append("fewer than two numeric parameters vary: no heat maps")
    if constant:
        notes.append(f"one value only, left out of the heat maps: {', '.join(constant)}")

    figures: list[ReportFigure] = []
    used: set[str] = set()

    def target(*parts: str) -> Path:
        stem, k = file_stem(*parts), 1
        name = stem
        while name in used:
            k += 1
            name = f"{stem}-{k}"
        used.add(name)
        return out / f"{name}.png"

    used.add(Path(FAILURES_NAME).stem)
    c = counts
    figures.append(ReportFigure(
        plot_failures(t, out / FAILURES_NAME), "failures",
        f"every run by verdict over {' and '.join(failure_axes(t))}: ok {c.ok}, "
        f"crash {c.crash}, error {c.error}"))
    for m in chosen:
        section = metric_label(m)
        for p in t.parameters:
            path = plot_metric_vs_param(t, m, p.name, target(m, "vs", p.name))
            figures.append(ReportFigure(path, section, f"{section} vs {p.name}: dots are ok runs, "
                                  "the line their mean per value with the min-max band, red "
                                  "crosses at the top crash (x) and error (+) runs"))
        for p1, p2 in itertools.combinations(numeric, 2):
            path = plot_heat_map(t, m, p1, p2, target(m, "map", p1, p2))
            figures.append(ReportFigure(path, section, f"{section}, mean over seeds, {p1} (x) by "
                                  f"{p2} (y); hatched cells have no ok run that measured it"))
    summary = summary_text(t, chosen, notes)
    summary_path = out / SUMMARY_NAME
    summary_path.write_text(summary, encoding="utf-8")
    index_path = out / INDEX_NAME
    index_path.write_text(index_html(t.campaign, summary, figures, notes), encoding="utf-8")
    return [f.path for f in figures] + [summary_path, index_path]

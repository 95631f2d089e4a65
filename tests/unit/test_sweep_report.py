"""The sweep report: aggregation of a campaign's results table, its figures, summary and page."""

from __future__ import annotations

import itertools
import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from groundstation.sweep_report import (
    DPI,
    FAILURE_FIGSIZE,
    LINE_FIGSIZE,
    MAP_FIGSIZE,
    N_BINS,
    ReportError,
    default_metrics,
    extremes,
    failure_axes,
    file_stem,
    grid_means,
    grouped_texts,
    line_stats,
    metric_label,
    point_means,
    read_sweep,
    resolve_metrics,
    sweep_table,
    use_log_scale,
    verdict_counts,
    write_report,
)

KI, TILT = "vehicle.controller.ki_pos", "run.tilt_deg"
POS, REC = "all_pos_err_mean_mm", "dist0_recovery_s"
KI_VALUES, TILT_VALUES, SEEDS = (0.1, 0.2, 0.4, 0.8), (0, 15, 30), (1, 2)
SEED_OFFSET_MM = {1: -0.5, 2: 0.5}     # the seeds' mean is the known function
ERROR_AT = (0.8, 30, 2)                  # (ki, tilt, seed) of the run that raised
CRASH_AT = (0.4, 15, 1)                  # and of the one that crashed
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def pos_err_mm(ki: float, tilt: float) -> float:
    return 3.0 + 10.0 * ki + 0.1 * tilt


def recovery_s(ki: float, tilt: float) -> float:
    return 2.0 - ki + 0.01 * tilt


def _arrow(runs: Sequence[dict[str, Any]], parameters: dict[str, pa.DataType],
           metrics: Sequence[str], campaign: str = "gains", meta: bool = True) -> pa.Table:
    """A sweep table of ``runs`` (dicts of parameter and metric values, ``seed``, ``verdict``,
    optional ``scenario``, ``crash_reason``, ``error``), with the schema the sweep writes."""
    n = len(runs)
    cols: dict[str, pa.Array] = {
        "run_id": pa.array([f"r{i:04d}" for i in range(n)], pa.string()),
        "run_index": pa.array(range(n), pa.int64()),
        "campaign": pa.array([campaign] * n, pa.string()),
        "seed": pa.array([r["seed"] for r in runs], pa.int64()),
        "scenario": pa.array([r.get("scenario") for r in runs], pa.string()),
        "verdict": pa.array([r["verdict"] for r in runs], pa.string()),
        "crash_reason": pa.array([r.get("crash_reason") for r in runs], pa.string()),
        "error": pa.array([r.get("error") for r in runs], pa.string()),
        "fasthex_version": pa.array(["0.1.0"] * n, pa.string()),
        "wall_time_s": pa.array([1.5] * n, pa.float64()),
    }
    for name, typ in parameters.items():
        cols[name] = pa.array([r[name] for r in runs], typ)
    for m in metrics:
        cols[m] = pa.array([float(r.get(m, math.nan)) for r in runs], pa.float64())
    table = pa.table(cols)
    if not meta:
        return table
    info = {"campaign": campaign, "parameters": list(parameters), "metrics": list(metrics),
            "version": 1}
    return table.replace_schema_metadata({b"fasthex.sweep": json.dumps(info).encode()})


def grid_runs() -> list[dict[str, Any]]:
    """4 ki x 3 tilt x 2 seeds; one run raised and one crashed (its metric must not count)."""
    runs: list[dict[str, Any]] = []
    for tilt, ki, seed in itertools.product(TILT_VALUES, KI_VALUES, SEEDS):
        run: dict[str, Any] = {KI: ki, TILT: tilt, "seed": seed, "verdict": "ok",
                                  POS: pos_err_mm(ki, tilt) + SEED_OFFSET_MM[seed],
                                  REC: recovery_s(ki, tilt)}
        if (ki, tilt, seed) == ERROR_AT:
            run.update({"verdict": "error", POS: math.nan, REC: math.nan,
                        "error": "ValueError: gain out of range"})
        if (ki, tilt, seed) == CRASH_AT:
            run.update({"verdict": "crash", POS: 999.0, "crash_reason": "altitude below 0.05 m"})
        runs.append(run)
    return runs


GRID_PARAMS = {KI: pa.float64(), TILT: pa.int64()}
GRID_METRICS = (POS, "all_pos_err_max_mm", REC)


@pytest.fixture(scope="module")
def grid_table() -> pa.Table:
    return _arrow(grid_runs(), GRID_PARAMS, GRID_METRICS)


def _write(tmp: Path, table: pa.Table, name: str = "sweep.parquet") -> Path:
    path = tmp / name
    pq.write_table(table, path)
    return path


def _check_png(path: Path, figsize: tuple[float, float]) -> None:
    import matplotlib.image

    assert path.read_bytes()[:8] == PNG_MAGIC
    img = matplotlib.image.imread(path)
    assert img.shape[:2] == (round(figsize[1] * DPI), round(figsize[0] * DPI))
    assert img.shape[0] > 0 and img.shape[1] > 0


# -- aggregation -----------------------------------------------------------------------------
def test_that_the_grid_means_are_the_known_function_averaged_over_the_ok_seeds(
        grid_table: pa.Table) -> None:
    g = grid_means(grid_table, POS, KI, TILT)
    assert not g.x.binned and not g.y.binned
    assert g.x.labels == ("0.1", "0.2", "0.4", "0.8") and g.y.labels == ("0", "15", "30")
    assert g.mean.shape == (3, 4)
    for (j, tilt), (i, ki) in itertools.product(enumerate(TILT_VALUES), enumerate(KI_VALUES)):
        expected, count = pos_err_mm(ki, tilt), 2
        for ki_f, tilt_f, seed_f in (ERROR_AT, CRASH_AT):   # the other seed alone remains
            if (ki, tilt) == (ki_f, tilt_f):
                expected += SEED_OFFSET_MM[3 - seed_f]
                count = 1
        assert g.mean[j, i] == pytest.approx(expected), (ki, tilt)
        assert g.count[j, i] == count


def test_that_a_cell_without_an_ok_run_is_nan() -> None:
    runs = [r for r in grid_runs() if not (r[KI] == 0.2 and r[TILT] == 15)]
    runs += [{KI: 0.2, TILT: 15, "seed": s, "verdict": "crash", POS: 1.0} for s in SEEDS]
    g = grid_means(_arrow(runs, GRID_PARAMS, GRID_METRICS), POS, KI, TILT)
    assert math.isnan(g.mean[1, 1]) and g.count[1, 1] == 0
    assert np.isfinite(np.delete(g.mean.ravel(), 1 * 4 + 1)).all()


def test_that_line_stats_pool_seeds_and_the_other_parameter(grid_table: pa.Table) -> None:
    s = line_stats(grid_table, POS, KI)
    np.testing.assert_allclose(s.axis.centres, KI_VALUES)
    ok = [r for r in grid_runs() if r["verdict"] == "ok"]
    for i, ki in enumerate(KI_VALUES):
        ys = [float(r[POS]) for r in ok if r[KI] == ki]
        assert s.mean[i] == pytest.approx(np.mean(ys))
        assert (s.lo[i], s.hi[i], s.count[i]) == (min(ys), max(ys), len(ys))


def test_that_the_best_and_worst_points_are_the_known_extremes(grid_table: pa.Table) -> None:
    found = extremes(grid_table, POS)
    assert found is not None
    best, worst = found
    assert best.values == (0.1, 0.0) and best.mean == pytest.approx(pos_err_mm(0.1, 0))
    # (0.8, 30) has the largest function value; only its seed 1 (-0.5 mm) is left
    assert worst.values == (0.8, 30.0) and worst.mean == pytest.approx(pos_err_mm(0.8, 30) - 0.5)
    assert (worst.runs, worst.measured) == (2, 1)
    points = point_means(grid_table, POS)
    assert len(points) == 12 and all(p.runs == 2 for p in points)


def test_that_verdicts_and_texts_are_counted(grid_table: pa.Table) -> None:
    c = verdict_counts(grid_table)
    assert (c.ok, c.crash, c.error, c.total) == (22, 1, 1, 24)
    assert grouped_texts(grid_table, "error") == [("ValueError: gain out of range", 1)]
    assert grouped_texts(grid_table, "crash") == [("altitude below 0.05 m", 1)]


def test_that_a_random_sweep_is_binned_and_log_scaled_where_it_spans_decades() -> None:
    rng = np.random.default_rng(7)
    n = 80
    kp = 10.0 ** rng.uniform(0.0, 3.0, n)           # 1 .. 1000: three decades
    x = rng.uniform(0.0, 1.0, n)
    y = 10.0 * x + np.log10(kp)
    runs = [{"vehicle.kp": float(a), "run.x": float(b), "seed": i, "verdict": "ok", POS: float(v)}
            for i, (a, b, v) in enumerate(zip(kp, x, y, strict=True))]
    t = sweep_table(_arrow(runs, {"vehicle.kp": pa.float64(), "run.x": pa.float64()}, [POS]))
    g = grid_means(t, POS, "vehicle.kp", "run.x")
    assert g.x.binned and g.y.binned and g.mean.shape == (N_BINS, N_BINS)
    assert g.x.log and not g.y.log
    assert g.x.edges is not None and g.y.edges is not None
    np.testing.assert_allclose(g.x.edges, np.geomspace(kp.min(), kp.max(), N_BINS + 1))
    np.testing.assert_allclose(g.y.edges, np.linspace(x.min(), x.max(), N_BINS + 1))
    assert int(g.count.sum()) == n
    for j, i in itertools.product(range(N_BINS), range(N_BINS)):   # brute force, cell by cell
        xe, ye = g.x.edges, g.y.edges
        inside = ((kp >= xe[i]) & ((kp < xe[i + 1]) | (i == N_BINS - 1))
                  & (x >= ye[j]) & ((x < ye[j + 1]) | (j == N_BINS - 1)))
        if inside.any():
            assert g.mean[j, i] == pytest.approx(y[inside].mean())
        else:
            assert math.isnan(g.mean[j, i])
    s = line_stats(t, POS, "run.x")
    assert s.axis.binned and int(s.count.sum()) == n


def test_log_scale_rule() -> None:
    assert use_log_scale([0.01, 0.1, 1.0])
    assert not use_log_scale([1.0, 30.0])           # under 1.5 decades
    assert not use_log_scale([0.0, 10.0, 1000.0])   # not all positive
    assert not use_log_scale([5.0])
    assert use_log_scale([1.0, 10.0, 100.0, 1000.0])
    assert not use_log_scale(np.arange(1.0, 101.0))        # linear, though two decades
    assert not use_log_scale([0.004, *np.linspace(0.05, 1.0, 40)])   # a uniform sample


def test_labels_and_file_names() -> None:
    assert metric_label(POS) == "all pos err mean [mm]"
    assert metric_label("all_spin_saturated_frac") == "all spin saturated [fraction]"
    assert metric_label(REC) == "dist0 recovery [s]"
    assert metric_label("sim_s_per_wall_s") == "sim per wall [s/s]"
    name = file_stem(POS, "vs", "scenario.disturbances.0.force_n.1")
    assert name == "all_pos_err_mean_mm-vs-scenario.disturbances.0.force_n.1"
    assert file_stem("a/b c", "[1, 2]") == "a_b_c-1_2"


def test_metric_choice(grid_table: pa.Table) -> None:
    assert default_metrics(grid_table) == [POS, REC]
    assert resolve_metrics(grid_table, None) == [POS, REC]
    assert resolve_metrics(grid_table, ["all_pos_err_max_mm"]) == ["all_pos_err_max_mm"]
    with pytest.raises(ReportError, match="available numeric metrics") as exc:
        resolve_metrics(grid_table, ["all_pos_err_median_mm"])
    for name in (*GRID_METRICS, "wall_time_s"):
        assert name in str(exc.value)


# -- reading ---------------------------------------------------------------------------------
def test_that_files_that_are_not_sweep_tables_are_refused(tmp_path: Path,
                                                          grid_table: pa.Table) -> None:
    with pytest.raises(ReportError, match="no such file"):
        read_sweep(tmp_path / "missing.parquet")
    plain = _write(tmp_path, _arrow(grid_runs(), GRID_PARAMS, GRID_METRICS, meta=False), "p.pq")
    with pytest.raises(ReportError, match="not a sweep table"):
        write_report(plain, tmp_path / "out")
    text = tmp_path / "notes.parquet"
    text.write_text("hello")
    with pytest.raises(ReportError, match="not a readable Parquet file"):
        read_sweep(text)
    bad = grid_table.replace_schema_metadata({b"fasthex.sweep": json.dumps(
        {"campaign": "x", "parameters": [KI, "run.missing"], "metrics": [], "version": 1})})
    with pytest.raises(ReportError, match=r"missing column\(s\) run\.missing"):
        sweep_table(bad)
    assert not (tmp_path / "out").exists()


def test_that_a_table_without_parameters_is_refused(tmp_path: Path) -> None:
    runs = [{"seed": s, "verdict": "ok", POS: 1.0} for s in range(3)]
    path = _write(tmp_path, _arrow(runs, {}, [POS]))
    with pytest.raises(ReportError, match="no parameter"):
        write_report(path, tmp_path / "out")


def test_that_an_unknown_metric_names_the_available_ones(tmp_path: Path,
                                                         grid_table: pa.Table) -> None:
    path = _write(tmp_path, grid_table)
    with pytest.raises(ReportError, match="all_pos_err_max_mm") as exc:
        write_report(path, tmp_path / "out", metrics=["pos_err"])
    assert "pos_err" in str(exc.value) and REC in str(exc.value)


# -- the report ------------------------------------------------------------------------------
def test_the_report_of_a_grid_sweep(tmp_path: Path, grid_table: pa.Table) -> None:
    out = tmp_path / "report"
    files = write_report(_write(tmp_path, grid_table), out)
    names = [f.name for f in files]
    assert names == [
        "failures.png",
        f"{POS}-vs-{KI}.png", f"{POS}-vs-{TILT}.png", f"{POS}-map-{KI}-{TILT}.png",
        f"{REC}-vs-{KI}.png", f"{REC}-vs-{TILT}.png", f"{REC}-map-{KI}-{TILT}.png",
        "summary.txt", "index.html"]
    assert all(f.parent == out and f.is_file() for f in files)
    sizes = {"failures.png": FAILURE_FIGSIZE}
    for f in files[:-2]:
        _check_png(f, sizes.get(f.name, MAP_FIGSIZE if "-map-" in f.name else LINE_FIGSIZE))

    summary = (out / "summary.txt").read_text()
    assert "campaign: gains" in summary
    assert "runs: 24 (ok 22, crash 1, error 1)" in summary
    assert f"best (lowest): 4 mm at {KI}=0.1, {TILT}=0 (2 of 2 run(s) measured)" in summary
    assert f"worst (highest): 13.5 mm at {KI}=0.8, {TILT}=30 (1 of 2" in summary
    # dist0 recovery: best at the largest ki and no tilt
    assert f"best (lowest): 1.2 s at {KI}=0.8, {TILT}=0" in summary
    assert "1 x ValueError: gain out of range" in summary
    assert "1 x altitude below 0.05 m" in summary

    page = (out / "index.html").read_text()
    for f in files[:-2]:
        assert f'<img src="{f.name}"' in page
    assert "<script" not in page and "http" not in page
    assert "runs: 24 (ok 22, crash 1, error 1)" in page


def test_the_report_of_a_single_parameter_and_chosen_metrics(tmp_path: Path) -> None:
    runs = [{"vehicle.mass_kg": m, "seed": s, "verdict": "ok", POS: 2.0 * m + s}
            for m, s in itertools.product((1.5, 2.0, 2.5), (0, 1))]
    files = write_report(_write(tmp_path, _arrow(runs, {"vehicle.mass_kg": pa.float64()},
                                                 [POS])),
                         tmp_path / "out", metrics=[POS, "wall_time_s"])
    assert [f.name for f in files] == [
        "failures.png", f"{POS}-vs-vehicle.mass_kg.png", "wall_time_s-vs-vehicle.mass_kg.png",
        "summary.txt", "index.html"]
    _check_png(files[0], FAILURE_FIGSIZE)
    summary = files[-2].read_text()
    assert "best (lowest): 3.5 mm at vehicle.mass_kg=1.5" in summary
    assert "no heat maps" in summary


def test_the_report_of_string_parameters_scenarios_and_a_constant(tmp_path: Path) -> None:
    runs = []
    for frame, scen, seed in itertools.product(('["x", "y"]', "plus"), ("hover", None), (0, 1)):
        bad = frame == "plus" and scen is None
        runs.append({"vehicle.frame": frame, "run.tilt_deg": 20.0, "seed": seed,
                     "scenario": scen, "verdict": "ok",
                     POS: math.nan if bad and seed == 0 else 5.0 + seed + 10.0 * bad})
    t = sweep_table(_arrow(runs, {"vehicle.frame": pa.string(), "run.tilt_deg": pa.float64()},
                           [POS]))
    assert [p.name for p in t.parameters] == ["vehicle.frame", "run.tilt_deg", "scenario"]
    s = line_stats(t, POS, "scenario")
    assert s.axis.labels == ("(none)", "hover")
    np.testing.assert_allclose(s.mean, [(5.0 + 6.0 + 16.0) / 3, 5.5])
    found = extremes(t, POS)
    assert found is not None and found[1].values == ("plus", 20.0, "(none)")
    assert failure_axes(t) == ["vehicle.frame", "scenario"]   # the constant one comes last
    files = write_report(_write(tmp_path, _arrow(runs, {"vehicle.frame": pa.string(),
                                                        "run.tilt_deg": pa.float64()}, [POS])),
                         tmp_path / "out")
    assert sorted(f.name for f in files if "-map-" in f.name) == []
    assert sum("-vs-" in f.name for f in files) == 3
    assert "one value only, left out of the heat maps: run.tilt_deg" in files[-2].read_text()


def test_the_report_when_every_run_failed(tmp_path: Path) -> None:
    runs = [{KI: ki, TILT: tilt, "seed": 0,
             "verdict": "error" if ki < 0.3 else "crash", POS: math.nan,
             "error": "RuntimeError: solver diverged" if ki < 0.3 else None,
             "crash_reason": "tilt limit" if ki >= 0.3 else None}
            for ki, tilt in itertools.product(KI_VALUES, TILT_VALUES)]
    files = write_report(_write(tmp_path, _arrow(runs, GRID_PARAMS, [POS])), tmp_path / "out")
    assert [f.name for f in files] == ["failures.png", "summary.txt", "index.html"]
    _check_png(files[0], FAILURE_FIGSIZE)
    summary = files[1].read_text()
    assert "runs: 12 (ok 0, crash 6, error 6)" in summary
    assert "every run failed (6 crash, 6 error)" in summary
    assert "6 x RuntimeError: solver diverged" in summary and "6 x tilt limit" in summary
    assert "every run failed" in files[2].read_text()

"""``fasthex sweep``: a campaign's runs on a process pool and on a Dask ``LocalCluster`` give the
serial table bit for bit; a run that raises or whose worker dies is a row; a killed sweep,
started again, flies only the missing runs.

The campaign: 16 runs of a 1.6 s hop (1 s take-off to 0.3 m, 0.6 s of measured hover) over
the position integral gain x the tilt x two seeds: short enough to fly many times.
"""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pyarrow.parquet as pq
import pytest

from groundstation.campaign import load_campaign
from groundstation.cli import main
from groundstation.sweep import (
    TIMING_COLUMNS,
    DaskRunner,
    ProcessPoolRunner,
    ResultsTable,
    SerialRunner,
    sweep,
)

HOP = """\
schema: fasthex.mission
version: 1
name: hop
start_pos_w_m: [0.0, 0.0, 0.1]
segments:
  - kind: takeoff
    duration_s: 1.0
    height_m: 0.3
    alpha: {kind: constant, value_deg: 0.0}
  - kind: hold
    duration_s: 0.6
  - kind: land
    duration_s: 3.0
"""

CAMPAIGN = """\
schema: fasthex.campaign
version: 1
name: {name}
mission: hop.yaml
preset: paper-calibrated
duration_s: 1.6
parameters:
  - path: vehicle.controller.ki_pos
    values: {gains}
  - path: run.tilt_deg
    values: [0.0, 30.0]
seeds: {seeds}
"""


def write_campaign(tmp_path: Path, name: str = "pool", seeds: str = "[0, 1]",
                   gains: str = "[10.0, 20.0, 30.0, 40.0]") -> Path:
    (tmp_path / "hop.yaml").write_text(HOP)
    path = tmp_path / f"{name}.yaml"
    path.write_text(CAMPAIGN.format(name=name, seeds=seeds, gains=gains))
    return path


def by_run(table_path: Path) -> dict[str, dict[str, Any]]:
    rows = pq.read_table(table_path).to_pylist()
    return {r["run_id"]: {k: v for k, v in r.items() if k not in TIMING_COLUMNS} for r in rows}


def same_bits(a: dict[str, Any], b: dict[str, Any]) -> bool:
    """Equal cell by cell, floats by their bits (NaN equal to NaN)."""
    if a.keys() != b.keys():
        return False
    for k in a:
        x, y = a[k], b[k]
        if isinstance(x, float) and isinstance(y, float):
            if x.hex() != y.hex() and not (math.isnan(x) and math.isnan(y)):
                return False
        elif x != y:
            return False
    return True


@pytest.fixture(scope="module")
def serial_table(tmp_path_factory: pytest.TempPathFactory) -> dict[str, dict[str, Any]]:
    tmp = tmp_path_factory.mktemp("serial")
    campaign = load_campaign(write_campaign(tmp))
    table = ResultsTable(tmp / "serial.parquet", {"campaign": campaign.name,
                                                  "parameters": campaign.parameter_names()})
    flown, skipped = sweep(list(campaign.runs()), table, SerialRunner())
    assert (flown, skipped) == (16, 0)
    return by_run(tmp / "serial.parquet")


def test_that_the_serial_table_has_a_row_per_run_with_parameters_and_metrics(
        serial_table: dict[str, dict[str, Any]]) -> None:
    rows = sorted(serial_table.values(), key=lambda r: r["run_index"])
    # Assert: 4 gains x 2 tilts x 2 seeds, in campaign order, every flight ok
    assert [r["run_index"] for r in rows] == list(range(16))
    assert [r["seed"] for r in rows[:4]] == [0, 1, 0, 1]
    assert [r["vehicle.controller.ki_pos"] for r in rows[::4]] == [10.0, 20.0, 30.0, 40.0]
    assert all(r["verdict"] == "ok" and r["error"] is None for r in rows)
    # 1.6 s at 500 Hz, the hover measured (300 ticks), tracked within the noise floor
    assert all(r["sim_time_s"] == pytest.approx(1.6, abs=0.002) for r in rows)
    assert all(r["all_ticks"] == 300 for r in rows)
    assert all(0.0 < r["all_pos_err_mean_mm"] < 30.0 for r in rows)
    assert all(r["vehicle"] == "fasthex" and r["mission"] == "hop" for r in rows)
    # the two seeds fly different noise; every run is its own
    assert rows[0]["all_pos_err_mean_mm"] != rows[1]["all_pos_err_mean_mm"]
    assert len({r["run_id"] for r in rows}) == 16


def test_that_a_dask_local_cluster_with_two_workers_gives_the_serial_table_bit_for_bit(
        tmp_path: Path, serial_table: dict[str, dict[str, Any]]) -> None:
    # Fixture
    campaign = load_campaign(write_campaign(tmp_path))
    table = ResultsTable(tmp_path / "dask.parquet", {"campaign": campaign.name,
                                                     "parameters": campaign.parameter_names()})
    # Test
    runner = DaskRunner("local", 2)
    assert runner.description == "Dask LocalCluster, 2 worker processes"
    flown, _ = sweep(list(campaign.runs()), table, runner)
    # Assert
    assert flown == 16
    rows = by_run(tmp_path / "dask.parquet")
    assert rows.keys() == serial_table.keys()
    different = [rid for rid in rows if not same_bits(rows[rid], serial_table[rid])]
    assert different == []


def test_that_a_dead_worker_costs_exactly_its_run_and_the_campaign_completes(
        tmp_path: Path, serial_table: dict[str, dict[str, Any]]) -> None:
    # Fixture: seed 13 kills the worker process flying it (os._exit): 4 of the 12 runs
    from process_targets import run_or_die

    campaign = load_campaign(write_campaign(tmp_path, seeds="[0, 13, 1]", gains="[10.0, 20.0]"))
    table = ResultsTable(tmp_path / "pool.parquet", {"campaign": campaign.name,
                                                     "parameters": campaign.parameter_names()})
    # Test
    flown, _ = sweep(list(campaign.runs()), table, ProcessPoolRunner(2, run_or_die))
    # Assert: every run has its row; the dead ones say why, the others are the serial rows
    rows = by_run(tmp_path / "pool.parquet")
    assert flown == len(rows) == 12
    dead = [r for r in rows.values() if r["seed"] == 13]
    assert len(dead) == 4
    assert all(r["verdict"] == "error" for r in dead)
    assert all("worker process died" in r["error"] and "exit code 9" in r["error"]
               for r in dead)
    alive = {rid: r for rid, r in rows.items() if r["seed"] != 13}
    assert len(alive) == 8 and alive.keys() <= serial_table.keys()
    for rid, row in alive.items():  # the same flights (their place in the campaign moved)
        assert same_bits(row | {"run_index": 0}, serial_table[rid] | {"run_index": 0})


def test_that_a_run_that_raises_is_a_row_with_the_error(tmp_path: Path) -> None:
    # Fixture: a CSV trajectory that leaves the shared disk after the campaign was checked
    # (one of the two files the parameter chooses between)
    import shutil

    from config import config_root

    mission_dir = tmp_path / "missions"
    mission_dir.mkdir()
    shutil.copy(config_root() / "missions" / "demo-trajectory.csv", mission_dir / "a.csv")
    shutil.copy(config_root() / "missions" / "demo-trajectory.csv", mission_dir / "b.csv")
    mission = (config_root() / "missions" / "demo-trajectory.yaml").read_text()
    (mission_dir / "traj.yaml").write_text(mission.replace("demo-trajectory.csv", "a.csv"))
    (tmp_path / "c.yaml").write_text("""\
schema: fasthex.campaign
version: 1
name: vanishing
mission: missions/traj.yaml
preset: ideal
duration_s: 1.0
parameters:
  - path: mission.segments.2.file
    values: [a.csv, b.csv]
""")
    campaign = load_campaign(tmp_path / "c.yaml")
    runs = list(campaign.runs())
    (mission_dir / "b.csv").unlink()
    table = ResultsTable(tmp_path / "t.parquet", {"campaign": campaign.name,
                                                  "parameters": campaign.parameter_names()})
    # Test
    sweep(runs, table, SerialRunner())
    # Assert
    rows = sorted(by_run(tmp_path / "t.parquet").values(), key=lambda r: r["run_index"])
    assert [r["verdict"] for r in rows] == ["ok", "error"]
    assert "b.csv" in rows[1]["error"] and rows[1]["error"].startswith("ConfigError")
    assert math.isnan(rows[1]["sim_time_s"])


def test_that_a_point_outside_a_fields_range_is_a_row_not_a_crashed_campaign(
        tmp_path: Path) -> None:
    (tmp_path / "c.yaml").write_text("""\
schema: fasthex.campaign
version: 1
name: bad-point
mission: gust-hover
preset: ideal
duration_s: 0.5
parameters:
  - path: vehicle.controller.kp_pos.1
    values: [50.0, -5.0]
""")
    out = tmp_path / "t.parquet"
    assert main(["sweep", str(tmp_path / "c.yaml"), "--workers", "1", "--out", str(out)]) == 0
    rows = sorted(by_run(out).values(), key=lambda r: r["run_index"])
    assert rows[0]["verdict"] == "ok"
    assert rows[1]["verdict"] == "error"
    assert "vehicle.controller.kp_pos.1=-5.0" in rows[1]["error"]
    assert "controller.kp_pos[1]" in rows[1]["error"] and "> 0" in rows[1]["error"]


def test_that_a_killed_sweep_started_again_flies_only_the_missing_runs(
        tmp_path: Path, serial_table: dict[str, dict[str, Any]]) -> None:
    # Fixture
    path = write_campaign(tmp_path)
    out = tmp_path / "killed.parquet"
    parts = out.with_name(out.name + ".parts")
    # each row journaled as it arrives (--flush-s 0): the whole campaign flies in about a second
    # here, less than the default 2 s journal interval, so the kill must come after one row
    cmd = [sys.executable, "-m", "groundstation", "sweep", str(path), "--workers", "2",
           "--out", str(out), "--flush-s", "0"]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            start_new_session=True)
    # Test: SIGKILL to its whole process group once some rows are on disk
    deadline = time.monotonic() + 120.0
    while not (parts.is_dir() and any(parts.glob("part-*.parquet"))):
        assert proc.poll() is None, proc.stderr.read().decode() if proc.stderr else ""
        assert time.monotonic() < deadline
        time.sleep(0.005)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait(timeout=30)
    part_rows = [pq.read_table(p).to_pylist() for p in parts.glob("part-*.parquet")]
    assert all(len(rows) == 1 for rows in part_rows)  # one part per row with --flush-s 0
    saved = {str(r["run_id"]) for rows in part_rows for r in rows}
    assert 0 < len(saved) < 16
    campaign = load_campaign(path)
    table = ResultsTable(out, {"campaign": campaign.name,
                               "parameters": campaign.parameter_names()})
    flown_ids: list[str] = []
    flown, skipped = sweep(list(campaign.runs()), table, SerialRunner(),
                           on_row=lambda row: flown_ids.append(row["run_id"]))
    # Assert: only the runs not saved flew, and the table is the serial one
    assert skipped == len(saved) and flown == 16 - len(saved)
    assert set(flown_ids).isdisjoint(saved)
    assert not parts.exists()
    rows = by_run(out)
    assert rows.keys() == serial_table.keys()
    assert all(same_bits(rows[rid], serial_table[rid]) for rid in rows)

"""The dashboard end to end: a short lockstep flight through the real byte path, its rows pushed
through the shared-memory telemetry ring into a separate dashboard process saving a ``.rrd``,
read back with rerun's own reader; ``fasthex replay`` of the same record; the ``off`` mode."""

from __future__ import annotations

import multiprocessing as mp
import re
import subprocess
import sys
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import rerun as rr  # a required dependency: a broken install fails, never skips

from config import find_config
from groundstation.dashboard import PANEL_ENTITIES, SCALAR_SERIES, drain_into_dashboard
from groundstation.record import RECORD_DTYPE, FlightRecord, read_record
from groundstation.telemetry import TelemetryRing

SHORT_MISSION = """\
schema: fasthex.mission
version: 1
name: short-tilt-step
description: a short hover through one tilt step, for the dashboard tests
start_pos_w_m: [0.0, 0.0, 0.1]
segments:
  - kind: takeoff
    duration_s: 2.0
    height_m: 0.6
    alpha: {kind: constant, value_deg: 0.0}
  - kind: hold
    duration_s: 4.0
    alpha:
      kind: steps
      times_s: [0.0, 1.0]
      values_deg: [0.0, 25.0]
  - kind: land
    duration_s: 3.5
    alpha: {kind: constant, value_deg: 0.0}
"""


def _cli(*args: str, timeout_s: float = 300.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "groundstation", *args], capture_output=True,
                          text=True, timeout=timeout_s, check=False)


@pytest.fixture(scope="module")
def flight(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, FlightRecord]:
    """A short lockstep flight of the shipped Exp. 1 session with the short mission."""
    d = tmp_path_factory.mktemp("flight")
    (d / "short.yaml").write_text(SHORT_MISSION)
    shipped = Path(find_config("sessions", "exp1-emulated")).read_text()
    session = re.sub(r"(?m)^mission: .*$", "mission: short.yaml", shipped)
    session = re.sub(r"(?m)^(\s*)clock: \w+", r"\1clock: lockstep", session)
    (d / "session.yaml").write_text(session)
    record = d / "flight.fhr"
    res = _cli("fly", str(d / "session.yaml"), "--record", str(record), "--quiet")
    assert res.returncode == 0, res.stderr[-2000:]
    return record, read_record(record)


def _read_rrd(path: Path) -> tuple[dict[str, list[dict[str, Any]]], int]:
    """Rows per entity of the recording store, and the number of blueprint stores."""
    reader = rr.chunk.RrdReader(path)
    rows: dict[str, list[dict[str, Any]]] = defaultdict(list)
    for chunk in reader.stream().to_chunks():
        if not chunk.is_static:  # static rows are styling and geometry, not data
            rows[chunk.entity_path] += chunk.to_record_batch().to_pylist()
    return rows, len(reader.blueprints())


def _sorted_scalars(rows: list[dict[str, Any]]) -> tuple[np.ndarray, np.ndarray]:
    rows = sorted(rows, key=lambda r: r["tick"])
    return (np.array([r["tick"] for r in rows]),
            np.array([r["Scalars:scalars"] for r in rows], dtype=float))


def test_that_a_lockstep_flight_through_the_ring_fills_every_dashboard_panel(
        flight: tuple[Path, FlightRecord], tmp_path: Path) -> None:
    record_path, record = flight
    rows = record.rows
    events_lines = (record_path.with_name(record_path.name + ".events.txt")
                    .read_text().splitlines())
    assert len(rows) > 3000 and any("->" in line for line in events_lines)
    rrd = tmp_path / "flight.rrd"
    ctx = mp.get_context("spawn")
    ring = TelemetryRing(RECORD_DTYPE, 1 << 14)
    events = ctx.Queue()
    stop = ctx.Event()
    proc = ctx.Process(target=drain_into_dashboard, args=(
        ring.name, 1 << 14, {"mode": "save", "rrd_path": str(rrd),
                             "metadata": record.metadata}, events, stop, 0.05))
    proc.start()
    try:
        for line in events_lines:
            events.put(line)
        for row in rows:  # as the loop does: one row per tick
            assert ring.push(row)
        stop.set()
        proc.join(timeout=120)
        assert proc.exitcode == 0
    finally:
        if proc.is_alive():
            proc.kill()
            proc.join()
        dropped = ring.dropped
        ring.close()
    assert dropped == 0

    data, n_blueprints = _read_rrd(rrd)
    assert n_blueprints == 1  # the layout travels inside the .rrd
    n = len(rows)
    for entity in PANEL_ENTITIES:
        assert data.get(entity), f"{entity} has no data"
    for entity in SCALAR_SERIES:
        if entity != "/spin/limits":
            assert len(data[entity]) == n, entity
            ticks, values = _sorted_scalars(data[entity])
            np.testing.assert_array_equal(ticks, np.arange(n))
            assert values.shape[1] == len(SCALAR_SERIES[entity]), entity
    # values are the record's, in the panels' units
    _, pos = _sorted_scalars(data["/position/actual"])
    np.testing.assert_allclose(pos, rows["pos_w_m"], atol=1e-6)
    _, tilt = _sorted_scalars(data["/tilt"])
    np.testing.assert_allclose(tilt[:, 2], np.degrees(rows["alpha_rad"].astype(float)),
                               atol=1e-4)
    _, spin = _sorted_scalars(data["/spin/actual"])
    np.testing.assert_allclose(spin, rows["spin_hz"], atol=1e-4)
    _, state = _sorted_scalars(data["/actuation"])
    assert set(np.unique(state)) == {0.0, 1.0, 2.0}  # 0 -> 25 deg passes through all three
    # the 3-D view: poses at 100 Hz, six thrust arrows per sample along the tilted axes
    assert len(data["/world/vehicle"]) == (n + 4) // 5
    arrows = data["/world/vehicle/thrust"]
    assert all(len(a["Arrows3D:vectors"]) == 6 for a in arrows)
    # events: every transition of the flight and the actuation changes seen in the rows
    texts = [t for r in data["/events"] for t in r["TextLog:text"]]
    for line in events_lines:
        if " -> " in line and line[0].isdigit():
            assert line.split(" s ", 1)[1] in texts
    assert any(t.startswith("actuation UDT (under-actuated) -> fully actuated") for t in texts)
    assert any(t.startswith("flight: ") for t in texts)
    verify = subprocess.run([sys.executable, "-m", "rerun", "rrd", "verify", str(rrd)],
                            capture_output=True, text=True, timeout=120, check=False)
    assert verify.returncode == 0, verify.stderr


def test_that_replay_streams_a_record_and_its_events_into_an_rrd(
        flight: tuple[Path, FlightRecord], tmp_path: Path) -> None:
    record_path, record = flight
    out = tmp_path / "replay.rrd"
    res = _cli("replay", str(record_path), "--speed", "max", "--rerun", "save", "--out", str(out))
    assert res.returncode == 0, res.stderr
    assert f"replayed {len(record.rows)} rows" in res.stdout
    data, _ = _read_rrd(out)
    assert len(data["/tilt"]) == len(record.rows)
    texts = [t for r in data["/events"] for t in r["TextLog:text"]]
    assert "LANDING -> DISARMED: touchdown" in texts
    assert any(t.startswith("preflight PASS") for t in texts)


def test_that_replay_of_a_missing_record_is_a_user_error(tmp_path: Path) -> None:
    res = _cli("replay", str(tmp_path / "nope.fhr"), "--rerun", "off")
    assert res.returncode == 2
    assert "no such flight record" in res.stderr


def test_that_the_off_mode_never_imports_rerun(flight: tuple[Path, FlightRecord]) -> None:
    code = ("import sys\n"
            "from groundstation.dashboard import Dashboard\n"
            "from groundstation.record import read_record\n"
            f"rec = read_record({str(flight[0])!r})\n"
            "d = Dashboard('off')\n"
            "d.log_rows(rec.rows); d.log_event(1.0, 'x'); d.log_event_line('2.000 s y'); "
            "d.log_health(1.0, {'a': 1.0}); d.close()\n"
            "print(d.rows_logged, d.events_logged, 'rerun' in sys.modules)\n")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120, check=False)
    assert res.returncode == 0, res.stderr
    assert res.stdout.split() == [str(len(flight[1].rows)), "2", "False"]

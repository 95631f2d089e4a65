"""``fasthex report`` on a simulated Exp. 1 record: the figure is written and the metrics are
exactly the ones ``fasthex simulate --json`` printed for the same flight."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from groundstation.metrics import PHASES


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "groundstation", *args], capture_output=True,
                          text=True, timeout=300, check=False)


def test_that_report_of_a_simulated_exp1_writes_the_figure_and_the_simulate_metrics(
        tmp_path: Path) -> None:
    record = tmp_path / "exp1.fhr"
    # 30 s: takeoff, settling, 10 s at alpha 0 (UDT) and the step to 30 deg (MDT)
    sim = _cli("simulate", "exp1-hover-tilt-steps", "--duration", "30", "--log", str(record),
               "--json")
    assert sim.returncode == 0, sim.stderr
    printed = json.loads(sim.stdout)
    assert printed["udt_ticks"] > 0 and printed["mdt_ticks"] > 0

    out = tmp_path / "report"
    rep = _cli("report", str(record), "--out", str(out))
    assert rep.returncode == 0, rep.stderr
    figure = out / "plots.png"
    assert figure.stat().st_size > 50_000
    assert figure.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    metrics = json.loads((out / "metrics.json").read_text())
    metric_keys = {k for k in printed if k.split("_", 1)[0] in PHASES}
    assert set(metrics) == metric_keys
    for key in metric_keys:  # the same rows and the same function: equal, not just close
        assert metrics[key] == printed[key], key
    md = (out / "metrics.md").read_text()
    assert f"| pos_err_mean_mm | {printed['all_pos_err_mean_mm']:.4g} |" in md


def test_that_report_defaults_its_folder_next_to_the_record(tmp_path: Path) -> None:
    record = tmp_path / "short.fhr"
    sim = _cli("simulate", "exp1-hover-tilt-steps", "--duration", "3", "--log", str(record))
    assert sim.returncode == 0, sim.stderr
    rep = _cli("report", str(record))
    assert rep.returncode == 0, rep.stderr
    folder = tmp_path / "short.fhr.report"
    assert {p.name for p in folder.iterdir()} == {"plots.png", "metrics.json", "metrics.md"}
    # nothing measured in 3 s (takeoff only): every phase is empty, written as null
    metrics = json.loads((folder / "metrics.json").read_text())
    assert metrics["all_ticks"] == 0.0
    assert metrics["all_pos_err_mean_mm"] is None


"""Runs per minute of one campaign on each executor of ``fasthex sweep``.

The campaign (default the shipped ``bench-hover``: 12 short hovers, 2 tilts x 3 position
integral gains x 2 seeds) is flown in the same process run by 1 worker (in this process, one
run after the other), 2 local worker processes and a Dask ``LocalCluster`` of 2 worker
processes, each into a table of its own. Printed for each: the runs, the wall time (from the
moment the runner is made to the last row: start-up included), runs per minute and its ratio
to the 1-worker figure of the same run (the baseline), the start-up cost (time to the first
row: processes, imports, the first flight), the rate after the first row and the time to
close. Then the check that the three tables are equal bit for bit, run by run, except the
timing columns (:data:`groundstation.sweep.TIMING_COLUMNS`); and the load average.

Run: ``python benchmarks/bench_sweep.py [CAMPAIGN]``.
"""

from __future__ import annotations

import math
import os
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from config import find_config
from groundstation.campaign import Campaign, load_campaign
from groundstation.sweep import (
    TIMING_COLUMNS,
    DaskRunner,
    ProcessPoolRunner,
    ResultsTable,
    Runner,
    SerialRunner,
    read_rows,
    sweep,
)


@dataclass(frozen=True)
class Timing:
    label: str
    runs: int
    wall_s: float  # runner made -> last row
    first_row_s: float
    close_s: float

    @property
    def runs_per_min(self) -> float:
        return 60.0 * self.runs / self.wall_s

    @property
    def after_first_per_min(self) -> float:
        """The rate once the first row is in (start-up left out)."""
        span = self.wall_s - self.first_row_s
        return 60.0 * (self.runs - 1) / span if self.runs > 1 and span > 0 else math.nan


def fly(label: str, campaign: Campaign, make: Callable[[], Runner], out: Path) -> Timing:
    """Fly every run of ``campaign`` on the runner ``make()`` builds, into ``out``."""
    runs = list(campaign.runs())
    table = ResultsTable(out, {"campaign": campaign.name,
                               "parameters": campaign.parameter_names()})
    rows_at: list[float] = []
    t0 = time.perf_counter()
    runner = make()
    sweep(runs, table, runner, on_row=lambda row: rows_at.append(time.perf_counter()))
    t_end = time.perf_counter()
    assert len(rows_at) == len(runs), f"{label}: {len(rows_at)} rows for {len(runs)} runs"
    return Timing(label, len(runs), rows_at[-1] - t0, rows_at[0] - t0, t_end - rows_at[-1])


def bits(value: Any) -> Any:
    """A cell as compared: a float by its bits (every NaN alike), anything else as it is."""
    if isinstance(value, float):
        return "nan" if math.isnan(value) else value.hex()
    return value


def table_by_run(path: Path) -> dict[str, dict[str, Any]]:
    return {str(row["run_id"]): {k: bits(v) for k, v in row.items() if k not in TIMING_COLUMNS}
            for row in read_rows(path)}


def differences(base: dict[str, dict[str, Any]], other: dict[str, dict[str, Any]]) -> list[str]:
    """What differs between two tables (empty when equal bit for bit, timing aside)."""
    out = [f"run {rid} only in one table" for rid in sorted(base.keys() ^ other.keys())]
    for rid in sorted(base.keys() & other.keys()):
        a, b = base[rid], other[rid]
        out += [f"run {rid}: {k}: {a.get(k)!r} != {b.get(k)!r}"
                for k in sorted(a.keys() | b.keys()) if a.get(k) != b.get(k)]
    return out


def main(argv: list[str]) -> int:
    name = argv[0] if argv else "bench-hover"
    campaign = load_campaign(find_config("campaigns", name))
    print(f"campaign {campaign.name}: {campaign.n_runs()} runs; {os.cpu_count()} cores")
    with tempfile.TemporaryDirectory(prefix="bench-sweep-") as tmp:
        folder = Path(tmp)
        executors: list[tuple[str, Callable[[], Runner]]] = [
            ("1 worker (serial)", SerialRunner),
            ("2 local workers", lambda: ProcessPoolRunner(2)),
            ("Dask LocalCluster, 2", lambda: DaskRunner("local", 2)),
        ]
        timings, tables = [], []
        for i, (label, make) in enumerate(executors):
            out = folder / f"t{i}.parquet"
            timings.append(fly(label, campaign, make, out))
            tables.append(table_by_run(out))
    base = timings[0].runs_per_min
    print(f"\n{'executor':<22} {'runs':>4} {'wall s':>7} {'runs/min':>9} {'x 1 worker':>10} "
          f"{'1st row s':>9} {'after 1st /min':>14} {'close s':>7}")
    for t in timings:
        print(f"{t.label:<22} {t.runs:>4} {t.wall_s:>7.2f} {t.runs_per_min:>9.1f} "
              f"{t.runs_per_min / base:>10.2f} {t.first_row_s:>9.2f} "
              f"{t.after_first_per_min:>14.1f} {t.close_s:>7.2f}")
    ok = True
    for t, table in zip(timings[1:], tables[1:], strict=True):
        diff = differences(tables[0], table)
        ok = ok and not diff
        print(f"\n{t.label} vs 1 worker: " + (
            f"{len(table)} runs equal bit for bit (except {', '.join(TIMING_COLUMNS)})"
            if not diff else f"{len(diff)} differences:\n  " + "\n  ".join(diff[:20])))
    load = ", ".join(f"{x:.2f}" for x in os.getloadavg())
    print(f"\nload average (1, 5, 15 min): {load}")
    return 0 if ok else 1


if __name__ == "__main__":  # the Dask workers are spawned: they import this module too
    sys.exit(main(sys.argv[1:]))

"""Cost of the live dashboard, and proof that it stays out of the 500 Hz loop.

Prints medians and p99 (microseconds) of:

1. per row, in the loop's process: the telemetry ring push (the baseline: what the loop pays)
   vs logging the same row to rerun directly (one ``Dashboard.log_rows`` of one row, i.e. every
   panel's ``send_columns``; and the cheapest direct form, ``set_time`` + one ``log`` of 30
   scalars), with the ratio against the push;
2. the telemetry process: ``ring.drain()`` + ``Dashboard.log_rows`` (``.rrd`` sink) of one
   100 ms block (50 rows), as rows per second and as the share of one core at 500 Hz;
3. the flight loop with the dashboard on vs off in the same run: the in-process closed loop
   (simulator + controller) pushing its rows into the ring, drained by a separate process that
   either feeds the dashboard (on) or discards them (off). Runs alternate off/on/off/on.
   The loop is paced at 500 Hz by the wall clock; printed: compute per tick p50/p99 (from
   the wake-up to the row), the ring push, and deadline misses (a row > one period late).

Run: ``python benchmarks/bench_dashboard.py [--seconds 10]``.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from groundstation.dashboard import Dashboard, drain_into_dashboard
from groundstation.record import RECORD_DTYPE
from groundstation.telemetry import TelemetryRing

PERIOD_S = 0.002
CAPACITY = 1 << 14


def _stats(us: np.ndarray) -> str:
    return f"median {np.median(us):8.1f} us   p99 {np.percentile(us, 99):8.1f} us"


def _sample_rows(seconds: float) -> np.ndarray:
    from controller.missions import Mission
    from groundstation.configs import load_disturbances, load_mission, load_vehicle
    from groundstation.record import RecordWriter
    from sim_backend.closed_loop import fly_mission

    writer = RecordWriter(None)
    fly_mission(load_vehicle("fasthex"), Mission(load_mission("exp1-hover-tilt-steps")),
                load_disturbances("paper-calibrated"), sink=writer, duration_s=seconds)
    return writer.close().rows


def bench_per_row(rows: np.ndarray, tmp: Path) -> None:
    print("1. per-row cost in the loop's process")
    tuples = rows.tolist()
    ring = TelemetryRing(RECORD_DTYPE, CAPACITY)
    push = np.empty(len(tuples))
    for i, row in enumerate(tuples):
        if i % 1000 == 0:
            ring.drain()
        t0 = time.perf_counter()
        ring.push(row)
        push[i] = time.perf_counter() - t0
    ring.close()
    push_us = push * 1e6
    print(f"   ring push (baseline)              {_stats(push_us)}")

    import rerun as rr

    dash = Dashboard("save", tmp / "direct.rrd")
    n = min(len(rows), 2000)
    direct = np.empty(n)
    for i in range(n):
        t0 = time.perf_counter()
        dash.log_rows(rows[i:i + 1])
        direct[i] = time.perf_counter() - t0
    dash.close()
    rec = rr.RecordingStream("bench")
    rec.save(str(tmp / "scalars.rrd"))
    scal = np.empty(n)
    values = np.zeros(30)
    for i in range(n):
        t0 = time.perf_counter()
        rec.set_time("sim_time", duration=float(rows["t_s"][i]))
        values[:3] = rows["pos_w_m"][i]
        rec.log("/state", rr.Scalars(values))
        scal[i] = time.perf_counter() - t0
    rec.flush()
    base = float(np.median(push_us))
    for name, arr in (("direct: dashboard, 1 row", direct), ("direct: set_time + Scalars(30)",
                                                              scal)):
        us = arr * 1e6
        print(f"   {name:33s} {_stats(us)}   x{np.median(us) / base:6.0f} median, "
              f"x{np.percentile(us, 99) / np.percentile(push_us, 99):6.0f} p99 vs push")


def bench_drain(rows: np.ndarray, tmp: Path) -> None:
    print("2. telemetry process: drain + send_columns of 100 ms blocks (50 rows)")
    ring = TelemetryRing(RECORD_DTYPE, CAPACITY)
    reader = TelemetryRing(RECORD_DTYPE, CAPACITY, name=ring.name)
    dash = Dashboard("save", tmp / "drain.rrd")
    tuples = rows.tolist()
    block = 50
    times = []
    for start in range(0, len(tuples) - block + 1, block):
        for row in tuples[start:start + block]:
            ring.push(row)
        t0 = time.perf_counter()
        dash.log_rows(reader.drain())
        times.append(time.perf_counter() - t0)
    t0 = time.perf_counter()
    dash.close()
    close_s = time.perf_counter() - t0
    reader.close()
    ring.close()
    us = np.array(times) * 1e6
    rate = block / np.median(times)
    print(f"   per block                         {_stats(us)}")
    print(f"   throughput {rate:,.0f} rows/s (x{rate / 500:.0f} the 500 rows/s of a flight); "
          f"one core {100 * np.median(times) / (block * PERIOD_S):.1f} % at 500 Hz; "
          f"final flush {close_s * 1e3:.0f} ms; .rrd {(tmp / 'drain.rrd').stat().st_size / 1e6:.1f}"
          f" MB for {len(times) * block / 500:.0f} s")


class _TimedRingSink:
    """The loop's sink, paced to 500 Hz by the wall clock: pushes the row into the ring, then
    sleeps to the next tick. Records each tick's compute (from the end of the previous sleep
    to this row) and counts deadline misses (a row more than one period late)."""

    def __init__(self, ring: TelemetryRing, n: int) -> None:
        self.ring = ring
        self.compute_s = np.zeros(n + 1)
        self.push_s = np.zeros(n + 1)
        self.k = 0
        self.misses = 0
        self.t0 = self.tick_start = time.perf_counter()

    def append_flat(self, values: tuple[Any, ...]) -> None:
        now = time.perf_counter()
        self.ring.push_flat(values)
        done = time.perf_counter()
        if self.k < len(self.push_s):
            self.compute_s[self.k] = now - self.tick_start
            self.push_s[self.k] = done - now
        self.k += 1
        late = done - (self.t0 + self.k * PERIOD_S)
        if late > PERIOD_S:
            self.misses += 1
        elif late < 0:
            time.sleep(-late)
        self.tick_start = time.perf_counter()


def _flight(dashboard_on: bool, seconds: float, tmp: Path, i: int) -> tuple[
        np.ndarray, np.ndarray, int]:
    from controller.missions import Mission
    from groundstation.configs import load_disturbances, load_mission, load_vehicle
    from sim_backend.closed_loop import fly_mission

    ctx = mp.get_context("spawn")
    ring = TelemetryRing(RECORD_DTYPE, CAPACITY)
    stop = ctx.Event()
    events = ctx.Queue()
    args = {"mode": "save" if dashboard_on else "off",
            "rrd_path": str(tmp / f"flight{i}.rrd") if dashboard_on else None}
    proc = ctx.Process(target=drain_into_dashboard,
                       args=(ring.name, CAPACITY, args, events, stop, 0.1))
    proc.start()
    time.sleep(2.0)  # let the drain process import rerun before the flight starts
    sink = _TimedRingSink(ring, int(seconds / PERIOD_S))
    fly_mission(load_vehicle("fasthex"), Mission(load_mission("exp1-hover-tilt-steps")),
                load_disturbances("paper-calibrated"), sink=sink, duration_s=seconds)
    stop.set()
    proc.join(120)
    dropped = ring.dropped
    ring.close()
    k = min(sink.k, len(sink.compute_s))
    return sink.compute_s[1:k], sink.push_s[:k], sink.misses + dropped


def bench_loop(seconds: float, tmp: Path) -> None:
    print(f"3. closed loop paced at 500 Hz, {seconds:.0f} s of Exp. 1 per run, runs "
          "off/on/off/on, dashboard process on vs off")
    res: dict[bool, list[tuple[np.ndarray, np.ndarray, int]]] = {False: [], True: []}
    for i, on in enumerate((False, True, False, True)):
        res[on].append(_flight(on, seconds, tmp, i))
    p99 = {}
    for on in (False, True):
        comp = np.concatenate([r[0] for r in res[on]]) * 1e6
        push = np.concatenate([r[1] for r in res[on]]) * 1e6
        p99[on] = np.percentile(comp, 99)
        print(f"   dashboard {'on ' if on else 'off'}: tick compute {_stats(comp)}; "
              f"ring push {_stats(push)}; deadline misses + drops "
              f"{[r[2] for r in res[on]]} of {int(seconds / PERIOD_S)} ticks per run")
    print(f"   tick compute p99 ratio on/off: {p99[True] / p99[False]:.2f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=10.0, help="flight length per run")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        rows = _sample_rows(20.0)
        bench_per_row(rows, tmp)
        bench_drain(rows, tmp)
        bench_loop(args.seconds, tmp)


if __name__ == "__main__":
    main()

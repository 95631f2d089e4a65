"""Flight-loop timing through the full byte path on the emulated vehicle.

1. A real-time emulated flight (default 60 s in the air): ticks, deadline misses (> 2 ms of
   compute), period p50/p99 and jitter p99, compute p50/p99 and IMU-in -> `w`-out latency; run
   with and without ``--realtime-settings`` style scheduling (CPU pinning, SCHED_FIFO when
   permitted, frozen GC), which is reported.
2. The same mission in lockstep: simulated seconds per wall second (target >= 5x).

Baseline in the same run: the compute of the tick's pure numerics alone (UKF predict + controller
step, no I/O), so the byte path's share is visible. Targets (architecture.md): misses < 0.1 %,
compute p99 < 0.8 ms, IMU-in -> w-out median < 0.5 ms.

Run: ``python benchmarks/bench_flight.py [--hover-s 60] [--skip-realtime]``.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from controller.missions import Mission
from controller.pipeline import FlightComputer
from controller.reference import VehicleState
from estimator import EstimatorConfig, Ukf
from groundstation.configs import load_mission, load_vehicle
from groundstation.session import FlightSession, SessionOutcome
from groundstation.session_config import load_session

MISSION = """\
schema: fasthex.mission
version: 1
name: bench-hover
description: takeoff, hover with tilt steps, land
start_pos_w_m: [0.0, 0.0, 0.1]
segments:
  - kind: takeoff
    duration_s: 3.0
    height_m: 1.0
    alpha: {{kind: constant, value_deg: 0.0}}
  - kind: hold
    duration_s: {hover}
    alpha: {{kind: steps, times_s: [0.0, 10.0, 30.0], values_deg: [0.0, 30.0, 0.0]}}
  - kind: land
    duration_s: 4.0
    alpha: {{kind: constant, value_deg: 0.0}}
"""

SESSION = """\
schema: fasthex.session
version: 1
name: bench
vehicle: fasthex
mission: bench-hover.yaml
backend:
  kind: emulated
  clock: {clock}
  seed: 1
telemetry:
  rerun: "off"
"""


def fly(tmp: Path, clock: str, hover_s: float, realtime_settings: bool,
        dashboard: str = "off") -> SessionOutcome:
    (tmp / "bench-hover.yaml").write_text(MISSION.format(hover=hover_s))
    (tmp / f"{clock}.yaml").write_text(SESSION.format(clock=clock))
    cfg = load_session(tmp / f"{clock}.yaml")
    return FlightSession(cfg, load_vehicle("fasthex"),
                         Mission(load_mission(tmp / "bench-hover.yaml")),
                         record_path=tmp / f"{clock}.fhr", echo_events=False,
                         realtime_settings=realtime_settings, dashboard=dashboard).run()


def numerics_baseline(n: int = 5000) -> tuple[float, float]:
    """UKF predict + controller step on the hover state, no I/O (us): median, p99."""
    params = load_vehicle("fasthex")
    with tempfile.TemporaryDirectory() as d:
        (Path(d) / "m.yaml").write_text(MISSION.format(hover=10.0))
        computer = FlightComputer(params, Mission(load_mission(Path(d) / "m.yaml")))
    ukf = Ukf(replace(EstimatorConfig(), mass_kg=params.mass_kg))
    ukf.initialize(0.0, (0.0, 0.0, 1.0), (1.0, 0.0, 0.0, 0.0))
    state = VehicleState((0.0, 0.0, 1.0), (0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
    out = np.empty(n)
    for k in range(n):
        t = 0.002 * (k + 1)
        t0 = time.perf_counter_ns()
        ukf.predict(t, (0.0, 0.0, 0.0), (0.0, 0.0, 9.81))
        computer.step(5.0 + t, state, 0.0)
        out[k] = (time.perf_counter_ns() - t0) / 1e3
    return float(np.median(out)), float(np.percentile(out, 99))


def report(name: str, out: SessionOutcome) -> None:
    r, t = out.result, out.result.timing
    print(f"{name}: {r.ticks} ticks, {r.flight_time_s:.1f} s flight; session "
          f"{out.wall_time_s:.1f} s wall with start-up, loop {r.loop_wall_s:.1f} s wall "
          f"({(r.ticks / 500.0) / r.loop_wall_s:.2f} sim s per wall s); end: {r.end_reason}")
    print(f"  deadline misses {t.deadline_misses} ({100 * t.miss_fraction:.3f} %), period "
          f"p50 {t.period_p50_ms:.3f} p99 {t.period_p99_ms:.3f} ms, jitter p99 "
          f"{t.jitter_p99_ms:.3f} ms")
    print(f"  compute p50 {t.compute_p50_ms:.3f} ms, p99 {t.compute_p99_ms:.3f} ms, max "
          f"{t.compute_max_ms:.2f} ms; IMU-in -> w-out p50 {t.latency_p50_ms:.3f} ms, p99 "
          f"{t.latency_p99_ms:.3f} ms")
    if out.realtime_settings:
        print("  scheduling: " + "; ".join(f"{k}: {v}" for k, v in
                                            out.realtime_settings.items()))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--hover-s", type=float, default=53.0, help="hover time (flight = +7 s)")
    ap.add_argument("--skip-realtime", action="store_true")
    ap.add_argument("--dashboard", action="store_true",
                    help="also: realtime with the rerun dashboard saving, vs off (same run)")
    args = ap.parse_args()
    med, p99 = numerics_baseline()
    print(f"baseline, tick numerics alone (UKF predict + controller): median {med:.1f} us, "
          f"p99 {p99:.1f} us")
    with tempfile.TemporaryDirectory(prefix="fasthex-bench-") as d:
        tmp = Path(d)
        report("lockstep", fly(tmp, "lockstep", args.hover_s, False))
        if not args.skip_realtime:
            report("realtime, default scheduling", fly(tmp, "realtime", args.hover_s, False))
            report("realtime, --realtime-settings", fly(tmp, "realtime", args.hover_s, True))
        if args.dashboard:
            for rt in (False, True):
                tag = ", --realtime-settings" if rt else ""
                report(f"realtime{tag}, dashboard off", fly(tmp, "realtime", args.hover_s, rt))
                report(f"realtime{tag}, dashboard saving .rrd",
                       fly(tmp, "realtime", args.hover_s, rt, dashboard="save"))


if __name__ == "__main__":
    main()

"""Realtime emulated flights on a loaded machine: a busy loop on every core (normal priority),
while `fasthex fly` flies a session with its default real-time settings.

Prints, per flight: end reason, deadline misses, compute p50/p99, the longest IMU gap on the
host clock and the mean tracking error; first a baseline flight without the hog, in the same run.

    python benchmarks/bench_loaded_flight.py [--session exp1-emulated] [--runs 3]
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any


def _hog(stop_at: float) -> None:
    x = 0
    while time.monotonic() < stop_at:
        x += 1


def fly(session: str, record: Path, extra: list[str]) -> dict[str, Any]:
    out = subprocess.run([sys.executable, "-m", "groundstation", "fly", session, "--clock",
                          "realtime", "--json", "--rerun", "off", "--record", str(record),
                          *extra], capture_output=True, text=True, timeout=900, check=False)
    try:
        result: dict[str, Any] = json.loads(out.stdout)
    except json.JSONDecodeError:
        return {"end_reason": f"no summary (exit {out.returncode}): {out.stderr[-300:]}"}
    result["exit_code"] = out.returncode
    return result


def line(label: str, r: dict[str, Any]) -> str:
    if "ticks" not in r:
        return f"{label:10s} {r['end_reason']}"
    miss_pct = 100 * r["deadline_misses"] / max(r["ticks"], 1)
    return (f"{label:10s} {r['end_reason']:22s} exit {r['exit_code']}  ticks {r['ticks']:6d}  "
            f"misses {r['deadline_misses']:4d} ({miss_pct:.3f} %)"
            f"  compute p50 {r['compute_p50_ms']:.3f} / p99 {r['compute_p99_ms']:.3f} ms  "
            f"longest IMU gap {r.get('imu_gap_max_ms', float('nan')):6.1f} ms "
            f"(at {r.get('imu_gap_max_at_s', float('nan')):.1f} s)  "
            f"e_p mean {r.get('all_pos_err_mean_mm', float('nan')):.2f} mm")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--session", default="exp1-emulated")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--hogs", type=int, default=os.cpu_count() or 2)
    ap.add_argument("--no-realtime-settings", action="store_true")
    ap.add_argument("--keep", default=None, metavar="DIR",
                    help="keep the records and events of every flight in DIR")
    args = ap.parse_args()
    extra = ["--no-realtime-settings"] if args.no_realtime_settings else []
    with tempfile.TemporaryDirectory(prefix="bench-loaded-") as scratch:
        tmp = args.keep or scratch
        Path(tmp).mkdir(parents=True, exist_ok=True)
        base = fly(args.session, Path(tmp) / "baseline.fhr", extra)
        print(line("baseline", base), flush=True)
        ok = 0
        for i in range(args.runs):
            stop_at = time.monotonic() + 600.0
            hogs = [mp.Process(target=_hog, args=(stop_at,), daemon=True)
                    for _ in range(args.hogs)]
            for h in hogs:
                h.start()
            try:
                r = fly(args.session, Path(tmp) / f"loaded-{i}.fhr", extra)
            finally:
                for h in hogs:
                    h.terminate()
                    h.join()
            print(line(f"loaded {i + 1}", r), flush=True)
            if r.get("exit_code") != 0:
                for fault in r.get("faults", []):
                    print(f"           fault {fault}", flush=True)
            ok += r.get("exit_code") == 0  # the flight ended as planned
        print(f"{ok} of {args.runs} loaded flights completed their mission "
              f"({args.hogs} busy loops)")
    return 0 if ok == args.runs else 1


if __name__ == "__main__":
    sys.exit(main())

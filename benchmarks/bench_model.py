"""Cost of the vehicle-model computations that run outside the 500 Hz tick.

Prints median and p99 (microseconds) of: the 6x6 allocation F(alpha), the exact lateral-force
polygon radius (vertex enumeration), and, as the baseline measured in the same run, the same
radius from a 72-direction support-function LP. Run: ``python benchmarks/bench_model.py``.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable

import numpy as np

from controller.model import VehicleModel, inscribed_radius
from groundstation.configs import load_vehicle


def _time_us(fn: Callable[[], object], repeats: int) -> np.ndarray:
    out = np.empty(repeats)
    for i in range(repeats):
        t0 = time.perf_counter_ns()
        fn()
        out[i] = (time.perf_counter_ns() - t0) / 1e3
    return out


def main() -> None:
    model = VehicleModel(load_vehicle("fasthex"))
    alpha = math.radians(30.0)
    cases = {
        "allocation F(alpha)": (lambda: model.allocation(alpha), 5000),
        "lateral radius, exact polygon": (lambda: model.lateral_force_radius_n(alpha), 300),
        "lateral radius, LP baseline": (
            lambda: inscribed_radius(model._lateral_force_polygon_lp(alpha)), 20),
    }
    results = {}
    print(f"{'case':34} {'median_us':>10} {'p99_us':>10}")
    for name, (fn, repeats) in cases.items():
        fn()  # warm up
        t = _time_us(fn, repeats)
        results[name] = float(np.median(t))
        print(f"{name:34} {np.median(t):10.1f} {np.percentile(t, 99):10.1f}")
    ratio = results["lateral radius, LP baseline"] / results["lateral radius, exact polygon"]
    print(f"exact polygon is {ratio:.1f}x faster than the LP baseline (same run)")


if __name__ == "__main__":
    main()

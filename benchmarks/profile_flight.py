"""Where a lockstep tick's compute goes: one flight of the shipped Exp. 1 session (the byte
path, the emulated vehicle in its own process), profiled two ways.

- **By kind of tick**: each tick is classed by the work it carried (a MoCap frame decoded and
  fused, the pose's comparison with the IMU alone, a servo cycle, none of these: plain), with
  the share of ticks and the compute p50 and mean of each class. The compute p50 of the flight
  lies in whichever class holds its middle tick.
- **By function**: wall time inside the loop's parts (inclusive, nested parts counted in both),
  per tick and per call. Each wrapper adds ~0.3-1 us a call, so the figures run a little above
  an unwrapped flight's (the kind table is taken without them, on a flight of its own).

Run: ``python benchmarks/profile_flight.py [--rate-hz 500] [--skip-functions]``. Machines are
noisy (2 shared cores here): compare classes and parts within one run.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import collections
import importlib
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import bench_speed  # the shipped session as the speed table flies it

from groundstation.session import SessionOutcome

#: the parts timed by function: "module:Class" -> method names
PARTS: dict[str, tuple[str, ...]] = {
    "estimator.ukf:Ukf": ("predict", "update_pose", "output_state", "force_ext_w_n", "usable",
                          "checkpoint"),
    "estimator.consistency:ConsistencyMonitor": ("add_imu", "add_pose"),
    "controller.pipeline:FlightComputer": ("step", "thrust_force_b"),
    "drivers.mikrokopter.device:FlightCtrl": ("send_rotor_speeds_hz", "link_stats"),
    "drivers.mocap.natnet_client:NatNetClient": ("receive", "handle_received"),
    "drivers.dynamixel.device:TiltServo": ("begin_cycle", "finish_cycle", "set_tilt"),
    "groundstation.loop:FlightLoop": ("_push_row", "_health", "_take_pose", "_compare_with_imu",
                                      "_exchange_with_operators", "_status_line"),
    "groundstation.loop:_Extremes": ("add",),
    "groundstation.flight:FlightStateMachine": ("update",),
}
#: the first ticks (preflight, arming, take-off) left out of the kind table
SKIP_TICKS = 3000


def _patch(spec: str, name: str, wrapper: Callable[[Callable[..., Any]], Callable[..., Any]]
           ) -> Callable[[], None]:
    """Replace ``spec``'s method ``name`` by ``wrapper(original)``; returns the undo."""
    mod, cls_name = spec.split(":")
    cls = getattr(importlib.import_module(mod), cls_name)
    original = getattr(cls, name)
    setattr(cls, name, wrapper(original))
    return lambda: setattr(cls, name, original)


def fly(rate_hz: float) -> SessionOutcome:
    with tempfile.TemporaryDirectory(prefix="fasthex-profile-") as d:
        return bench_speed.fly(Path(d), "lockstep", rate_hz, None)


def by_kind(rate_hz: float) -> None:
    """The flight's ticks classed by the work they carried."""
    compute: list[int] = []
    kinds: list[frozenset[str]] = []
    carried: set[str] = set()

    def flagging(label: str, when: Callable[[Any], bool]
                 ) -> Callable[[Callable[..., Any]], Callable[..., Any]]:
        def wrapper(f: Callable[..., Any]) -> Callable[..., Any]:
            def w(*a: Any, **k: Any) -> Any:
                r = f(*a, **k)
                if when(r):
                    carried.add(label)
                return r
            return w
        return wrapper

    def recording(f: Callable[..., Any]) -> Callable[..., Any]:
        def w(self: Any, start_ns: int, end_ns: int, *rest: Any) -> Any:
            compute.append(end_ns - start_ns)
            kinds.append(frozenset(carried))
            carried.clear()
            return f(self, start_ns, end_ns, *rest)
        return w

    undo = [
        _patch("groundstation.timing:LoopTimer", "record", recording),
        _patch("drivers.mocap.natnet_client:NatNetClient", "handle_received",
               flagging("frame", lambda r: bool(r))),
        _patch("groundstation.loop:FlightLoop", "_compare_with_imu",
               flagging("comparison", lambda r: True)),
        _patch("drivers.dynamixel.device:TiltServo", "begin_cycle",
               flagging("servo", lambda r: True)),
    ]
    try:
        out = fly(rate_hz)
    finally:
        for u in undo:
            u()
    c = np.array(compute[SKIP_TICKS:]) / 1e3
    t = out.result.timing
    speed = out.result.ticks / rate_hz / out.result.loop_wall_s
    print(f"flight: {out.result.ticks} ticks, {speed:.1f}x real time; compute p50 "
          f"{t.compute_p50_ms * 1e3:.0f} us, mean {t.compute_mean_ms * 1e3:.0f} us; "
          "numerics (timed in the ticks) p50 "
          f"{t.numerics_p50_ms * 1e3:.0f} us, mean {t.numerics_mean_ms * 1e3:.0f} us")
    groups: dict[str, list[float]] = collections.defaultdict(list)
    for v, k in zip(c.tolist(), kinds[SKIP_TICKS:], strict=True):
        groups[" + ".join(sorted(k)) or "plain"].append(v)
    print("\n| tick carries | share of ticks | compute p50 (us) | mean (us) |\n|---|---|---|---|")
    for name, vals in sorted(groups.items(), key=lambda kv: -len(kv[1])):
        a = np.array(vals)
        print(f"| {name} | {100 * len(a) / len(c):.1f} % | {np.median(a):.0f} | {a.mean():.0f} |")


def by_function(rate_hz: float) -> None:
    """Inclusive wall time of each part, per tick and per call."""
    total: dict[str, int] = collections.defaultdict(int)
    calls: dict[str, int] = collections.defaultdict(int)
    clock = time.perf_counter_ns

    def timing(label: str) -> Callable[[Callable[..., Any]], Callable[..., Any]]:
        def wrapper(f: Callable[..., Any]) -> Callable[..., Any]:
            def w(*a: Any, **k: Any) -> Any:
                t0 = clock()
                try:
                    return f(*a, **k)
                finally:
                    total[label] += clock() - t0
                    calls[label] += 1
            return w
        return wrapper

    undo = [_patch(spec, name, timing(f"{spec.split(':')[1]}.{name}"))
            for spec, names in PARTS.items() for name in names]
    try:
        out = fly(rate_hz)
    finally:
        for u in undo:
            u()
    ticks = out.result.ticks
    print(f"\nby function (wrapped flight: compute p50 "
          f"{out.result.timing.compute_p50_ms * 1e3:.0f} us, mean "
          f"{out.result.timing.compute_mean_ms * 1e3:.0f} us)")
    print("| part | us per tick | us per call | calls |\n|---|---|---|---|")
    for label, ns in sorted(total.items(), key=lambda kv: -kv[1]):
        print(f"| {label} | {ns / ticks / 1e3:.1f} | {ns / calls[label] / 1e3:.1f} | "
              f"{calls[label]} |")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rate-hz", type=float, default=500.0, choices=(500.0, 1000.0))
    ap.add_argument("--skip-functions", action="store_true")
    args = ap.parse_args()
    by_kind(args.rate_hz)
    if not args.skip_functions:
        by_function(args.rate_hz)
    return 0


if __name__ == "__main__":
    sys.exit(main())

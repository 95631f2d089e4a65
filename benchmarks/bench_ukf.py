"""UKF cost per call: the fast path against stock filterpy, measured in the same run.

Both run the same :class:`estimator.Ukf` logic (history ring, gate, health, force observer) on
the same synthetic flight (the 3-D ``lively`` trajectory, paper-class sensors, 500 Hz IMU,
100 Hz MoCap); only the numeric kernel differs: ``fast`` is the default (the compiled numba
loops, whole predict and update steps in one call each, when numba is installed), ``numpy``
propagates all 31 sigma points as one numpy array (the fallback without numba), ``filterpy``
is the stock ``UnscentedKalmanFilter`` calling the process model once per sigma point. Every
``predict`` and ``update_pose`` call is timed with ``perf_counter_ns``; the estimates of each
fast path are compared with filterpy's tick by tick (they must agree to 1e-9).

Usage: ``python benchmarks/bench_ukf.py [--seconds 20] [--ref-seconds 4] [--latency-ms 10]``.
Three flights: poses captured on IMU ticks and delivered at once (``update_pose`` is a pure
update); poses captured between ticks and ``--latency-ms`` late, with the default fusion
horizon (the filter runs that far behind, ``predict`` includes the output predictor and
``update_pose`` fuses without replaying); the same late poses with ``max_fusion_delay_s = 0``
(the filter at the newest sample: ``update_pose`` replays the IMU samples since the capture).
Run with ``OPENBLAS_NUM_THREADS=1`` (set here by default): 15x15 matrices gain nothing from
BLAS threads and a second thread only competes for the cores.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import time
from dataclasses import dataclass

import numpy as np

from estimator import EstimatorConfig, Ukf
from estimator import synthetic as sy

TARGET_TICK_US = 40.0
TARGET_SPEEDUP = 20.0


@dataclass
class Timings:
    predict_ns: list[int]
    update_ns: list[int]
    states: list[np.ndarray]


def drive(est: Ukf, sc: sy.Scenario, n_ticks: int, keep_states: int) -> Timings:
    tr = sc.truth
    est.initialize(0.0, tr.pos_w_m[0], tr.q_wb[0], tr.vel_w_m_s[0])
    clock = time.perf_counter_ns
    predict_ns: list[int] = []
    update_ns: list[int] = []
    states: list[np.ndarray] = []
    frames = sc.frames
    nxt = 0
    for k in range(n_ticks):
        t = float(tr.t_s[k])
        gyro, accel, force = sc.gyro_rad_s[k], sc.accel_m_s2[k], sc.force_cmd_b_n[k]
        t0 = clock()
        est.predict(t, gyro, accel, force)
        predict_ns.append(clock() - t0)
        while nxt < len(frames) and frames[nxt].arrival_t_s <= t:
            f = frames[nxt]
            t0 = clock()
            est.update_pose(f.capture_t_s, f.pos_w_m, f.q_wb)
            update_ns.append(clock() - t0)
            nxt += 1
        if k < keep_states:
            e = est.estimate()
            states.append(np.concatenate([e.pos_w_m, e.vel_w_m_s, e.q_wb, e.gyro_bias_rad_s,
                                          e.accel_bias_m_s2, e.cov.ravel(), e.force_ext_w_n]))
    return Timings(predict_ns, update_ns, states)


def stats_us(samples: list[int], warmup: int) -> tuple[float, float]:
    arr = np.asarray(samples[warmup:], dtype=np.float64) / 1e3
    return float(np.median(arr)), float(np.percentile(arr, 99))


def scenario(seconds: float, latency_s: float, on_imu_ticks: bool) -> sy.Scenario:
    # on_imu_ticks with no latency: every pose is fused at the current state (a pure update);
    # otherwise the pose is fused at its capture time between two IMU samples (replay)
    phase = 0.02 if on_imu_ticks else None
    mocap = sy.MocapModel(pos_sigma_m=5e-4, att_sigma_deg=0.115, latency_min_s=latency_s,
                          latency_max_s=latency_s, capture_phase_s=phase)
    force = sy.ExternalForce(constant_w_n=(0.3, 0.0, 0.0), ou_sigma_n=0.3)
    return sy.make_scenario(sy.lively(), seconds, sy.PAPER_IMU, mocap, seed=1, force=force)


def compare(sc: sy.Scenario, seconds: float, ref_seconds: float, label: str,
            cfg: EstimatorConfig | None = None) -> tuple[dict[str, tuple[float, float]], float]:
    rate = sy.PAPER_IMU.rate_hz
    n_fast, n_ref = round(seconds * rate), round(ref_seconds * rate)
    cfg = cfg or EstimatorConfig()
    ref = drive(Ukf(cfg, kernel="filterpy"), sc, n_ref, keep_states=n_ref)
    t0 = time.perf_counter()
    fast_ukf = Ukf(cfg, kernel="fast")          # compiles (or loads the cache) here
    startup_s = time.perf_counter() - t0
    fast = drive(fast_ukf, sc, n_fast, keep_states=n_ref)
    numpy_path = drive(Ukf(cfg, kernel="numpy"), sc, n_fast, keep_states=n_ref)
    worst = max(float(np.max(np.abs(a - b))) for a, b in zip(fast.states, ref.states,
                                                                strict=True))
    worst = max(worst, max(float(np.max(np.abs(a - b)))
                           for a, b in zip(numpy_path.states, ref.states, strict=True)))
    rows = {}
    print(f"{label:<22} fast = {fast_ukf.kernel_name} kernel, constructed in "
          f"{startup_s * 1e3:.0f} ms (JIT or cache load, before any tick); first predict "
          f"{fast.predict_ns[0] / 1e3:.1f} us")
    for name, tm in (("filterpy", ref), ("numpy", numpy_path), ("fast", fast)):
        p_med, p_99 = stats_us(tm.predict_ns, 100)
        u_med, u_99 = stats_us(tm.update_ns, 20)
        tick = (sum(tm.predict_ns) + sum(tm.update_ns)) / len(tm.predict_ns) / 1e3
        rows[name] = (p_med, u_med)
        print(f"{label:<22} {name:<9} {len(tm.predict_ns):>6}/{len(tm.update_ns):<5} "
              f"{p_med:>8.1f} {p_99:>8.1f} {u_med:>8.1f} {u_99:>8.1f} {tick:>9.1f}")
    return rows, worst


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=20.0, help="flight for the fast path")
    parser.add_argument("--ref-seconds", type=float, default=4.0,
                        help="flight for the stock filterpy baseline (slow)")
    parser.add_argument("--latency-ms", type=float, default=10.0,
                        help="MoCap latency of the late flights")
    args = parser.parse_args()
    duration = max(args.seconds, args.ref_seconds)

    print("UKF cost per call (us), 15 error states, 31 sigma points, IMU 500 Hz, MoCap 100 Hz, "
          f"OPENBLAS_NUM_THREADS={os.environ['OPENBLAS_NUM_THREADS']}")
    print(f"{'flight':<22} {'kernel':<9} {'calls p/u':>12} {'pred med':>8} {'p99':>8} "
          f"{'upd med':>8} {'p99':>8} {'tick mean':>9}")
    pure, worst_pure = compare(scenario(duration, 0.0, True), args.seconds, args.ref_seconds,
                               "poses on IMU ticks")
    late_label = f"late {args.latency_ms:g} ms, horizon"
    late_sc = scenario(duration, args.latency_ms / 1e3, False)
    late, worst_late = compare(late_sc, args.seconds, args.ref_seconds, late_label)
    replay_label = f"late {args.latency_ms:g} ms, replay"
    replay, worst_replay = compare(late_sc, args.seconds, args.ref_seconds, replay_label,
                                   EstimatorConfig(max_fusion_delay_s=0.0))
    for label, rows in (("poses on IMU ticks", pure), (late_label, late),
                        (replay_label, replay)):
        fp, fu = rows["fast"]
        sp, su = rows["filterpy"]
        np_p, np_u = rows["numpy"]
        total_fast, total_ref = fp + fu, sp + su
        print(f"{label}: speed-up (stock / fast, medians) predict {sp / fp:.1f}x, update "
              f"{su / fu:.1f}x, predict+update {total_ref / total_fast:.1f}x; fast "
              f"predict+update {total_fast:.1f} us; numpy kernel {np_p + np_u:.1f} us "
              f"({(np_p + np_u) / total_fast:.1f}x the fast one)")
    fp, fu = pure["fast"]
    sp, su = pure["filterpy"]
    met = fp + fu < TARGET_TICK_US and (sp + su) / (fp + fu) >= TARGET_SPEEDUP
    print(f"target (pure predict + update median < {TARGET_TICK_US:.0f} us and >= "
          f"{TARGET_SPEEDUP:.0f}x the stock filterpy): {'met' if met else 'NOT met'}")
    (lp, lu), (rp, ru) = late["fast"], replay["fast"]
    print(f"late poses: the horizon costs {lp + lu:.1f} us per predict+update (medians) "
          f"against {rp + ru:.1f} us replaying (same run)")
    worst = max(worst_pure, worst_late, worst_replay)
    print(f"largest difference of the estimates, fast vs stock filterpy: {worst:.2e} "
          f"({'identical to 1e-9' if worst < 1e-9 else 'DIFFERENT'})")
    return 0 if worst < 1e-9 else 1


if __name__ == "__main__":
    raise SystemExit(main())

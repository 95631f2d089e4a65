"""The fusion horizon and output predictor against the replaying filter (same flights)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from estimator import EstimatorConfig, Ukf
from estimator import synthetic as sy
from estimator.quaternion import angle_between

DURATION_S = 6.0
SETTLED_S = 2.0


def fly(cfg: EstimatorConfig, mocap: sy.MocapModel) -> tuple[sy.Scenario, sy.RunLog, Ukf, int]:
    """The lively 3-D flight; also the filter's UKF predicts (sigma-point passes)."""
    sc = sy.make_scenario(sy.lively(), DURATION_S, sy.PAPER_IMU, mocap, seed=5)
    est = Ukf(cfg)
    tr = sc.truth
    est.initialize(0.0, tr.pos_w_m[0], tr.q_wb[0], tr.vel_w_m_s[0])
    log = sy.run(est, sc)
    return sc, log, est, est.filter_steps


FIXED_10MS = replace(sy.PAPER_MOCAP, latency_min_s=0.010, latency_max_s=0.010)


def test_that_the_horizon_follows_the_smallest_latency_and_nothing_is_replayed() -> None:
    # Fixture: poses 10 ms late (then up to one IMU period until the next tick sees them)
    sc, _, est, predicts = fly(EstimatorConfig(), FIXED_10MS)
    n_imu = len(sc.truth.t_s)
    # Assert: the filter runs 10-12 ms behind and predicts once per IMU sample, no more
    assert 0.010 <= est.fusion_delay_s < 0.012 + 1e-9
    assert n_imu - 10 <= predicts <= n_imu
    assert est.health().poses_accepted >= 0.95 * DURATION_S * FIXED_10MS.rate_hz


def test_that_without_a_horizon_every_late_pose_replays_the_imu() -> None:
    sc, _, est, predicts = fly(EstimatorConfig(max_fusion_delay_s=0.0), FIXED_10MS)
    n_imu = len(sc.truth.t_s)
    assert est.fusion_delay_s == 0.0
    # 100 poses/s, each replaying its 5-6 IMU periods of age: about twice the predicts
    assert predicts > 1.8 * n_imu


@pytest.mark.parametrize("mocap", [FIXED_10MS, sy.PAPER_MOCAP], ids=["10ms", "5-15ms"])
def test_that_the_output_predictor_gives_the_replaying_filters_estimate(
        mocap: sy.MocapModel) -> None:
    # Fixture: the same flight, the same samples, with and without the horizon
    sc, horizon, _, _ = fly(EstimatorConfig(), mocap)
    _, replay, _, _ = fly(EstimatorConfig(max_fusion_delay_s=0.0), mocap)
    settled = sc.truth.t_s >= SETTLED_S
    # Assert: the same estimate, far below its own error (0.26 mm, 0.03 deg). A pose moved
    # by at most half an IMU period (1 ms) with a ~2 mm/s velocity error shifts by ~2 um;
    # the mean-only output integration over ~10 ms adds less
    dp = np.linalg.norm(horizon.pos_w_m - replay.pos_w_m, axis=1)[settled]
    datt = np.degrees(angle_between(horizon.q_wb, replay.q_wb))[settled]
    err = np.linalg.norm(replay.pos_w_m - sc.truth.pos_w_m, axis=1)[settled]
    print(f"\nhorizon vs replay: max {dp.max() * 1e6:.1f} um, {datt.max():.5f} deg; "
          f"replay error rms {np.sqrt(np.mean(err ** 2)) * 1e3:.3f} mm")
    assert dp.max() < 10e-6
    assert datt.max() < 1e-3
    assert np.sqrt(np.mean(err ** 2)) > 1e-4  # (the comparison is not between two zeros)


@pytest.mark.parametrize("delay_s", [0.0, 0.02])
def test_that_the_plain_float_output_state_is_the_estimates(delay_s: float) -> None:
    # Fixture: with a horizon the outputs come from the predictor, without it from the filter
    _, _, est, _ = fly(EstimatorConfig(max_fusion_delay_s=delay_s), FIXED_10MS)
    # Test
    pos, vel, q, omega = est.output_state()
    e = est.estimate()
    # Assert: the same numbers, as Python floats
    assert (pos, vel, q, omega) == (tuple(e.pos_w_m.tolist()), tuple(e.vel_w_m_s.tolist()),
                                    tuple(e.q_wb.tolist()), tuple(e.omega_b_rad_s.tolist()))
    assert est.force_ext_w_n() == tuple(e.force_ext_w_n.tolist())
    assert all(type(v) is float for v in (*pos, *vel, *q, *omega))


def _fly_with_an_early_pose(window: int = 32) -> tuple[Ukf, int, int]:
    """1 kHz IMU at rest, 100 Hz poses 11 ms late, every 40th pose only 9 ms late (read right
    after a delayed IMU sample) -> (filter, IMU samples, poses fused)."""
    est = Ukf(EstimatorConfig(latency_window=window))
    est.initialize(0.0, (0.0, 0.0, 1.0), (1.0, 0.0, 0.0, 0.0))
    n_imu, dt = 4000, 0.001
    arrivals: list[tuple[float, float]] = []        # (arrival, capture) times
    for k in range(n_imu):
        t = dt * (k + 1)
        if k % 10 == 0:
            late = 0.009 if (k // 10) % 40 == 39 else 0.011
            arrivals.append((t + late, t))
        est.predict(t, (0.0, 0.0, 0.0), (0.0, 0.0, 9.81))
        while arrivals and arrivals[0][0] <= t + 1e-9:
            est.update_pose(arrivals.pop(0)[1], (0.0, 0.0, 1.0), (1.0, 0.0, 0.0, 0.0))
    return est, n_imu, est.health().poses_accepted


def test_that_one_early_pose_does_not_pull_the_horizon_down_for_the_whole_window() -> None:
    # Fixture: a pose in 40 looks 2 ms less late than the others
    est, n_imu, accepted = _fly_with_an_early_pose()
    # Assert: the horizon stays at the usual 11 ms and no pose replays the IMU (one filter step
    # per sample). With the smallest latency as the horizon (9 ms) each of the ~350 other
    # poses would replay 2 samples: ~700 more steps
    assert accepted >= 390
    assert est.fusion_delay_s == pytest.approx(0.011, abs=1e-6)
    assert est.filter_steps <= n_imu + 10  # (the first poses, while the window fills)


def test_that_a_short_latency_window_takes_the_smallest_latency() -> None:
    # Fixture: a window of 4 poses has no eighth to leave out
    est, _, _ = _fly_with_an_early_pose(window=4)
    # Assert: the early pose sets the horizon while it is in the window (the last pose was
    # one, at 4000 ms: 9 ms late)
    assert est.fusion_delay_s == pytest.approx(0.009, abs=1e-6)

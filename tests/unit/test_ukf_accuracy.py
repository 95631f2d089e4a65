"""Accuracy on synthetic flights with the paper's sensor class and a 5-15 ms MoCap latency.

The filter starts at the true pose but with zero bias estimates (true biases: a few mrad/s and
a few cm/s^2), so the bias tests see real convergence. Errors are measured from 5 s on.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import pytest

from estimator import EstimatorConfig, Ukf
from estimator import synthetic as sy

DURATION_S = 10.0
SETTLE_S = 5.0
TRAJECTORIES: dict[str, Callable[[], sy.Trajectory]] = {
    "hover": sy.hover, "exp2a_sine_x": sy.sine_x, "roll_sine_6deg": sy.roll_sine,
    "lively_3d": sy.lively,
}


def fly(traj: sy.Trajectory, cfg: EstimatorConfig, seed: int = 3,
        imu: sy.ImuModel = sy.PAPER_IMU, duration_s: float = DURATION_S,
        mocap: sy.MocapModel = sy.PAPER_MOCAP) -> tuple[sy.Scenario, sy.RunLog]:
    sc = sy.make_scenario(traj, duration_s, imu, mocap, seed=seed)
    est = Ukf(cfg)
    tr = sc.truth
    est.initialize(0.0, tr.pos_w_m[0], tr.q_wb[0], tr.vel_w_m_s[0])
    return sc, sy.run(est, sc)


@pytest.fixture(scope="module", params=list(TRAJECTORIES))
def flight(request: pytest.FixtureRequest) -> tuple[str, sy.Scenario, sy.RunLog]:
    name = request.param
    return (name, *fly(TRAJECTORIES[name](), EstimatorConfig()))


def errors(sc: sy.Scenario, log: sy.RunLog, after_s: float) -> tuple[float, float, float]:
    m = sc.truth.t_s >= after_s
    pos = sy.rmse(log.pos_w_m[m], sc.truth.pos_w_m[m])
    vel = sy.rmse(log.vel_w_m_s[m], sc.truth.vel_w_m_s[m])
    att = math.degrees(float(np.sqrt(np.mean(
        sy.attitude_errors_rad(log.q_wb[m], sc.truth.q_wb[m]) ** 2))))
    return pos, vel, att


def test_that_position_velocity_and_attitude_rmse_meet_the_targets(
        flight: tuple[str, sy.Scenario, sy.RunLog]) -> None:
    name, sc, log = flight
    pos, vel, att = errors(sc, log, SETTLE_S)
    print(f"{name}: pos {pos * 1e3:.3f} mm, vel {vel * 1e3:.2f} mm/s, att {att:.4f} deg")
    assert pos < 1e-3
    assert vel < 10e-3
    assert att < 0.2


def test_that_gyro_and_accel_biases_converge_within_5_s(
        flight: tuple[str, sy.Scenario, sy.RunLog]) -> None:
    # converged: below a fifth of the initial error, and staying there
    _, sc, log = flight
    m = sc.truth.t_s >= 5.0
    bg_err = np.abs(log.gyro_bias_rad_s[m] - sy.PAPER_IMU.gyro_bias_rad_s).max()
    ba_err = np.abs(log.accel_bias_m_s2[m] - sy.PAPER_IMU.accel_bias_m_s2).max()
    assert bg_err < 0.2 * np.abs(sy.PAPER_IMU.gyro_bias_rad_s).max()
    assert ba_err < 0.2 * np.abs(sy.PAPER_IMU.accel_bias_m_s2).max()


def test_that_switching_latency_compensation_off_makes_the_error_grow() -> None:
    # Fixture: the Exp. 2a sine (1 m/s peak): 10 ms of latency is about 10 mm of lag
    traj = sy.sine_x()
    sc_on, on = fly(traj, EstimatorConfig(latency_compensation=True))
    sc_off, off = fly(traj, EstimatorConfig(latency_compensation=False))
    # without the gate, to see the lag itself rather than the gate refusing lagged poses
    sc_raw, raw = fly(traj, EstimatorConfig(latency_compensation=False, gate_nis=1e12))
    # Test
    pos_on, vel_on, _ = errors(sc_on, on, SETTLE_S)
    pos_off, vel_off, _ = errors(sc_off, off, SETTLE_S)
    pos_raw, vel_raw, _ = errors(sc_raw, raw, SETTLE_S)
    print(f"latency compensation on: {pos_on * 1e3:.3f} mm {vel_on * 1e3:.2f} mm/s; off: "
          f"{pos_off * 1e3:.3f} mm {vel_off * 1e3:.2f} mm/s; off, no gate: "
          f"{pos_raw * 1e3:.3f} mm {vel_raw * 1e3:.2f} mm/s")
    # Assert
    assert pos_on < 1e-3
    assert pos_off > 10.0 * pos_on
    assert vel_off > 3.0 * vel_on
    assert pos_raw > 10.0 * pos_on
    assert vel_raw > 3.0 * vel_on


def test_that_the_filter_is_as_accurate_with_a_1_khz_imu() -> None:
    imu = sy.ImuModel(rate_hz=1000.0, gyro_noise_rad_s_sqrt_hz=8.7e-4,
                      accel_noise_m_s2_sqrt_hz=2e-3, gyro_bias_rad_s=(0.005, -0.008, 0.006),
                      accel_bias_m_s2=(0.05, -0.04, 0.06))
    sc, log = fly(sy.lively(), EstimatorConfig(), imu=imu, duration_s=7.0)
    pos, vel, att = errors(sc, log, SETTLE_S)
    print(f"1 kHz: pos {pos * 1e3:.3f} mm, vel {vel * 1e3:.2f} mm/s, att {att:.4f} deg")
    assert pos < 1e-3
    assert vel < 10e-3
    assert att < 0.2


def test_that_holding_the_newest_imu_sample_over_the_period_also_meets_the_targets() -> None:
    sc, log = fly(sy.sine_x(), EstimatorConfig(imu_integration="hold"), duration_s=7.0)
    pos, vel, att = errors(sc, log, SETTLE_S)
    assert pos < 1e-3
    assert vel < 10e-3
    assert att < 0.2

"""Start-up from a rest period, and the external-force observer."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from estimator import EstimatorConfig, HealthFlag, PoseVerdict, Ukf
from estimator import synthetic as sy


def test_that_the_filter_starts_from_rest_with_the_gyro_bias_of_the_rest_period() -> None:
    # Fixture: 1 s on the ground, then the Exp. 2a sine ramps in over 2 s
    sc = sy.make_scenario(sy.sine_x(start_s=1.0, ramp_s=2.0), 8.0, sy.PAPER_IMU,
                          sy.PAPER_MOCAP, seed=21)
    est = Ukf(EstimatorConfig())
    first_init_t: list[float] = []

    def watch(k: int) -> None:
        if est.initialized and not first_init_t:
            first_init_t.append(float(sc.truth.t_s[k]))
            # the rest mean: per-sample gyro noise / sqrt(samples) ~ 0.9 mrad/s after 0.5 s
            err = est.estimate().gyro_bias_rad_s - sy.PAPER_IMU.gyro_bias_rad_s
            assert np.abs(err).max() < 4e-3

    # Test
    log = sy.run(est, sc, on_tick=watch)
    # Assert: started right after the rest period, then flies as accurately as ever
    assert 0.5 <= first_init_t[0] < 0.6
    assert any(v is PoseVerdict.INITIALIZING for _, v in log.verdicts)
    m = sc.truth.t_s >= 4.0
    assert sy.rmse(log.pos_w_m[m], sc.truth.pos_w_m[m]) < 1e-3
    assert sy.rmse(log.vel_w_m_s[m], sc.truth.vel_w_m_s[m]) < 10e-3


def test_that_a_moving_vehicle_is_not_mistaken_for_one_at_rest() -> None:
    sc = sy.make_scenario(sy.sine_x(), 2.0, sy.PAPER_IMU, sy.PAPER_MOCAP, seed=22)
    est = Ukf(EstimatorConfig())
    sy.run(est, sc)
    state = est.estimate()
    assert not est.initialized
    assert HealthFlag.NOT_INITIALIZED in state.health.flags


def force_flight(cfg: EstimatorConfig, feed_force: bool, duration_s: float = 12.0
                 ) -> tuple[sy.Scenario, sy.RunLog]:
    # paper-calibrated disturbance: 0.3 N tether + OU force 0.3 N rms, tau 1 s
    force = sy.ExternalForce(constant_w_n=(0.3, 0.0, 0.0), ou_sigma_n=0.3, ou_tau_s=1.0)
    sc = sy.make_scenario(sy.lively(), duration_s, sy.PAPER_IMU, sy.PAPER_MOCAP, seed=23,
                          force=force, mass_kg=cfg.mass_kg)
    est = Ukf(cfg)
    tr = sc.truth
    est.initialize(0.0, tr.pos_w_m[0], tr.q_wb[0], tr.vel_w_m_s[0])
    return sc, sy.run(est, sc, feed_force=feed_force)


def test_that_the_force_observer_tracks_the_external_force_within_0_1_n() -> None:
    sc, log = force_flight(EstimatorConfig(), feed_force=True)
    m = sc.truth.t_s >= 3.0
    err = log.force_ext_w_n[m] - sc.force_ext_w_n[m]
    per_axis = np.sqrt(np.mean(err ** 2, axis=0))
    total = sy.rmse(log.force_ext_w_n[m], sc.force_ext_w_n[m])
    print(f"force RMSE per axis {np.round(per_axis, 3)} N, norm {total:.3f} N")
    assert per_axis.max() < 0.1
    # better than assuming no force at all, by a wide margin
    assert total < 0.4 * sy.rmse(np.zeros_like(err), sc.force_ext_w_n[m])


def test_that_the_force_observer_can_be_switched_off_and_waits_for_a_command() -> None:
    _, off = force_flight(EstimatorConfig(force_observer=False), True, duration_s=1.0)
    assert np.all(off.force_ext_w_n[off.initialized] == 0.0)
    _, no_cmd = force_flight(EstimatorConfig(), False, duration_s=1.0)
    assert np.all(no_cmd.force_ext_w_n[no_cmd.initialized] == 0.0)


def test_that_the_observer_accounts_for_the_rotor_lag_between_command_and_thrust() -> None:
    # Fixture: the rotors produce the scenario's thrust 30 ms after it is commanded, so the
    # command is F + tau dF/dt (the inverse of the first-order lag)
    tau = 0.03
    force = sy.ExternalForce(constant_w_n=(0.3, 0.0, 0.0), ou_sigma_n=0.3, ou_tau_s=1.0)
    sc = sy.make_scenario(sy.lively(), 8.0, sy.PAPER_IMU, sy.PAPER_MOCAP, seed=24, force=force)
    dt = 1.0 / sy.PAPER_IMU.rate_hz
    commanded = sc.force_cmd_b_n + tau * np.gradient(sc.force_cmd_b_n, dt, axis=0)
    sc = replace(sc, force_cmd_b_n=commanded)
    m = sc.truth.t_s >= 3.0
    results = {}
    for lag in (0.0, tau):
        est = Ukf(EstimatorConfig(force_cmd_lag_s=lag))
        tr = sc.truth
        est.initialize(0.0, tr.pos_w_m[0], tr.q_wb[0], tr.vel_w_m_s[0])
        log = sy.run(est, sc, feed_force=True)
        results[lag] = np.sqrt(np.mean((log.force_ext_w_n[m] - sc.force_ext_w_n[m]) ** 2, axis=0))
    print(f"force RMSE per axis, lag ignored {np.round(results[0.0], 3)} N, "
          f"modelled {np.round(results[tau], 3)} N")
    # Assert
    assert results[tau].max() < 0.1
    assert results[0.0].max() > 1.5 * results[tau].max()

"""The synthetic truth is exact: its IMU readings integrate back to its own trajectory."""

from __future__ import annotations

import numpy as np

from estimator import synthetic as sy
from estimator.quaternion import angle_between, quat_exp, quat_mul, quat_to_rot


def test_that_the_derivatives_of_every_trajectory_match_finite_differences() -> None:
    t = np.linspace(0.0, 12.0, 4001)
    h = 1e-5
    for traj in (sy.hover(), sy.sine_x(), sy.roll_sine(), sy.lively(),
                 sy.lively(start_s=1.0, ramp_s=2.0)):
        for sig in (traj.x, traj.y, traj.z, traj.roll, traj.pitch, traj.yaw):
            _, df, ddf = sig(t)
            fp, dfp, _ = sig(t + h)
            fm, dfm, _ = sig(t - h)
            np.testing.assert_allclose(df, (fp - fm) / (2 * h), atol=1e-7)
            # O(h) at the ends of a ramp, where the jerk steps
            np.testing.assert_allclose(ddf, (dfp - dfm) / (2 * h), atol=1e-4)


def test_that_noise_free_imu_readings_dead_reckon_the_trajectory() -> None:
    # Fixture: a 3-D trajectory, perfect sensors at 1 kHz, midpoint integration
    rate = 1000.0
    traj = sy.lively()
    t = np.arange(0, 4001) / rate
    truth = sy.sample_truth(traj, t)
    q, p, v = truth.q_wb[0], truth.pos_w_m[0], truth.vel_w_m_s[0]
    g = np.array([0.0, 0.0, -9.81])
    # Test
    for k in range(1, len(t)):
        dt = t[k] - t[k - 1]
        w = 0.5 * (truth.omega_b_rad_s[k - 1] + truth.omega_b_rad_s[k])
        a0 = quat_to_rot(q) @ truth.specific_force_b_m_s2[k - 1] + g
        q = quat_mul(q, quat_exp(w * dt))
        a1 = quat_to_rot(q) @ truth.specific_force_b_m_s2[k] + g
        p = p + v * dt + 0.25 * (a0 + a1) * dt * dt
        v = v + 0.5 * (a0 + a1) * dt
    # Assert: second-order integration error only (4 s at 1 kHz)
    assert float(angle_between(q, truth.q_wb[-1])) < 1e-5
    assert np.linalg.norm(v - truth.vel_w_m_s[-1]) < 1e-4
    assert np.linalg.norm(p - truth.pos_w_m[-1]) < 1e-4


def test_that_a_hovering_imu_reads_plus_g_and_mocap_frames_arrive_late_and_in_order() -> None:
    sc = sy.make_scenario(sy.hover(), 1.0, sy.ImuModel(gyro_noise_rad_s_sqrt_hz=1e-12,
                                                      accel_noise_m_s2_sqrt_hz=1e-12),
                          sy.PAPER_MOCAP, seed=0)
    np.testing.assert_allclose(sc.accel_m_s2, np.tile([0.0, 0.0, 9.81], (500, 1)), atol=1e-9)
    lat = np.array([f.arrival_t_s - f.capture_t_s for f in sc.frames])
    assert len(sc.frames) == 100
    assert lat.min() >= 0.005 - 1e-12
    assert lat.max() <= 0.015 + 1e-12
    assert np.all(np.diff([f.arrival_t_s for f in sc.frames]) >= 0)


def test_that_the_external_force_is_consistent_with_accelerometer_and_thrust() -> None:
    force = sy.ExternalForce(constant_w_n=(0.3, 0.0, -0.1), ou_sigma_n=0.3, ou_tau_s=1.0)
    sc = sy.make_scenario(sy.lively(), 2.0, sy.ImuModel(gyro_noise_rad_s_sqrt_hz=1e-12,
                                                       accel_noise_m_s2_sqrt_hz=1e-12),
                          sy.MocapModel(), seed=1, force=force, mass_kg=3.1)
    rot = quat_to_rot(sc.truth.q_wb)
    # m * specific force (body) = thrust (body) + R^T F_ext
    recon = sc.force_cmd_b_n + np.einsum("nji,nj->ni", rot, sc.force_ext_w_n)
    np.testing.assert_allclose(3.1 * sc.accel_m_s2, recon, atol=1e-8)

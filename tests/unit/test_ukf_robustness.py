"""Dropouts, outliers, marker swaps, bad samples and the health flags."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from estimator import EstimatorConfig, HealthFlag, PoseVerdict, ResetInfo, Ukf
from estimator import synthetic as sy

SHORT = (6.0, 6.1)    # 100 ms without poses
LONG = (8.0, 8.5)     # 500 ms without poses
OUTLIER_T = 9.505     # one frame with a 0.3 m jump (marker swap for one frame)

DropoutRun = tuple[sy.Scenario, sy.RunLog, list[HealthFlag], list[np.ndarray]]


def start_at_truth(sc: sy.Scenario, cfg: EstimatorConfig | None = None) -> Ukf:
    est = Ukf(cfg or EstimatorConfig())
    tr = sc.truth
    est.initialize(0.0, tr.pos_w_m[0], tr.q_wb[0], tr.vel_w_m_s[0])
    return est


@pytest.fixture(scope="module")
def dropout_run() -> DropoutRun:
    mocap = sy.MocapModel(pos_sigma_m=5e-4, att_sigma_deg=0.115, latency_min_s=0.005,
                          latency_max_s=0.015, dropouts_s=(SHORT, LONG),
                          outliers=((OUTLIER_T, (0.3, 0.0, 0.0)),))
    sc = sy.make_scenario(sy.lively(), 10.5, sy.PAPER_IMU, mocap, seed=5)
    est = start_at_truth(sc)
    flags: list[HealthFlag] = []
    covs: list[np.ndarray] = []

    def record(k: int) -> None:
        e = est.estimate()
        flags.append(e.health.flags)
        if k % 50 == 0:
            covs.append(e.cov)

    return sc, sy.run(est, sc, on_tick=record), flags, covs


def window(sc: sy.Scenario, a: float, b: float) -> np.ndarray:
    return (sc.truth.t_s >= a) & (sc.truth.t_s < b)


def test_that_a_100_ms_dropout_stays_within_5_mm_and_1_deg(dropout_run: DropoutRun) -> None:
    sc, log, _, _ = dropout_run
    m = window(sc, SHORT[0], SHORT[1] + 0.03)
    pos_err = np.linalg.norm(log.pos_w_m[m] - sc.truth.pos_w_m[m], axis=1)
    att_err = np.degrees(sy.attitude_errors_rad(log.q_wb[m], sc.truth.q_wb[m]))
    assert pos_err.max() < 5e-3
    assert att_err.max() < 1.0


@pytest.mark.parametrize(("gap", "growth"), [(SHORT, 1.5), (LONG, 5.0)])
def test_that_the_covariance_grows_during_a_dropout_and_the_filter_reconverges_within_1_s(
        dropout_run: DropoutRun, gap: tuple[float, float], growth: float) -> None:
    sc, log, _, _ = dropout_run
    t = sc.truth.t_s
    before = log.pos_sigma_m[np.searchsorted(t, gap[0]) - 1]
    at_end = log.pos_sigma_m[np.searchsorted(t, gap[1] + 0.005)]   # last frame still in flight
    assert at_end > growth * before
    # re-converged: from 1 s after the poses return, as accurate as before the gap
    after = window(sc, gap[1] + 1.0, gap[1] + 1.4)
    ref = window(sc, gap[0] - 0.9, gap[0] - 0.1)
    err_after = sy.rmse(log.pos_w_m[after], sc.truth.pos_w_m[after])
    err_ref = sy.rmse(log.pos_w_m[ref], sc.truth.pos_w_m[ref])
    assert err_after < max(2.0 * err_ref, 1e-3)
    assert log.pos_sigma_m[after].max() < 1.5 * before


def test_that_mocap_stale_is_flagged_during_the_dropout_and_cleared_after(
        dropout_run: DropoutRun) -> None:
    sc, _, flags, _ = dropout_run
    t = sc.truth.t_s
    stale = np.array([HealthFlag.MOCAP_STALE in f for f in flags])
    # stale once the newest capture is mocap_stale_s (50 ms) old, i.e. inside the long gap
    assert stale[window(sc, LONG[0] + 0.08, LONG[1])].all()
    assert not stale[window(sc, LONG[1] + 0.1, LONG[1] + 1.0)].any()
    assert not stale[window(sc, 1.0, SHORT[0] + 0.03)].any()
    assert not any(HealthFlag.DIVERGED in f for f in flags)
    assert t[-1] > LONG[1] + 1.0


def test_that_an_outlier_pose_is_rejected_and_counted(dropout_run: DropoutRun) -> None:
    sc, log, _, _ = dropout_run
    verdicts = dict(log.verdicts)
    assert verdicts[OUTLIER_T] is PoseVerdict.REJECTED
    assert sum(v is PoseVerdict.REJECTED for v in verdicts.values()) <= 3  # the outlier + chi2
    m = window(sc, OUTLIER_T, OUTLIER_T + 0.2)
    assert np.linalg.norm(log.pos_w_m[m] - sc.truth.pos_w_m[m], axis=1).max() < 2e-3


def test_that_the_covariance_stays_symmetric_positive_definite(dropout_run: DropoutRun) -> None:
    _, _, _, covs = dropout_run
    for cov in covs:
        np.testing.assert_array_equal(cov, cov.T)
        assert np.linalg.eigvalsh(cov).min() > 0.0


def test_that_a_marker_swap_that_stays_resets_position_to_mocap_after_n_rejections() -> None:
    # Fixture: from 3 s on, MoCap reports the body 0.3 m off (a swapped marker set)
    cfg = EstimatorConfig(max_consecutive_rejections=10)
    swap = tuple((0.005 + k / 100.0, (0.3, 0.0, 0.0)) for k in range(300, 500))
    mocap = sy.MocapModel(pos_sigma_m=5e-4, att_sigma_deg=0.115, latency_min_s=0.01,
                          latency_max_s=0.01, outliers=swap)
    sc = sy.make_scenario(sy.hover(), 5.0, sy.PAPER_IMU, mocap, seed=6)
    est = start_at_truth(sc, cfg)
    # Test
    log = sy.run(est, sc)
    # Assert
    after = [v for t, v in log.verdicts if t > 3.0]
    assert after[:9] == [PoseVerdict.REJECTED] * 9
    assert after[9] is PoseVerdict.RESET
    assert est.health().resets == 1
    end = est.estimate().pos_w_m
    np.testing.assert_allclose(end, sc.truth.pos_w_m[-1] + [0.3, 0.0, 0.0], atol=3e-3)


@pytest.mark.parametrize(("imu_noted", "missed", "mocap_hz"), [
    (True, True, 100.0), (True, False, 100.0), (False, False, 100.0), (True, True, 12.0)])
def test_that_a_reseed_takes_mocaps_velocity_only_when_the_imu_was_seen_failing(
        imu_noted: bool, missed: bool, mocap_hz: float) -> None:
    # Fixture: a hover whose IMU, at 2 s, reads 20 ms of an impact the body never had (as an
    # impact beyond the link's range reads too little): a 0.5 m/s phantom upward velocity.
    # (At 12 Hz the refused poses of the last 0.1 s are too few: the last 3 give the slope.)
    sc = sy.make_scenario(sy.hover(), 4.0 if mocap_hz >= 100.0 else 6.0, sy.PAPER_IMU,
                          sy.MocapModel(rate_hz=mocap_hz, pos_sigma_m=5e-4), seed=6)
    hit = (sc.truth.t_s >= 2.0) & (sc.truth.t_s < 2.02)
    sc.accel_m_s2[hit] += (0.0, 0.0, 25.0)
    est = start_at_truth(sc)
    first: list[ResetInfo] = []

    def note(k: int) -> None:       # what the loop does when the link counts an anomaly
        if imu_noted and hit[k]:    # an impact beyond the link's range, or lost samples
            est.note_imu_anomaly(float(sc.truth.t_s[k]), motion_missed=missed)
        if not first and est.last_reset is not None:
            first.append(est.last_reset)

    # Test
    log = sy.run(est, sc, on_tick=note)
    # Assert: the poses are refused until the re-seed, which measured the gap between the
    # IMU's velocity and MoCap's (the refused poses' slope: the hover's ~0)
    info = first[0] if first else None
    assert info is not None and info.imu_suspect is imu_noted
    assert info.imu_missed_motion is missed
    assert info.streak_start_s == pytest.approx(2.0, abs=0.05 + 1.0 / mocap_hz)
    assert info.vel_mocap_w_m_s is not None
    assert np.linalg.norm(info.vel_mocap_w_m_s) < 0.05
    assert info.velocity_gap_m_s == pytest.approx(0.5, abs=0.1)
    after = log.t_s > info.t_s + 0.05
    v_err = np.linalg.norm(log.vel_w_m_s[after] - sc.truth.vel_w_m_s[after], axis=1)
    if imu_noted:   # MoCap's velocity taken: one re-seed, the estimate right from there
        assert est.health().resets == 1
        assert v_err.max() < 0.05
    else:           # the IMU's velocity kept (MoCap is the suspect): off after the re-seed,
        # which the next ones repeat (what the loop counts as MoCap and IMU disagreeing)
        assert v_err[0] > 0.3
        assert est.health().resets >= 3


def test_that_dead_reckoning_grows_the_covariance_monotonically() -> None:
    sc = sy.make_scenario(sy.hover(), 2.0, sy.PAPER_IMU, sy.MocapModel(), seed=7)
    est = start_at_truth(sc)
    sigmas = []
    for k in range(len(sc.truth.t_s)):
        est.predict(float(sc.truth.t_s[k]), sc.gyro_rad_s[k], sc.accel_m_s2[k])
        sigmas.append(float(np.max(est.estimate().pos_sigma_m)))
    assert np.all(np.diff(sigmas) >= 0.0)
    assert sigmas[-1] > sigmas[0]
    assert HealthFlag.MOCAP_STALE in est.health().flags


def test_that_non_finite_samples_and_poses_are_dropped_and_counted() -> None:
    sc = sy.make_scenario(sy.hover(), 0.2, sy.PAPER_IMU, sy.MocapModel(), seed=8)
    est = start_at_truth(sc)
    est.predict(0.002, sc.gyro_rad_s[0], sc.accel_m_s2[0])
    before = est.estimate()
    est.predict(0.004, [math.nan, 0.0, 0.0], sc.accel_m_s2[1])
    est.predict(0.004, sc.gyro_rad_s[1], sc.accel_m_s2[1], [0.0, math.inf, 30.0])
    assert est.update_pose(0.004, [0.0, math.nan, 1.0], [1, 0, 0, 0]) is PoseVerdict.INVALID
    assert est.update_pose(0.004, [0.0, 0.0, 1.0], [0, 0, 0, 0]) is PoseVerdict.INVALID
    state = est.estimate()
    assert state.health.imu_invalid == 1
    assert state.health.poses_invalid == 2
    assert state.health.ok
    assert state.t_s == 0.004 and before.t_s == 0.002
    assert np.all(np.isfinite(state.cov)) and np.all(np.isfinite(state.force_ext_w_n))


def test_that_a_blown_up_state_flags_divergence_and_the_next_pose_reseeds() -> None:
    sc = sy.make_scenario(sy.hover(), 0.2, sy.PAPER_IMU, sy.MocapModel(), seed=8)
    est = start_at_truth(sc)
    est.predict(0.002, sc.gyro_rad_s[0], sc.accel_m_s2[0])
    with np.errstate(all="ignore"):
        est.predict(0.004, sc.gyro_rad_s[1], [1e200, 0.0, 0.0])   # finite, absurd
    state = est.estimate()
    assert HealthFlag.DIVERGED in state.health.flags
    assert np.all(np.isfinite(state.pos_w_m)) and np.all(np.isfinite(state.cov))
    verdict = est.update_pose(0.004, sc.truth.pos_w_m[1], sc.truth.q_wb[1])
    assert verdict is PoseVerdict.RESET
    assert HealthFlag.DIVERGED not in est.health().flags
    np.testing.assert_allclose(est.estimate().pos_w_m, sc.truth.pos_w_m[1])


def test_that_a_singular_covariance_is_repaired_and_counted() -> None:
    # perfectly known biases: zero variance, so the first Cholesky fails
    sc = sy.make_scenario(sy.hover(), 0.2, sy.PAPER_IMU, sy.MocapModel(), seed=10)
    cov = np.diag([1e-4] * 9 + [0.0] * 6)
    est = Ukf(EstimatorConfig())
    est.initialize(0.0, sc.truth.pos_w_m[0], sc.truth.q_wb[0], cov=cov)
    est.predict(0.002, sc.gyro_rad_s[0], sc.accel_m_s2[0])
    state = est.estimate()
    assert state.health.covariance_repairs == 1
    assert np.linalg.eigvalsh(state.cov).min() > 0.0


def test_that_an_initial_covariance_that_is_not_one_is_refused() -> None:
    est = Ukf(EstimatorConfig())
    with pytest.raises(ValueError, match="positive semi-definite"):
        est.initialize(0.0, [0, 0, 1], [1, 0, 0, 0], cov=-np.eye(15))


def test_that_out_of_order_imu_samples_and_too_old_poses_are_dropped_and_counted() -> None:
    sc = sy.make_scenario(sy.hover(), 1.0, sy.PAPER_IMU, sy.MocapModel(), seed=9)
    est = start_at_truth(sc, EstimatorConfig(history_s=0.1))
    for k in range(300):
        est.predict(float(sc.truth.t_s[k]), sc.gyro_rad_s[k], sc.accel_m_s2[k])
    before = est.estimate()
    est.predict(float(sc.truth.t_s[100]), sc.gyro_rad_s[100], sc.accel_m_s2[100])
    verdict = est.update_pose(0.3, sc.truth.pos_w_m[149], sc.truth.q_wb[149])  # 0.3 s late
    after = est.estimate()
    assert verdict is PoseVerdict.TOO_OLD
    assert after.health.imu_out_of_order == 1
    assert after.health.poses_too_old == 1
    assert after.t_s == before.t_s
    np.testing.assert_array_equal(after.pos_w_m, before.pos_w_m)


def test_that_biases_outside_their_range_are_flagged() -> None:
    est = Ukf(EstimatorConfig())
    est.initialize(0.0, [0, 0, 1], [1, 0, 0, 0], gyro_bias_rad_s=[0.3, 0, 0],
                   accel_bias_m_s2=[0, 0, -2.0])
    flags = est.health().flags
    assert HealthFlag.GYRO_BIAS_OUT_OF_RANGE in flags
    assert HealthFlag.ACCEL_BIAS_OUT_OF_RANGE in flags
    est.initialize(0.0, [0, 0, 1], [1, 0, 0, 0])
    assert est.health().ok


values = st.one_of(st.floats(-1e6, 1e6), st.sampled_from([math.nan, math.inf, -math.inf]))
vec3 = st.tuples(values, values, values)
quat = st.tuples(values, values, values, values)
events = st.one_of(
    st.tuples(st.just("imu"), st.floats(-0.01, 0.05), vec3, vec3),
    st.tuples(st.just("pose"), st.floats(-0.5, 0.05), vec3, quat),
    st.tuples(st.just("rest_pose"), st.floats(-0.5, 0.05), vec3, quat),
)


@settings(max_examples=60, deadline=None)
@given(st.lists(events, max_size=60), st.booleans())
def test_that_arbitrary_inputs_never_raise_nor_leave_a_non_finite_estimate(
        seq: list[tuple[str, float, tuple[float, ...], tuple[float, ...]]],
        start_initialized: bool) -> None:
    est = Ukf(EstimatorConfig(init_rest_s=0.01, init_min_poses=1))
    t = 0.0
    if start_initialized:
        est.initialize(0.0, [0, 0, 1], [1, 0, 0, 0])
    with np.errstate(all="ignore"):
        for kind, dt, a, b in seq:
            if kind == "imu":
                t += dt
                est.predict(t, a, b, a)
            elif kind == "pose":
                est.update_pose(t + dt, a, b)
            else:   # a plausible pose, so that the rest start-up gets exercised too
                est.update_pose(t + dt, [0.0, 0.0, 1.0], [1.0, 0.0, 0.0, 0.0])
            state = est.estimate()
            if est.initialized:
                assert np.all(np.isfinite(state.cov))
                assert np.all(np.isfinite(state.pos_w_m)) and np.all(np.isfinite(state.vel_w_m_s))
                assert np.all(np.isfinite(state.q_wb))
                assert np.all(np.isfinite(state.force_ext_w_n))
                assert abs(float(np.linalg.norm(state.q_wb)) - 1.0) < 1e-9


def test_that_usable_agrees_with_the_health_report_tick_by_tick() -> None:
    """The loop's per-tick check (``usable``) is the health report's NOT_INITIALIZED and
    DIVERGED, without the report: the same answer before initialisation, while dead
    reckoning grows the position sigma past the divergence limit, and on a blown-up state."""
    def reported(est: Ukf) -> bool:
        return not est.health().flags & (HealthFlag.DIVERGED | HealthFlag.NOT_INITIALIZED)

    sc = sy.make_scenario(sy.hover(), 2.0, sy.PAPER_IMU, sy.MocapModel(), seed=7)
    fresh = Ukf(EstimatorConfig())
    assert fresh.usable() is reported(fresh) is False
    est = start_at_truth(sc, EstimatorConfig(diverged_pos_sigma_m=0.02))
    seen = []
    for k in range(len(sc.truth.t_s)):
        est.predict(float(sc.truth.t_s[k]), sc.gyro_rad_s[k], sc.accel_m_s2[k])
        assert est.usable() is reported(est)
        seen.append(est.usable())
    assert seen[0] and not seen[-1]        # dead reckoning: usable, then diverged
    with np.errstate(all="ignore"):
        est.predict(3.0, sc.gyro_rad_s[0], [1e200, 0.0, 0.0])
    assert est.usable() is reported(est) is False

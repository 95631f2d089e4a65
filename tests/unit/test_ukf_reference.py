"""The fast paths (compiled loops; all sigma points as one numpy array) against stock filterpy,
sigma point by point."""

from __future__ import annotations

from dataclasses import replace
from typing import Literal

import numpy as np
import pytest

from estimator import EstimatorConfig, PoseVerdict, Ukf
from estimator import synthetic as sy


@pytest.mark.parametrize("kernel", ["compiled", "numpy"])
def test_that_the_fast_path_gives_the_plain_filterpy_estimates_to_1e_9(
        kernel: Literal["compiled", "numpy"]) -> None:
    # Fixture: late poses (replay), a dropout, an outlier (gate), the force observer on
    mocap = sy.MocapModel(pos_sigma_m=5e-4, att_sigma_deg=0.115, latency_min_s=0.005,
                          latency_max_s=0.015, dropouts_s=((0.8, 1.0),),
                          outliers=((1.505, (0.3, 0.0, 0.0)),))
    force = sy.ExternalForce(constant_w_n=(0.3, 0.0, 0.0), ou_sigma_n=0.3)
    sc = sy.make_scenario(sy.lively(), 2.0, sy.PAPER_IMU, mocap, seed=11, force=force)
    cfg = EstimatorConfig()
    fast, ref = Ukf(cfg, kernel=kernel), Ukf(cfg, kernel="filterpy")
    tr = sc.truth
    for est in (fast, ref):
        est.initialize(0.0, tr.pos_w_m[0], tr.q_wb[0], tr.vel_w_m_s[0])
    worst = 0.0

    def compare(k: int) -> None:
        nonlocal worst
        a, b = fast.estimate(), ref.estimate()
        for name in ("pos_w_m", "vel_w_m_s", "q_wb", "omega_b_rad_s", "gyro_bias_rad_s",
                     "accel_bias_m_s2", "cov", "force_ext_w_n"):
            worst = max(worst, float(np.max(np.abs(getattr(a, name) - getattr(b, name)))))
        assert replace(a.health, last_nis=0.0) == replace(b.health, last_nis=0.0)
        if np.isfinite(a.health.last_nis):
            assert abs(a.health.last_nis - b.health.last_nis) < 1e-6 * (1 + a.health.last_nis)

    # Test: the reference is driven in lockstep from inside the fast run
    frames = iter(sc.frames)
    pending = next(frames, None)
    ref_verdicts = []

    def drive_reference(k: int) -> None:
        nonlocal pending
        t = float(tr.t_s[k])
        ref.predict(t, sc.gyro_rad_s[k], sc.accel_m_s2[k], sc.force_cmd_b_n[k])
        while pending is not None and pending.arrival_t_s <= t:
            ref_verdicts.append(ref.update_pose(pending.capture_t_s, pending.pos_w_m,
                                                pending.q_wb))
            pending = next(frames, None)
        compare(k)

    log = sy.run(fast, sc, feed_force=True, on_tick=drive_reference)
    # Assert
    assert [v for _, v in log.verdicts] == ref_verdicts
    assert PoseVerdict.REJECTED in ref_verdicts          # the gate was exercised
    assert worst < 1e-9, worst
    print(f"largest difference fast vs filterpy: {worst:.2e}")


def test_that_the_compiled_predict_hands_a_repair_in_the_queue_to_the_python_path() -> None:
    # Fixture: late poses (the filter runs behind, inputs queued); at 1 s both filters get a
    # covariance with zero bias variances (not positive definite: the next step repairs it)
    mocap = replace(sy.PAPER_MOCAP, latency_min_s=0.010, latency_max_s=0.010)
    sc = sy.make_scenario(sy.lively(), 1.6, sy.PAPER_IMU, mocap, seed=3)
    fast, ref = Ukf(EstimatorConfig(), kernel="compiled"), Ukf(EstimatorConfig(), kernel="numpy")
    tr = sc.truth
    for est in (fast, ref):
        est.initialize(0.0, tr.pos_w_m[0], tr.q_wb[0], tr.vel_w_m_s[0])
    frames = iter(sc.frames)
    pending = next(frames, None)
    queued = 0
    for k in range(len(tr.t_s)):
        t = float(tr.t_s[k])
        if k == 500:
            for est in (fast, ref):
                est._P[9:15, :] = 0.0
                est._P[:, 9:15] = 0.0
        for est in (fast, ref):
            est.predict(t, sc.gyro_rad_s[k], sc.accel_m_s2[k])
        while pending is not None and pending.arrival_t_s <= t:
            for est in (fast, ref):
                est.update_pose(pending.capture_t_s, pending.pos_w_m, pending.q_wb)
            pending = next(frames, None)
        queued = max(queued, len(fast._pending))
        a, b = fast.estimate(), ref.estimate()
        for name in ("pos_w_m", "vel_w_m_s", "q_wb", "cov"):
            np.testing.assert_allclose(getattr(a, name), getattr(b, name), rtol=0, atol=1e-9)
    # Assert: the repair happened in both, while inputs were queued
    assert queued >= 4
    assert fast.health().covariance_repairs == ref.health().covariance_repairs >= 1
    assert fast.filter_steps == ref.filter_steps


def test_that_the_compiled_replay_hands_a_repair_to_the_python_path() -> None:
    # Fixture: poses 5-15 ms late (many older than the horizon: replayed from the history);
    # from 1 s on, for 40 ms, every history entry of both filters gets zero bias variances, so
    # a replay then rewinds to a covariance that is not positive definite (the update repairs
    # it). Breaking the compiled replay's hand-over makes the estimates differ
    sc = sy.make_scenario(sy.lively(), 1.6, sy.PAPER_IMU, sy.PAPER_MOCAP, seed=4)
    fast, ref = Ukf(EstimatorConfig(), kernel="compiled"), Ukf(EstimatorConfig(), kernel="numpy")
    kernel = fast._step_kernel
    assert kernel is not None
    statuses: list[int] = []
    compiled_replay = kernel.fuse_in_past

    def counted(*args: object) -> tuple[int, float]:
        status, nis = compiled_replay(*args)  # type: ignore[arg-type]
        statuses.append(status)
        return status, nis

    kernel.fuse_in_past = counted  # type: ignore[method-assign]
    tr = sc.truth
    for est in (fast, ref):
        est.initialize(0.0, tr.pos_w_m[0], tr.q_wb[0], tr.vel_w_m_s[0])
    frames = iter(sc.frames)
    pending = next(frames, None)
    for k in range(len(tr.t_s)):
        t = float(tr.t_s[k])
        if 500 <= k < 520:
            for est in (fast, ref):
                est._hist_P[:, 9:15, :] = 0.0
                est._hist_P[:, :, 9:15] = 0.0
        for est in (fast, ref):
            est.predict(t, sc.gyro_rad_s[k], sc.accel_m_s2[k])
        while pending is not None and pending.arrival_t_s <= t:
            verdicts = {est.update_pose(pending.capture_t_s, pending.pos_w_m, pending.q_wb)
                        for est in (fast, ref)}
            assert len(verdicts) == 1
            pending = next(frames, None)
        a, b = fast.estimate(), ref.estimate()
        for name in ("pos_w_m", "vel_w_m_s", "q_wb", "cov"):
            np.testing.assert_allclose(getattr(a, name), getattr(b, name), rtol=0, atol=1e-9)
    # Assert: replays ran compiled, one was handed over, and both filters repaired it alike
    assert statuses.count(0) >= 20
    assert 1 in statuses
    assert fast.health().covariance_repairs == ref.health().covariance_repairs >= 1
    assert fast.filter_steps == ref.filter_steps

"""Dead reckoning from a checkpoint (``Ukf.checkpoint`` / ``Ukf.dead_reckon_from``): how the
loop undoes a MoCap found wrong only after the filter had fused it for a while (a frozen
tracker that still streams: groundstation.loop, DEAD_RECKON_LOOKBACK_S)."""

from __future__ import annotations

import math

import numpy as np

from estimator import EstimatorConfig, Ukf
from estimator import synthetic as sy
from estimator.types import ACCEL_BIAS, GYRO_BIAS
from estimator.ukf import UkfCheckpoint

Inputs = list[tuple[float, tuple[float, ...], tuple[float, ...], None]]


def _scenario(seed: int) -> sy.Scenario:
    mocap = sy.MocapModel(pos_sigma_m=5e-4, att_sigma_deg=0.115, latency_min_s=0.01,
                          latency_max_s=0.01)
    return sy.make_scenario(sy.lively(), 4.0, sy.PAPER_IMU, mocap, seed=seed)


def _fly(est: Ukf, sc: sy.Scenario, *, poses_until_s: float = math.inf,
         freeze_at_s: float = math.inf, checkpoint_at_s: float = math.inf
         ) -> tuple[Inputs, UkfCheckpoint | None]:
    """The loop's order (predict, then the poses that arrived); poses captured after
    ``poses_until_s`` are not fused, those after ``freeze_at_s`` are the pose of then with
    their own noise (a frozen tracker); a checkpoint after the tick at ``checkpoint_at_s``."""
    inputs: Inputs = []
    cp = None
    frames, i = sc.frames, 0
    frozen: tuple[np.ndarray, np.ndarray] | None = None
    for k, t_np in enumerate(sc.truth.t_s):
        t = float(t_np)
        inp = (t, tuple(sc.gyro_rad_s[k]), tuple(sc.accel_m_s2[k]), None)
        est.predict(*inp)
        inputs.append(inp)
        while i < len(frames) and frames[i].arrival_t_s <= t:
            f = frames[i]
            i += 1
            if f.capture_t_s > poses_until_s:
                continue
            pos, q = f.pos_w_m, f.q_wb
            if f.capture_t_s > freeze_at_s:
                frozen = frozen or (pos.copy(), q.copy())
                j = int(np.searchsorted(sc.truth.t_s, f.capture_t_s))
                pos = frozen[0] + (f.pos_w_m - sc.truth.pos_w_m[j])   # the noise goes on
                q = frozen[1]
            est.update_pose(f.capture_t_s, pos, q)
        if cp is None and t >= checkpoint_at_s:
            cp = est.checkpoint()
    return inputs, cp


def _start(sc: sy.Scenario) -> Ukf:
    est = Ukf(EstimatorConfig())
    est.initialize(0.0, sc.truth.pos_w_m[0], sc.truth.q_wb[0], sc.truth.vel_w_m_s[0])
    return est


def test_that_dead_reckoning_from_a_checkpoint_replays_the_filter_exactly() -> None:
    # Fixture: poses until 2 s, a checkpoint at 2 s, the IMU alone after
    sc = _scenario(seed=11)
    est = _start(sc)
    inputs, cp = _fly(est, sc, poses_until_s=2.0 - 0.011, checkpoint_at_s=2.0)
    assert cp is not None
    live = est.estimate()
    # Test
    replayed = est.dead_reckon_from(cp, inputs)
    # Assert: the same samples through the same code: the same estimate
    after = est.estimate()
    assert replayed == sum(1 for t, *_ in inputs if t > cp.t_s)
    np.testing.assert_array_equal(after.pos_w_m, live.pos_w_m)
    np.testing.assert_array_equal(after.vel_w_m_s, live.vel_w_m_s)
    np.testing.assert_array_equal(after.q_wb, live.q_wb)
    # the checkpoint stays usable: twice gives the same again
    est.dead_reckon_from(cp, inputs)
    np.testing.assert_array_equal(est.estimate().pos_w_m, live.pos_w_m)


def test_that_dead_reckoning_from_before_a_freeze_undoes_what_the_frozen_poses_did() -> None:
    # Fixture: the tracker freezes at 2 s and streams that pose (with its noise) to 4 s while
    # the vehicle moves on (lively: up to ~0.5 m/s); the filter fuses what it can, refuses,
    # re-seeds on it
    sc = _scenario(seed=12)
    est = _start(sc)
    inputs, cp = _fly(est, sc, freeze_at_s=2.0, checkpoint_at_s=1.8)
    assert cp is not None
    truth_end = sc.truth.pos_w_m[-1]
    pinned_m = float(np.linalg.norm(est.estimate().pos_w_m - truth_end))
    # Test
    est.dead_reckon_from(cp, inputs)
    # Assert: 2.2 s on the IMU alone, started from the truth's estimate: within centimetres,
    # where the frozen poses held the estimate decimetres off
    dead_reckoned_m = float(np.linalg.norm(est.estimate().pos_w_m - truth_end))
    assert pinned_m > 0.1
    assert dead_reckoned_m < 0.02
    assert est.health().resets >= 1   # the counters go on counting what happened


def test_that_a_bias_the_checkpoint_had_not_settled_is_taken_from_now() -> None:
    # Fixture: a checkpoint at start-up (the biases' initial uncertainty) and one 3.5 s later,
    # poses all the way (the biases settle)
    sc = _scenario(seed=13)
    est = _start(sc)
    early = est.checkpoint()
    inputs, late = _fly(est, sc, checkpoint_at_s=3.5)
    assert late is not None
    now = est.estimate()
    # Test / Assert: from the early one, the biases of now (the replay's predictions leave a
    # bias as it is, to rounding)
    est.dead_reckon_from(early, inputs)
    bias = est.estimate()
    np.testing.assert_allclose(bias.gyro_bias_rad_s, now.gyro_bias_rad_s, rtol=0, atol=1e-12)
    np.testing.assert_allclose(bias.accel_bias_m_s2, now.accel_bias_m_s2, rtol=0, atol=1e-12)
    # from the late one (settled): its own, which now's differ from (0.5 s more of poses)
    est.dead_reckon_from(late, inputs)
    x_late = late.state["_x"]
    assert isinstance(x_late, np.ndarray)
    np.testing.assert_allclose(est.estimate().gyro_bias_rad_s, x_late[GYRO_BIAS], rtol=0,
                               atol=1e-12)
    np.testing.assert_allclose(est.estimate().accel_bias_m_s2, x_late[ACCEL_BIAS], rtol=0,
                               atol=1e-12)
    assert np.abs(x_late[ACCEL_BIAS] - now.accel_bias_m_s2).max() > 1e-9

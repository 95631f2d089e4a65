"""MoCap against the IMU alone (estimator.consistency), on synthetic truth with the paper's
sensor class: agreement on lively motion, a frozen tracker found, what the biases and the
windows do, hostile input."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from estimator.consistency import MAX_PENDING_IMU, WINDOW_S, Comparison, ConsistencyMonitor
from estimator.synthetic import (
    PAPER_IMU,
    PAPER_MOCAP,
    MocapFrame,
    Scenario,
    lively,
    make_scenario,
    roll_sine,
)
from groundstation.loop import (
    MONITOR_PERSIST_S,
    MONITOR_ROTATION_DEG,
    MONITOR_VELOCITY_M_S,
)

G = 9.81


def feed(sc: Scenario, frames: list[MocapFrame] | None = None,
         gyro_bias: tuple[float, float, float] = PAPER_IMU.gyro_bias_rad_s,
         accel_bias: tuple[float, float, float] = PAPER_IMU.accel_bias_m_s2,
         clean_since_s: float = -math.inf,
         monitor: ConsistencyMonitor | None = None) -> list[Comparison]:
    """The loop's order: every IMU sample as it comes, each frame when it arrives."""
    m = monitor or ConsistencyMonitor(G)
    t = sc.truth.t_s
    out: list[Comparison] = []
    k = 0
    for f in frames if frames is not None else sc.frames:
        while k < len(t) and t[k] <= f.arrival_t_s:
            m.add_imu(float(t[k]), tuple(sc.gyro_rad_s[k].tolist()),
                      tuple(sc.accel_m_s2[k].tolist()))
            k += 1
        c = m.add_pose(f.capture_t_s, tuple(f.pos_w_m.tolist()), tuple(f.q_wb.tolist()),
                       gyro_bias, accel_bias, accel_clean_since_s=clean_since_s)
        if c is not None:
            out.append(c)
    return out


@pytest.fixture(scope="module")
def lively_run() -> Scenario:
    # Exp. 2a's 0.6 m lateral sine plus motion on every other axis, 12 s
    return make_scenario(lively(), 12.0, PAPER_IMU, PAPER_MOCAP, seed=5)


def test_mocap_and_the_imu_agree_on_lively_motion(lively_run: Scenario) -> None:
    out = feed(lively_run)
    # from one horizon plus a window on, about every frame is compared
    assert len(out) > 0.95 * (len(lively_run.frames) - 120)
    rot = np.array([c.rotation_deg for c in out])
    gap = np.array([c.velocity_gap_m_s for c in out])
    # MoCap's noise (0.115 deg, 0.5 mm) over 20-pose windows and the IMU's white noise over
    # 1 s: the loop's limits are about twice the largest of 1000 comparisons
    assert rot.max() < 0.6 * MONITOR_ROTATION_DEG
    assert gap.max() < 0.6 * MONITOR_VELOCITY_M_S
    assert all(abs(c.t_s - c.start_s - (1.0 + 0.5 * WINDOW_S)) < 0.02 for c in out)


def test_a_tracker_that_freezes_is_seen_within_a_fraction_of_the_horizon(
        lively_run: Scenario) -> None:
    t_freeze = 6.0
    rng = np.random.default_rng(1)
    frozen = next(f for f in lively_run.frames if f.capture_t_s >= t_freeze)
    frames = [f if f.capture_t_s < t_freeze else
              replace(f, pos_w_m=frozen.pos_w_m + rng.normal(0.0, 5e-4, 3))
              for f in lively_run.frames]
    out = feed(lively_run, frames)
    before = [c for c in out if c.t_s < t_freeze]
    assert max(c.rotation_deg for c in before) < MONITOR_ROTATION_DEG
    bad = [c for c in out if c.t_s >= t_freeze and (c.rotation_deg > MONITOR_ROTATION_DEG
                                                     or c.velocity_gap_m_s > MONITOR_VELOCITY_M_S)]
    # the lateral sine accelerates at up to 1.7 m/s^2: 0.06 m/s of it within ~0.1 s
    assert bad and bad[0].t_s - t_freeze < 0.2
    # and it stays seen while the vehicle keeps moving
    late = [c for c in out if c.t_s > t_freeze + 0.3]
    assert sum(c.velocity_gap_m_s > MONITOR_VELOCITY_M_S for c in late) > 0.9 * len(late)


def test_the_gyro_bias_is_taken_out_and_matters() -> None:
    sc = make_scenario(roll_sine(), 6.0, PAPER_IMU, PAPER_MOCAP, seed=2)
    right = [c.rotation_deg for c in feed(sc)]
    wrong = [c.rotation_deg for c in feed(sc, gyro_bias=(0.0, 0.0, 0.0))]
    # an unknown bias of |(5, -8, 6)| mrad/s turns the gyro's frame 0.64 deg per second
    expected_deg = math.degrees(float(np.linalg.norm(PAPER_IMU.gyro_bias_rad_s)))
    assert float(np.median(right)) < 0.1
    assert float(np.median(wrong)) == pytest.approx(expected_deg, rel=0.15)


def test_the_accelerometer_bias_is_taken_out_and_matters() -> None:
    sc = make_scenario(roll_sine(), 6.0, PAPER_IMU, PAPER_MOCAP, seed=3)
    right = [c.velocity_gap_m_s for c in feed(sc)]
    wrong = [c.velocity_gap_m_s for c in feed(sc, accel_bias=(0.0, 0.0, 0.0))]
    # |(0.05, -0.04, 0.06)| m/s^2 unknown: 0.088 m/s of velocity over the 1 s horizon
    expected = float(np.linalg.norm(PAPER_IMU.accel_bias_m_s2))
    assert float(np.median(right)) < 0.015
    assert float(np.median(wrong)) == pytest.approx(expected, rel=0.15)


def test_no_velocity_gap_over_a_horizon_that_had_an_imu_anomaly(lively_run: Scenario) -> None:
    out = feed(lively_run, clean_since_s=8.0)
    # the horizon's first window starts half a window before its mean time
    first_window_start = [(c.start_s - 0.5 * WINDOW_S, c) for c in out]
    assert all(math.isnan(c.velocity_gap_m_s) for s, c in first_window_start if s < 7.99)
    assert all(math.isfinite(c.velocity_gap_m_s) for s, c in first_window_start if s > 8.01)
    assert all(math.isfinite(c.rotation_deg) for c in out)


def test_a_mocap_jump_disagrees_for_one_window_only(lively_run: Scenario) -> None:
    """A marker swap that stays (a position step): the windows holding the step see a velocity
    spike, for a window's 0.2 s as the step enters the horizon and again as it leaves; shorter
    than the loop's MONITOR_PERSIST_S, so the UKF's re-seed judges it, not this."""
    t_jump = 5.0
    step_w_m = np.array([0.5, 0.0, 0.0])
    frames = [f if f.capture_t_s < t_jump else replace(f, pos_w_m=f.pos_w_m + step_w_m)
              for f in lively_run.frames]
    out = feed(lively_run, frames)
    runs: list[float] = []
    since = None
    for c in out:
        if c.velocity_gap_m_s > MONITOR_VELOCITY_M_S or c.rotation_deg > MONITOR_ROTATION_DEG:
            since = c.t_s if since is None else since
            runs.append(c.t_s - since)
        else:
            since = None
    assert runs, "the step is seen"
    assert max(runs) < MONITOR_PERSIST_S


def test_a_mocap_slower_than_25_hz_is_not_compared() -> None:
    """Fewer than 5 poses in a 0.2 s window: MoCap's velocity would be mostly noise."""
    sc = make_scenario(lively(), 5.0, PAPER_IMU, replace(PAPER_MOCAP, rate_hz=20.0), seed=1)
    assert feed(sc) == []
    sc = make_scenario(lively(), 5.0, PAPER_IMU, replace(PAPER_MOCAP, rate_hz=30.0), seed=1)
    assert len(feed(sc)) > 90


def test_a_long_mocap_outage_loses_no_imu_sample() -> None:
    """12 s without MoCap is more IMU samples than are kept pending: the oldest are
    integrated as they go, and the comparison agrees again after the outage."""
    sc = make_scenario(lively(), 18.0, PAPER_IMU, replace(PAPER_MOCAP, dropouts_s=((3.0, 15.0),)),
                       seed=4)
    assert 12.0 * PAPER_IMU.rate_hz > MAX_PENDING_IMU
    out = feed(sc)
    after = [c for c in out if c.t_s > 15.0]
    assert len(after) > 150
    assert max(c.rotation_deg for c in after) < 0.6 * MONITOR_ROTATION_DEG
    assert max(c.velocity_gap_m_s for c in after) < 0.6 * MONITOR_VELOCITY_M_S
    assert not [c for c in out if 3.0 < c.t_s < 15.0]


def test_a_pose_older_than_the_last_is_not_compared() -> None:
    m = ConsistencyMonitor(G)
    for k in range(600):
        m.add_imu(k * 0.002, (0.0, 0.0, 0.0), (0.0, 0.0, G))
    for k in range(120):
        m.add_pose(0.005 + k * 0.01, (0.0, 0.0, 1.0), (1.0, 0.0, 0.0, 0.0), (0, 0, 0), (0, 0, 0))
    assert m.add_pose(1.0, (0.0, 0.0, 1.0), (1.0, 0.0, 0.0, 0.0), (0, 0, 0), (0, 0, 0)) is None
    c = m.add_pose(1.195, (0.0, 0.0, 1.0), (1.0, 0.0, 0.0, 0.0), (0, 0, 0), (0, 0, 0))
    assert c is not None and c.rotation_deg < 1e-9 and c.velocity_gap_m_s < 1e-9


def test_rejects_a_window_as_long_as_its_horizon() -> None:
    with pytest.raises(ValueError):
        ConsistencyMonitor(G, horizon_s=0.1, window_s=0.1)


finite_or_not = st.floats(allow_nan=True, allow_infinity=True, width=64)


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(st.booleans(), finite_or_not, st.tuples(*[finite_or_not] * 3),
                          st.tuples(*[finite_or_not] * 4)), max_size=300))
def test_hostile_numbers_never_raise(events: list[tuple[bool, float, tuple[float, ...],
                                                        tuple[float, ...]]]) -> None:
    m = ConsistencyMonitor(G)
    for is_imu, t, v3, v4 in events:
        if is_imu:
            m.add_imu(t, v3, v3)
        else:
            m.add_pose(t, v3, v4, v3, v3, accel_clean_since_s=t)


_finite = st.floats(min_value=-1e3, max_value=1e3, allow_nan=False)


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(*[_finite] * 11), min_size=5, max_size=40), st.data())
def test_that_the_compiled_window_gives_the_bits_of_the_interpreted_one(
        rows: list[tuple[float, ...]], data: st.DataObject) -> None:
    from estimator import compiled

    if not compiled.AVAILABLE:
        pytest.skip("numba is not installed: the monitor runs the window interpreted")
    # distinct times (a slope needs a spread), any other values
    rows = [(float(k) * 0.01 + r[0] * 1e-6, *r[1:]) for k, r in enumerate(rows)]
    lo = data.draw(st.integers(0, len(rows) - 2))
    hi = data.draw(st.integers(lo + 2, len(rows)))
    arr = np.array(rows)
    fast, plain = np.empty(compiled.POSE_WIDTH), np.empty(compiled.POSE_WIDTH)
    with np.errstate(all="ignore"):
        compiled.window_stats.py_func(arr, lo, hi, plain)  # type: ignore[attr-defined]
        try:
            compiled.window_stats(arr, lo, hi, fast)
        except ZeroDivisionError:   # c summed to zero (never in the monitor: c is aligned)
            assert not np.isfinite(plain).all()
            return
    assert fast.tobytes() == plain.tobytes()


def test_that_the_monitor_compares_the_same_with_and_without_the_compiled_window(
        lively_run: Scenario, monkeypatch: pytest.MonkeyPatch) -> None:
    from estimator import compiled

    if not compiled.AVAILABLE:
        pytest.skip("numba is not installed: the monitor runs the Python window")
    fast = feed(lively_run)
    monkeypatch.setattr(compiled, "AVAILABLE", False)
    plain = feed(lively_run)
    assert len(fast) == len(plain) > 1000
    assert fast == plain      # every field of every comparison, exactly

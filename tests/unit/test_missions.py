"""Missions: segment kinematics, alpha profiles, the shipped experiments, config errors."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from config import available
from config.schema import ConfigError, load_config_text
from controller.missions import MISSION_SCHEMA, Mission, MissionSpec
from controller.reference import quat_to_rot
from groundstation.configs import load_mission

SHIPPED = available("missions")


def _mission(segments: str, start: str = "[0.0, 0.0, 0.1]") -> Mission:
    text = (f"schema: {MISSION_SCHEMA}\nversion: 1\nname: t\nstart_pos_w_m: {start}\n"
            f"segments:\n{segments}")
    return Mission(load_config_text(text, MissionSpec, schema=MISSION_SCHEMA))


def _check_derivatives(m: Mission, t0: float, t1: float) -> None:
    h = 1e-4
    t = t0
    while t < t1:
        r, rp, rm = m.reference(t), m.reference(t + h), m.reference(t - h)
        for i in range(3):
            assert r.vel_w_m_s[i] == pytest.approx(
                (rp.pos_w_m[i] - rm.pos_w_m[i]) / (2 * h), abs=1e-5)
            assert r.acc_w_m_s2[i] == pytest.approx(
                (rp.vel_w_m_s[i] - rm.vel_w_m_s[i]) / (2 * h), abs=1e-4)
        t += (t1 - t0) / 37.0


@pytest.mark.parametrize("name", SHIPPED)
def test_that_every_shipped_mission_loads_and_is_continuous(name: str) -> None:
    # Fixture
    m = Mission(load_mission(name))
    # Test / Assert: no jumps in position between consecutive ticks
    prev = m.reference(0.0).pos_w_m
    t = 0.002
    while t < m.duration_s + 1.0:
        p = m.reference(t).pos_w_m
        assert math.dist(p, prev) < 0.004  # < 2 m/s at 500 Hz
        prev = p
        t += 0.002
    assert m.reference(0.0).pos_w_m == m.start_pos_w_m
    assert m.reference(m.duration_s + 5.0).pos_w_m[2] < m.start_pos_w_m[2]  # landed, sunk


def test_that_the_paper_experiments_use_the_fixed_profiles() -> None:
    # Fixture
    e1 = Mission(load_mission("exp1-hover-tilt-steps"))
    e2a = Mission(load_mission("exp2a-sine-translation"))
    e2b = Mission(load_mission("exp2b-roll-sine"))
    t0 = e1.measured_interval_s()[0]  # type: ignore[index]
    # Assert: Exp. 1 alpha 0/30/0/30 for 10/20/20/20 s at the paper's position
    assert e1.measured_interval_s() == (10.0, 80.0)
    for dt, deg in ((5.0, 0.0), (15.0, 30.0), (35.0, 0.0), (65.0, 30.0)):
        r = e1.reference(t0 + dt)
        assert math.degrees(r.alpha_rad or 0.0) == pytest.approx(deg)
        assert r.pos_w_m == pytest.approx((-0.14, -0.05, 1.0))
        assert r.measured
    # Exp. 2a: 1 m/s peak speed, 1.67 m/s^2 peak acceleration, ramp 0 -> 30 over 10..50 s
    speeds = [abs(e2a.reference(t0 + 5 + k * 0.01).vel_w_m_s[0]) for k in range(7000)]
    accs = [abs(e2a.reference(t0 + 5 + k * 0.01).acc_w_m_s2[0]) for k in range(7000)]
    assert max(speeds) == pytest.approx(1.0, abs=0.01)
    assert max(accs) == pytest.approx(1.667, abs=0.01)
    assert math.degrees(e2a.reference(t0 + 30.0).alpha_rad or 0.0) == pytest.approx(15.0)
    # Exp. 2b: 6 deg roll peak at 0.1 Hz, fixed position
    r = e2b.reference(t0 + 2.5)
    rr = quat_to_rot(r.q_wr)
    assert math.degrees(math.atan2(rr[7], rr[8])) == pytest.approx(6.0, abs=1e-6)
    assert r.pos_w_m == pytest.approx((-0.08, -0.03, 1.0))


def test_that_goto_and_faded_sine_have_consistent_derivatives() -> None:
    # Fixture
    m = _mission("  - {kind: goto, duration_s: 3.0, pos_w_m: [1.0, -2.0, 1.5], yaw_deg: 30}\n"
                 "  - {kind: sine, duration_s: 10.0, axis: y, amplitude_m: 0.5,\n"
                 "     frequency_hz: 0.3, fade_in_s: 2.0, fade_out_s: 2.0}\n")
    # Test / Assert
    _check_derivatives(m, 0.01, 12.99)
    assert m.reference(3.0).pos_w_m == pytest.approx((1.0, -2.0, 1.5))
    assert m.reference(3.0).vel_w_m_s == pytest.approx((0.0, 0.0, 0.0), abs=1e-12)
    assert m.reference(13.0).vel_w_m_s == pytest.approx((0.0, 0.0, 0.0), abs=1e-12)


def test_that_the_attitude_sine_angular_velocity_matches_the_rotation() -> None:
    # Fixture
    m = _mission("  - {kind: attitude_sine, duration_s: 10.0, axis: pitch, amplitude_deg: 10,\n"
                 "     frequency_hz: 0.2}\n")
    h = 1e-5
    for t in (0.3, 1.7, 4.1):
        r0, r1 = quat_to_rot(m.reference(t).q_wr), quat_to_rot(m.reference(t + h).q_wr)
        # body rate from R^T dR/dt (skew part)
        d = [(b - a) / h for a, b in zip(r0, r1, strict=True)]
        wy = sum(r0[3 * k + 0] * d[3 * k + 2] for k in range(3))  # (R^T Rdot)_13
        # Assert
        assert m.reference(t).omega_r_rad_s[1] == pytest.approx(wy, abs=1e-4)


def test_that_segments_without_alpha_keep_the_previous_value_or_auto() -> None:
    # Fixture
    m = _mission("  - kind: hold\n    duration_s: 5\n"
                 "    alpha: {kind: ramp, from_deg: 0, to_deg: 20, start_s: 1, end_s: 3}\n"
                 "  - {kind: hold, duration_s: 5}\n"
                 "  - kind: hold\n    duration_s: 5\n    alpha: {kind: auto}\n"
                 "  - {kind: hold, duration_s: 5}\n")
    # Assert
    assert math.degrees(m.reference(2.0).alpha_rad or 0.0) == pytest.approx(10.0)
    assert math.degrees(m.reference(7.0).alpha_rad or 0.0) == pytest.approx(20.0)
    assert m.reference(12.0).alpha_rad is None
    assert m.reference(17.0).alpha_rad is None
    assert m.auto_profile(17.0) is not None


def test_that_the_lateral_demand_of_a_roll_is_the_weight_component() -> None:
    # Fixture: hold rolled by 6 deg -> m g sin(6 deg) lateral in the body frame
    m = _mission("  - {kind: attitude_sine, duration_s: 10.0, axis: roll, amplitude_deg: 6,\n"
                 "     frequency_hz: 0.1}\n")
    # Test
    demand = m.lateral_demand_n(0.0, 10.0, 3.1, 9.81, step_s=0.05)
    # Assert
    assert demand == pytest.approx(3.1 * 9.81 * math.sin(math.radians(6.0)), rel=1e-3)


@pytest.mark.parametrize(("segments", "key"), [
    ("  - {kind: spin, duration_s: 1}\n", "segments[0].kind"),
    ("  - {kind: hold, duration_s: -1}\n", "segments[0].duration_s"),
    ("  - kind: hold\n    duration_s: 1\n    alpha: {kind: steps, times_s: [0, 1],"
     " values_deg: [0]}\n", "segments[0].alpha.values_deg"),
    ("  - {kind: sine, duration_s: 2, axis: w, amplitude_m: 1, frequency_hz: 1}\n",
     "segments[0].axis"),
])
def test_that_bad_missions_are_refused_naming_the_key(segments: str, key: str) -> None:
    with pytest.raises(ConfigError) as err:
        _mission(segments)
    assert err.value.key == key


@pytest.mark.parametrize(("segments", "start", "line", "key", "message"), [
    # a takeoff that does not climb above where it starts
    ("  - {kind: takeoff, duration_s: 3, height_m: 0.12}\n", "[0.0, 0.0, 0.1]", 6,
     "segments[0].height_m", "must be above where the takeoff starts (z = 0.1 m) by >= 0.05 m, "
     "got 0.12"),
    ("  - {kind: goto, duration_s: 5, pos_w_m: [0, 0, 2]}\n"
     "  - {kind: takeoff, duration_s: 3, height_m: 1.5}\n", "[0.0, 0.0, 0.1]", 7,
     "segments[1].height_m", "must be above where the takeoff starts (z = 2 m) by >= 0.05 m, "
     "got 1.5"),
    # alpha timings outside their segment never happen
    ("  - kind: hold\n    duration_s: 5\n    alpha: {kind: steps, times_s: [0, 7],"
     " values_deg: [0, 10]}\n", "[0.0, 0.0, 0.1]", 8, "segments[0].alpha.times_s",
     "a step at 7 s never happens in a segment of 5 s"),
    # minimum-jerk peak speed 1.875 d / T = 1.875 * 10 / 1 = 18.75 m/s
    ("  - {kind: goto, duration_s: 1, pos_w_m: [10, 0, 0.1]}\n", "[0.0, 0.0, 0.1]", 6,
     "segments[0].pos_w_m", "a 10 m move in 1 s peaks at 18.8 m/s and 57.7 m/s^2; expected <= "
     "10 m/s and 9.81 m/s^2 (a longer duration_s)"),
    # A (2 pi f)^2 = 0.5 * (2 pi)^2 = 19.7 m/s^2
    ("  - {kind: sine, duration_s: 5, axis: x, amplitude_m: 0.5, frequency_hz: 1}\n",
     "[0.0, 0.0, 0.1]", 6, "segments[0].amplitude_m",
     "peak acceleration A (2 pi f)^2 = 19.7 m/s^2; expected <= 9.81 m/s^2"),
    # a land that touches down at 0.42 m/s (the old short hover's 0.75 m in 1.5 s): the
    # estimator does not see the impact, and such a flight ends in the MoCap/IMU failsafe
    ("  - {kind: takeoff, duration_s: 2, height_m: 0.8}\n"
     "  - {kind: land, duration_s: 1.5}\n", "[0.0, 0.0, 0.1]", 7, "segments[1].duration_s",
     "this land touches down (passes the start height) at 0.416 m/s; expected <= 0.18 m/s, as "
     "the estimator does not see a harder impact (a longer duration_s or a smaller sink_m)"),
    # a start 1e9 m away is outside any workspace
    ("  - {kind: hold, duration_s: 1}\n", "[1e9, 0.0, 0.1]", 4, "start_pos_w_m[0]",
     "expected a number >= -100 and <= 100, got 1000000000.0"),
])
def test_that_physically_impossible_missions_are_refused_at_their_line(
        segments: str, start: str, line: int, key: str, message: str) -> None:
    with pytest.raises(ConfigError) as err:
        _mission(segments, start=start)
    assert (err.value.line, err.value.key, err.value.message) == (line, key, message)


def test_that_the_extents_cover_each_segment_and_the_alphas_are_listed() -> None:
    # Fixture
    from controller.missions import explicit_alphas_deg, segment_extents_w_m

    text = (f"schema: {MISSION_SCHEMA}\nversion: 1\nname: t\nstart_pos_w_m: [0.0, 0.0, 0.1]\n"
            "segments:\n  - {kind: takeoff, duration_s: 3, height_m: 1.0,\n"
            "     alpha: {kind: constant, value_deg: 5}}\n"
            "  - {kind: sine, duration_s: 10, axis: y, amplitude_m: 0.4, frequency_hz: 0.2,\n"
            "     alpha: {kind: ramp, from_deg: 0, to_deg: 20, end_s: 4}}\n"
            "  - {kind: goto, duration_s: 5, pos_w_m: [1.0, -1.0, 1.5]}\n")
    spec_ = load_config_text(text, MissionSpec, schema=MISSION_SCHEMA)
    # Test
    extents = segment_extents_w_m(spec_)
    alphas = explicit_alphas_deg(spec_)
    # Assert
    assert extents[0] == ((0.0, 0.0, 0.1), (0.0, 0.0, 1.0))
    assert extents[1] == ((0.0, -0.4, 1.0), (0.0, 0.4, 1.0))
    assert extents[2][0] == pytest.approx((0.0, -1.0, 1.0))
    assert extents[2][1] == pytest.approx((1.0, 0.0, 1.5), abs=1e-9)
    assert alphas == [("segments[0].alpha.value_deg", 5.0), ("segments[1].alpha.from_deg", 0.0),
                      ("segments[1].alpha.to_deg", 20.0)]


def test_that_a_climb_beyond_the_vehicles_thrust_is_refused() -> None:
    # Fixture: 0.9 m in 0.75 s peaks at 5.77 * 0.9 / 0.75^2 = 9.2 m/s^2 (under the mission's
    # own 1 g cap); fasthex lifts 0.9 * 61.8 N / 3.1 kg - g = 8.1 m/s^2 at most
    from groundstation.configs import check_mission_against_vehicle, load_vehicle

    text = (f"schema: {MISSION_SCHEMA}\nversion: 1\nname: t\nstart_pos_w_m: [0.0, 0.0, 0.1]\n"
            "segments:\n  - {kind: takeoff, duration_s: 0.75, height_m: 1.0}\n")
    lines: dict[str, int] = {}
    spec_ = load_config_text(text, MissionSpec, schema=MISSION_SCHEMA, lines=lines)
    # Test
    with pytest.raises(ConfigError) as err:
        check_mission_against_vehicle(spec_, load_vehicle("fasthex"), "m.yaml", lines)
    # Assert
    assert str(err.value) == (
        "m.yaml:6: segments[0].duration_s: the reference accelerates vertically at 9.24 m/s^2; "
        "vehicle 'fasthex' manages 8.13 m/s^2 up and 9.32 m/s^2 down (a longer duration_s)")
    # the same climb in 1 s (5.2 m/s^2) is within reach
    slow = load_config_text(text.replace("duration_s: 0.75", "duration_s: 1.0"), MissionSpec,
                            schema=MISSION_SCHEMA)
    check_mission_against_vehicle(slow, load_vehicle("fasthex"), "m.yaml", lines)


@pytest.mark.parametrize(("height_m", "sink_m", "duration_s"), [
    (0.5, 0.1, 5.0), (0.7, 0.05, 4.0), (0.9, 0.05, 6.0), (0.3, 0.2, 6.0), (2.0, 0.01, 4.0)])
def test_that_the_touchdown_speed_is_the_references_descent_rate_at_the_start_height(
        height_m: float, sink_m: float, duration_s: float) -> None:
    # Fixture: a land from height_m above the start, sampled every 0.1 ms
    from controller.missions import touchdown_speed_m_s

    start_z = 0.1
    m = _mission(f"  - {{kind: goto, duration_s: 10, pos_w_m: [0, 0, {start_z + height_m}]}}\n"
                 f"  - {{kind: land, duration_s: {duration_s}, sink_m: {sink_m}}}\n")
    # Test
    speed = touchdown_speed_m_s(height_m, sink_m, duration_s)
    # Assert: equal to the reference's own descent rate where it crosses the start height
    t = 10.0
    while m.reference(t).pos_w_m[2] > start_z:
        t += 1e-4
    assert speed == pytest.approx(-m.reference(t).vel_w_m_s[2], rel=2e-3)
    assert touchdown_speed_m_s(height_m, 0.0, duration_s) == 0.0  # aims at the start: at rest
    assert touchdown_speed_m_s(0.0, sink_m, duration_s) == 0.0    # starts on the ground


def test_that_every_shipped_mission_touches_down_gently() -> None:
    from controller.missions import MAX_TOUCHDOWN_SPEED_M_S

    for name in SHIPPED:
        m = Mission(load_mission(name))
        start_z, t, fastest = m.start_pos_w_m[2], 0.0, 0.0
        while t < m.duration_s:  # every crossing of the start height, going down
            ref = m.reference(t)
            if abs(ref.pos_w_m[2] - start_z) < 2e-3 and ref.vel_w_m_s[2] < 0.0:
                fastest = max(fastest, -ref.vel_w_m_s[2])
            t += 1e-3
        assert 0.0 < fastest <= MAX_TOUCHDOWN_SPEED_M_S, (name, fastest)


def test_that_a_touch_and_go_is_not_taken_for_a_reference_below_the_ground(
        tmp_path: Path) -> None:
    # Fixture: land, then take off again: the second take-off starts where the first landing
    # rests, its sink_m (5 cm) under the start height; the below-ground check refused it
    path = tmp_path / "touch-and-go.yaml"
    path.write_text(f"schema: {MISSION_SCHEMA}\nversion: 1\nname: t\n"
                    "start_pos_w_m: [0.0, 0.0, 0.1]\nsegments:\n"
                    + "  - {kind: takeoff, duration_s: 3.0, height_m: 0.8}\n"
                      "  - {kind: hold, duration_s: 2.0}\n"
                      "  - {kind: land, duration_s: 4.0}\n" * 2)
    # Test / Assert: it loads, and both take-offs fly
    m = Mission(load_mission(path))
    assert m.reference(9.0 + 3.0).pos_w_m[2] == pytest.approx(0.8, abs=1e-6)

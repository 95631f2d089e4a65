"""The mission kinds of circle, lissajous, waypoints, ramp, trajectory (CSV) and the attitude
block: exact derivatives, rest at the ends, limits, CSV errors, the pre-flight check."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from config.schema import ConfigError, load_config_text
from controller.missions import MISSION_SCHEMA, Mission, MissionSpec
from controller.preflight import lateral_force_shortfalls
from controller.reference import quat_to_rot
from groundstation.configs import load_mission, load_vehicle, preflight_warnings

PARAMS = load_vehicle("fasthex")
HEAD = f"schema: {MISSION_SCHEMA}\nversion: 1\nname: t\nstart_pos_w_m: [0.0, 0.0, 1.0]\n"


def _mission(segments: str) -> Mission:
    return Mission(load_config_text(HEAD + "segments:\n" + segments, MissionSpec,
                                    schema=MISSION_SCHEMA))


def _check_derivatives(m: Mission, seg: int) -> None:
    """Central differences of p, v and R agree with the analytic v, a and body rate."""
    t0, t1 = m.segment_bounds_s(seg)
    h = 1e-5
    for t in np.linspace(t0 + 2 * h, t1 - 2 * h, 301):
        r, rp, rm = m.reference(t), m.reference(t + h), m.reference(t - h)
        for i in range(3):
            assert r.vel_w_m_s[i] == pytest.approx(
                (rp.pos_w_m[i] - rm.pos_w_m[i]) / (2 * h), abs=1e-6)
            assert r.acc_w_m_s2[i] == pytest.approx(
                (rp.vel_w_m_s[i] - rm.vel_w_m_s[i]) / (2 * h), abs=1e-5)
        rot = np.array(quat_to_rot(r.q_wr)).reshape(3, 3)
        d_rot = (np.array(quat_to_rot(rp.q_wr)) - np.array(quat_to_rot(rm.q_wr))).reshape(3, 3)
        w_hat = rot.T @ d_rot / (2 * h)  # R^T dR/dt = [w]x
        assert (w_hat[2, 1], w_hat[0, 2], w_hat[1, 0]) == pytest.approx(r.omega_r_rad_s,
                                                                          abs=1e-5)


def _at_rest(m: Mission, seg: int) -> None:
    for t in m.segment_bounds_s(seg):
        r = m.reference(t)
        assert max(map(abs, r.vel_w_m_s)) < 1e-9


def test_that_a_circle_has_its_radius_speed_and_rests_at_both_ends() -> None:
    # Fixture
    m = _mission("  - {kind: circle, duration_s: 14, radius_m: 0.5, period_s: 6,"
                 " fade_in_s: 2, fade_out_s: 2}\n")
    # Test / Assert: centre 0.5 m along +x of the start, full rate between the fades
    _check_derivatives(m, 0)
    _at_rest(m, 0)
    for t in (3.0, 7.0, 11.0):
        r = m.reference(t)
        assert math.hypot(r.pos_w_m[0] - 0.5, r.pos_w_m[1]) == pytest.approx(0.5, abs=1e-12)
        assert math.hypot(*r.vel_w_m_s) == pytest.approx(0.5 * 2 * math.pi / 6, rel=1e-9)
        assert math.hypot(*r.acc_w_m_s2) == pytest.approx(0.5 * (2 * math.pi / 6) ** 2)
        assert r.pos_w_m[2] == 1.0


def test_that_a_circle_with_a_centre_and_speed_turns_clockwise_in_a_vertical_plane() -> None:
    m = _mission("  - {kind: circle, duration_s: 10, centre_w_m: [0.0, 0.0, 1.4],"
                 " speed_m_s: 0.4, plane: xz, direction: cw}\n")
    _check_derivatives(m, 0)
    r = m.reference(5.0)
    assert r.pos_w_m[1] == 0.0 and math.hypot(*r.vel_w_m_s) == pytest.approx(0.4)
    # cw turns from z towards x: at the bottom (where it starts) it moves along -x
    assert m.reference(2.1).vel_w_m_s[0] < 0.0


def test_that_a_figure_eight_follows_its_amplitudes_and_returns_to_rest() -> None:
    m = _mission("  - {kind: lissajous, duration_s: 16, amplitudes_m: [0.6, 0.3, 0.1],"
                 " frequencies_hz: [0.125, 0.25, 0.25], phases_deg: [0, 0, 90]}\n")
    _check_derivatives(m, 0)
    _at_rest(m, 0)
    assert m.reference(16.0).pos_w_m == pytest.approx((0.0, 0.0, 1.0))
    r = m.reference(6.0)  # full amplitude: x = 0.6 sin(2 pi 0.125 6), y = 0.3 sin(3 pi)
    assert r.pos_w_m[0] == pytest.approx(0.6 * math.sin(1.5 * math.pi))
    assert r.pos_w_m[1] == pytest.approx(0.0, abs=1e-12)


def test_that_waypoints_pass_every_point_at_rest_within_the_limits() -> None:
    m = _mission("  - {kind: waypoints, points_w_m: [[1, 0, 1], [1, 1, 1.5], [0, 0, 1]],"
                 " yaw_deg: [0, 90, 0], max_speed_m_s: 0.5, max_accel_m_s2: 0.4, dwell_s: 1}\n")
    _check_derivatives(m, 0)
    c = m._segments[0]
    speeds, accels = [], []
    for t in np.linspace(0.0, c.duration, 4001):
        r = m.reference(t)
        speeds.append(math.hypot(*r.vel_w_m_s))
        accels.append(math.hypot(*r.acc_w_m_s2))
    assert max(speeds) <= 0.5 + 1e-9 and max(accels) <= 0.4 + 1e-9
    assert max(max(speeds), 0.0) == pytest.approx(0.5, rel=0.01)  # the longest legs hit a cap
    for leg, point in zip(c.path.legs, [(1, 0, 1), (1, 1, 1.5), (0, 0, 1)], strict=True):  # type: ignore[union-attr]
        r = m.reference(leg.t0_s + leg.move_s)
        assert r.pos_w_m == pytest.approx(point) and math.hypot(*r.vel_w_m_s) < 1e-9


def test_that_a_smoothed_ramp_cruises_at_constant_velocity_with_bounded_acceleration() -> None:
    m = _mission("  - {kind: ramp, duration_s: 6, pos_w_m: [1.0, 0.5, 1.0], yaw_deg: 45,"
                 " smooth_s: 1}\n")
    _check_derivatives(m, 0)
    _at_rest(m, 0)
    v_cruise = math.hypot(1.0, 0.5) / 5.0  # distance / (T - smooth_s)
    assert math.hypot(*m.reference(3.0).vel_w_m_s) == pytest.approx(v_cruise)
    assert m.reference(3.0).acc_w_m_s2 == pytest.approx((0.0, 0.0, 0.0), abs=1e-12)
    assert m.reference(3.0).omega_r_rad_s[2] == pytest.approx(math.radians(45) / 5.0)
    peak = max(math.hypot(*m.reference(t).acc_w_m_s2) for t in np.linspace(0, 6, 3001))
    assert peak == pytest.approx(v_cruise * 1.875, rel=1e-3)  # V * max s' / smooth_s
    assert m.reference(6.0).pos_w_m == pytest.approx((1.0, 0.5, 1.0))


def test_that_an_attitude_block_rides_on_a_translation_and_blends_out() -> None:
    m = _mission("  - kind: ramp\n    duration_s: 8\n    pos_w_m: [1.0, 0.0, 1.0]\n"
                 "    smooth_s: 1\n    attitude:\n      pitch_deg: 5\n      roll_deg: -3\n"
                 "      blend_s: 2\n      sine: {axis: roll, amplitude_deg: 4,"
                 " frequency_hz: 0.5, fade_in_s: 1, fade_out_s: 1}\n")
    _check_derivatives(m, 0)
    r = m.reference(4.0)  # offsets in full, sine at sin(4 pi) = 0
    assert r.q_wr == pytest.approx(quat_from_zyx(-3.0, 5.0, 0.0), abs=1e-12)
    assert m.reference(8.0).q_wr == pytest.approx((1.0, 0.0, 0.0, 0.0), abs=1e-12)
    assert m.reference(4.0).pos_w_m == _mission(
        "  - {kind: ramp, duration_s: 8, pos_w_m: [1.0, 0.0, 1.0], smooth_s: 1}\n"
    ).reference(4.0).pos_w_m


def quat_from_zyx(roll_deg: float, pitch_deg: float, yaw_deg: float) -> tuple[float, ...]:
    from controller.reference import quat_from_euler_zyx
    return quat_from_euler_zyx(*map(math.radians, (roll_deg, pitch_deg, yaw_deg)))


@pytest.mark.parametrize(("segment", "key"), [
    ("{kind: circle, duration_s: 10, radius_m: 2, period_s: 1}", "segments[0].period_s"),
    ("{kind: circle, duration_s: 10, radius_m: 1, period_s: 5, speed_m_s: 1}",
     "segments[0].period_s"),
    ("{kind: circle, duration_s: 10, centre_w_m: [0, 1, 2], period_s: 5}",
     "segments[0].centre_w_m"),
    ("{kind: lissajous, duration_s: 10, amplitudes_m: [3, 0, 0], frequencies_hz: [1, 0, 0]}",
     "segments[0].amplitudes_m"),
    ("{kind: lissajous, duration_s: 3, amplitudes_m: [1, 0, 0], frequencies_hz: [0.1, 0, 0]}",
     "segments[0].fade_in_s"),
    ("{kind: waypoints, points_w_m: [[1, 0, 1]], yaw_deg: [0, 1]}", "segments[0].yaw_deg"),
    ("{kind: ramp, duration_s: 2, pos_w_m: [30, 0, 1]}", "segments[0].duration_s"),
    ("{kind: ramp, duration_s: 2}", "segments[0].pos_w_m"),
    ("{kind: ramp, duration_s: 2, yaw_deg: 10, smooth_s: 1}", "segments[0].smooth_s"),
    ("{kind: hold, duration_s: 2, attitude: {roll_deg: 5, blend_s: 1.5}}",
     "segments[0].attitude.blend_s"),
])
def test_that_bad_new_segments_are_refused_naming_the_key(segment: str, key: str) -> None:
    with pytest.raises(ConfigError) as err:
        _mission(f"  - {segment}\n")
    assert err.value.key == key


# -- trajectory CSV ---------------------------------------------------------------------------
GOOD_CSV = "t_s,x_m,y_m,z_m,yaw_deg,pitch_deg,roll_deg,alpha_deg\n" + "".join(
    f"{t:.1f},{0.4 * math.sin(math.pi * t / 8) ** 2:.6f},{0.1 * t / 8:.6f},1.0,"
    f"{10 * t / 8:.4f},0,0,{15 + t:.1f}\n" for t in np.arange(0.0, 8.01, 0.2))


#: the land after the trajectory (a mission to fly ends on the ground)
LAND_S = 4.0


def _write(tmp_path: Path, csv_text: str, origin: str = "start") -> Path:
    (tmp_path / "traj.csv").write_text(csv_text)
    mission = tmp_path / "m.yaml"
    mission.write_text(HEAD + "segments:\n  - {kind: trajectory, file: traj.csv, origin: "
                       f"{origin}}}\n  - {{kind: land, duration_s: {LAND_S}}}\n")
    return mission


def test_that_a_trajectory_file_is_splined_with_exact_derivatives(tmp_path: Path) -> None:
    m = Mission(load_mission(_write(tmp_path, GOOD_CSV)))
    assert m.duration_s == pytest.approx(8.0 + LAND_S)
    _check_derivatives(m, 0)
    _at_rest(m, 0)
    r = m.reference(4.0)  # a knot: the spline passes through the row
    assert r.pos_w_m == pytest.approx((0.4, 0.05, 1.0))
    assert r.alpha_rad == pytest.approx(math.radians(19.0))
    assert math.degrees(math.atan2(quat_to_rot(r.q_wr)[3], quat_to_rot(r.q_wr)[0])) == \
        pytest.approx(5.0)


@pytest.mark.parametrize(("mutate", "line", "column"), [
    (lambda rows: rows.__setitem__(5, rows[5].replace("0.8,", "0.5,", 1)), 6, "column 1 (t_s)"),
    (lambda rows: rows.__setitem__(3, "0.4,nan," + rows[3].split(",", 2)[2]), 4,
     "column 2 (x_m)"),
    (lambda rows: rows.__setitem__(0, rows[0].replace(",z_m", "")), 1, "column z_m"),
    (lambda rows: rows.__setitem__(0, rows[0] + ",speed"), 1, "column 9 (speed)"),
    # a 30 m jump in one row: the spline rings ahead of it and crosses the cap a few rows
    # early; the rows of the worst excess are named, the jump's (line 11 or the one before)
    (lambda rows: rows.__setitem__(10, "1.8,30.0," + rows[10].split(",", 2)[2]), range(10, 12),
     "column 2 (x_m), column 3 (y_m), column 4 (z_m)"),
])
def test_that_bad_trajectory_files_name_file_line_and_column(
        tmp_path: Path, mutate: object, line: int | range, column: str) -> None:
    rows = GOOD_CSV.splitlines()
    assert callable(mutate)
    mutate(rows)
    with pytest.raises(ConfigError) as err:
        load_mission(_write(tmp_path, "\n".join(rows) + "\n"))
    assert err.value.file.endswith("traj.csv")
    assert err.value.line in (line if isinstance(line, range) else (line,))
    assert err.value.key == column


def test_that_a_world_frame_trajectory_must_start_where_the_mission_is(tmp_path: Path) -> None:
    with pytest.raises(ConfigError) as err:
        load_mission(_write(tmp_path, GOOD_CSV.replace(",1.0,", ",1.5,"), origin="world"))
    assert err.value.key == "segments[0].origin" and err.value.file.endswith("m.yaml")


# -- pre-flight lateral-force check -----------------------------------------------------------
def test_that_the_lateral_force_warning_names_the_span_beyond_the_tilt() -> None:
    # Fixture: a 1 m circle at 4 s per turn needs m r w^2 = 3.1 * 2.47 = 7.7 N; 10 deg gives
    # 0.8 * 2.6 = 2.1 N. Full rate from 2 s to 12 s after the segment start (t = 1 s).
    m = _mission("  - {kind: hold, duration_s: 1, alpha: {kind: constant, value_deg: 10}}\n"
                 "  - {kind: circle, duration_s: 14, radius_m: 1, period_s: 4}\n"
                 "  - {kind: hold, duration_s: 2}\n")
    # Test
    spans = lateral_force_shortfalls(m, PARAMS)
    lines = preflight_warnings(m, PARAMS)
    # Assert: one span in the circle, from when the fading rate crosses the bound to when it
    # falls back below it
    assert len(spans) == 1 and spans[0].segment == 1 and not spans[0].accepted
    bound = spans[0].bound_at_peak_n
    w_cross = math.sqrt(bound / (PARAMS.mass_kg * 1.0)) / (2 * math.pi / 4)  # e(t) at crossing
    assert 0.0 < w_cross < 1.0
    assert 1.0 < spans[0].start_s < 3.0 and 13.0 < spans[0].end_s < 15.0
    assert spans[0].peak_demand_n == pytest.approx(PARAMS.mass_kg * (2 * math.pi / 4) ** 2,
                                                   rel=0.05)
    assert "warning" in lines[0] and f"{spans[0].start_s:.2f}-{spans[0].end_s:.2f} s" in lines[1]


def test_that_the_warning_stays_quiet_at_enough_tilt() -> None:
    m = _mission("  - {kind: hold, duration_s: 3, alpha: {kind: constant, value_deg: 30}}\n"
                 "  - {kind: circle, duration_s: 14, radius_m: 1, period_s: 6}\n")
    assert lateral_force_shortfalls(m, PARAMS) == []


@pytest.mark.parametrize("name", ["exp1-hover-tilt-steps", "exp2a-sine-translation",
                                  "exp2a-sine-translation-auto", "exp2b-roll-sine",
                                  "demo-circle", "demo-figure-eight", "demo-waypoints",
                                  "demo-ramp-pitched", "demo-trajectory"])
def test_that_no_shipped_mission_warns(name: str) -> None:
    m = Mission(load_mission(name, vehicle=PARAMS))
    assert preflight_warnings(m, PARAMS) == []


def test_that_a_trajectory_tilt_beyond_the_vehicle_is_named_at_its_csv_row(
        tmp_path: Path) -> None:
    # Fixture: the row at t = 4 s (line 22: the header, then a row every 0.2 s) asks 40 deg of
    # a vehicle that tilts to 35 deg; the error named the mission's `file:` line
    rows = GOOD_CSV.splitlines()
    assert rows[21].startswith("4.0,")
    rows[21] = rows[21].rsplit(",", 1)[0] + ",40.0"
    mission = _write(tmp_path, "\n".join(rows) + "\n")
    # Test
    with pytest.raises(ConfigError) as err:
        load_mission(mission, vehicle=PARAMS)
    # Assert: the CSV's file, line and column
    assert err.value.file == str(tmp_path / "traj.csv")
    assert (err.value.line, err.value.key) == (22, "column 8 (alpha_deg)")
    assert err.value.message == ("40 deg is outside vehicle 'fasthex''s tilt (a tilt range of "
                                 f"0..{PARAMS.tilt.max_tilt_deg:g} deg)")

"""The preflight check table of the loop (``FlightLoop._preflight``) at the edges of each check:
the IMU rate exactly at 80 % (lockstep from sequence numbers, realtime from the wall clock),
the clock-sync line, every servo case (no reading, no goal yet, off its goal by exactly 1 deg,
not answering), the newest pose exactly 0.1 s old, an uninitialised estimator that reports no
flag, the vehicle exactly at the start-offset limit.

The flights of tests/integration/test_failsafes.py refuse on each check through the byte path;
these pin the boundaries and the values the operator reads, which a flight rarely lands on.
"""

from __future__ import annotations

import math
from types import SimpleNamespace
from typing import Any

import pytest

from controller.reference import VehicleState
from drivers.dynamixel.device import ServoHealth
from estimator.types import HealthFlag
from groundstation.loop import FlightLoop, LoopOptions

IMU = "flight-ctrl streaming IMU at 80-125 % of the set rate"
SERVO = "servo answers, multi-turn, at the commanded angle"
MOCAP = "MoCap sees the body at >= 80 % of its rate"
ESTIMATOR = "estimator converged"
START = "vehicle at the mission's start position"
START_POS_W_M = (0.0, 0.0, 0.1)
NO_READING = object()  # the servo never answered: the loop passes None


def _servo(*, ok: bool = True, tilt_deg: float = 0.0, goal_deg: float = 0.0) -> Any:
    return SimpleNamespace(ok=ok, tilt_rad=math.radians(tilt_deg),
                           goal_tilt_rad=math.radians(goal_deg),
                           health=ServoHealth.OK if ok else ServoHealth.NO_REPLY)


def _checks(*, lockstep: bool = True, rate_fraction: float = 1.0, wall_rate_hz: float = 500.0,
            clock_known: bool = False, servo: Any = None, pose_age_s: float = 0.01,
            mocap_rate_hz: float = 100.0, initialized: bool = True, healthy: bool = True,
            x_m: float = 0.0) -> dict[str, tuple[bool, str]]:
    """The check table of a loop whose links and estimator report the given values."""
    loop = object.__new__(FlightLoop)
    loop.opts = LoopOptions(lockstep=lockstep, imu_rate_hz=500.0, ground_z_m=0.0,
                            max_start_offset_m=0.25)
    loop.imu_rate_fraction = rate_fraction
    clock = SimpleNamespace(known=clock_known, rate_hz=494.0, offset_s=1.5, drift_ppm=-12000.0,
                            drift_sigma_ppm=3.0)
    stats = SimpleNamespace(imu=SimpleNamespace(measured_rate_hz=wall_rate_hz), imu_clock=clock)
    loop.imu = SimpleNamespace(link_stats=lambda: stats)
    mstats = SimpleNamespace(rate_hz=mocap_rate_hz, clock_offset_s=0.0,
                             clock_drift_ppm=math.nan, clock_drift_sigma_ppm=math.nan)
    loop.pose = SimpleNamespace(stats=lambda: mstats)
    loop.mission = SimpleNamespace(start_pos_w_m=START_POS_W_M)
    health = SimpleNamespace(ok=healthy,
                             flags=HealthFlag.OK if healthy else HealthFlag.DIVERGED)
    loop.ukf = SimpleNamespace(initialized=initialized,
                               health=lambda: health)
    est = VehicleState((x_m, 0.0, 0.1), (0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
    reading = None if servo is NO_READING else _servo() if servo is None else servo
    loop._preflight(2.0, est, reading, pose_age_s)
    return {name: (ok, value) for name, ok, value in loop.preflight_report}


def test_that_everything_nominal_passes_every_check() -> None:
    assert all(ok for ok, _ in _checks().values())


def test_that_lockstep_judges_the_imu_on_sequence_numbers_and_passes_at_exactly_80_percent(
        ) -> None:
    # the wall-clock rate of a lockstep run means nothing (here 100 Hz): it is not read
    assert _checks(rate_fraction=0.8, wall_rate_hz=100.0)[IMU] == (
        True, "80 % of the samples arrived (lockstep: from sequence numbers)")
    assert _checks(rate_fraction=0.79)[IMU][0] is False


def test_that_realtime_judges_the_imu_on_the_measured_rate_and_passes_at_exactly_80_percent(
        ) -> None:
    # the sequence-number fraction is a lockstep figure: not read in real time
    assert _checks(lockstep=False, wall_rate_hz=400.0, rate_fraction=0.1)[IMU] == (
        True, "400 Hz of 500 Hz")
    assert _checks(lockstep=False, wall_rate_hz=399.9)[IMU][0] is False


def test_that_realtime_fails_an_imu_rate_above_125_percent_of_the_set_rate() -> None:
    # a backlog read in one burst (a stream start once read 1613 Hz of 500 Hz) or a board set
    # faster than the session: not a healthy link either
    assert _checks(lockstep=False, wall_rate_hz=625.0)[IMU] == (True, "625 Hz of 500 Hz")
    assert _checks(lockstep=False, wall_rate_hz=625.1)[IMU][0] is False
    assert _checks(lockstep=False, wall_rate_hz=1613.0)[IMU] == (False, "1613 Hz of 500 Hz")


def test_that_the_board_clock_is_reported_once_the_clock_sync_knows_it() -> None:
    assert _checks(lockstep=False, clock_known=True)[IMU][1] == (
        "500 Hz of 500 Hz; board clock 494.0 Hz, offset +1.500 s, drift -12000 +- 3 ppm")
    assert "board clock" not in _checks(lockstep=False, clock_known=False)[IMU][1]


def test_that_the_servo_check_needs_a_reading_an_ok_servo_and_the_goal_within_1_deg() -> None:
    assert _checks(servo=_servo(tilt_deg=0.99, goal_deg=0.0))[SERVO] == (True, "OK, tilt 0.99 deg")
    # exactly 1 deg off its goal is not "at the commanded angle"
    assert _checks(servo=_servo(tilt_deg=1.0, goal_deg=0.0))[SERVO][0] is False
    assert _checks(servo=_servo(tilt_deg=5.0, goal_deg=0.0))[SERVO][0] is False
    # the difference to the goal counts, not the angle: at 10 deg and asked 10.5 deg it passes
    assert _checks(servo=_servo(tilt_deg=10.0, goal_deg=10.5))[SERVO][0] is True
    # no goal commanded yet (NaN): an answering servo is enough, a silent one is not
    assert _checks(servo=_servo(goal_deg=math.nan))[SERVO][0] is True
    assert _checks(servo=_servo(ok=False, goal_deg=math.nan))[SERVO] == (
        False, "NO_REPLY, tilt 0.00 deg")
    assert _checks(servo=_servo(ok=False))[SERVO][0] is False


def test_that_no_servo_reading_fails_the_servo_check() -> None:
    assert _checks(servo=NO_READING)[SERVO] == (False, "no reading")


def test_that_the_newest_pose_must_be_younger_than_0_1_s() -> None:
    assert _checks(pose_age_s=0.099)[MOCAP] == (True, "100 Hz, newest pose 99 ms old")
    assert _checks(pose_age_s=0.1)[MOCAP][0] is False


def test_that_the_mocap_rate_counts_in_real_time_only() -> None:
    # lockstep: the wall-clock frame rate follows the simulation's speed, not the server's
    assert _checks(mocap_rate_hz=50.0)[MOCAP][0] is True
    assert _checks(lockstep=False, mocap_rate_hz=79.0)[MOCAP][0] is False
    assert _checks(lockstep=False, mocap_rate_hz=80.0)[MOCAP][0] is True


def test_that_an_uninitialised_estimator_fails_even_without_a_flag() -> None:
    checks = _checks(initialized=False, healthy=True)
    assert checks[ESTIMATOR][0] is False
    assert checks[START] == (False, "no estimate yet")
    assert _checks(initialized=True, healthy=False)[ESTIMATOR][0] is False


def test_that_the_start_offset_limit_itself_fails() -> None:
    assert _checks(x_m=0.249)[START] == (True, "249 mm away")
    assert _checks(x_m=0.25)[START] == (False, "250 mm away")


def test_that_the_health_snapshot_reads_the_body_tilt_from_the_estimate() -> None:
    loop = object.__new__(FlightLoop)
    half = math.radians(30.0) / 2  # 30 deg of roll
    est = VehicleState((0.0, 0.0, 1.0), (0.0, 0.0, 0.0), (math.cos(half), math.sin(half), 0.0,
                                                           0.0), (0.0, 0.0, 0.0))
    h = loop._health(0.0, True, 0.01, True, ServoHealth.OK, 16.0, est, False, "mission", True)
    assert h.body_tilt_deg == pytest.approx(30.0, abs=1e-9)
    assert (h.imu_rate_ok, h.mocap_age_s, h.battery_v, h.pos_w_m) == (True, 0.01, 16.0,
                                                                      (0.0, 0.0, 1.0))


def test_that_a_lost_imu_snapshot_adds_no_take_off_or_mocap_failsafe_to_the_cut() -> None:
    # the loop's snapshot when the IMU stream is lost passes only what it knows; the take-off
    # and MoCap-consistency flags default to "fine", so the IMU cut is the one reason given
    loop = object.__new__(FlightLoop)
    est = VehicleState((0.0, 0.0, 1.0), (0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
    h = loop._health(math.inf, False, math.inf, False, ServoHealth.OK, math.inf, est, False,
                     "mission", False)
    assert h.lifted_off and h.takeoff_reached and h.mocap_consistent
    assert h.body_tilt_deg == 0.0


def test_that_an_upside_down_estimate_a_hair_off_unit_reads_180_deg_not_an_error() -> None:
    # |q| a little above 1 (rounding in the filter) puts r33 below -1: acos must not raise
    loop = object.__new__(FlightLoop)
    est = VehicleState((0.0, 0.0, 1.0), (0.0, 0.0, 0.0), (0.0, 1.0 + 1e-7, 0.0, 0.0),
                       (0.0, 0.0, 0.0))
    h = loop._health(0.0, True, 0.01, True, ServoHealth.OK, 16.0, est, False, "mission", True)
    assert h.body_tilt_deg == 180.0


def test_that_a_drift_known_worse_than_a_tenth_of_a_percent_is_not_shown_as_a_value() -> None:
    from groundstation.loop import DRIFT_SHOWN_SIGMA_PPM, _drift

    assert DRIFT_SHOWN_SIGMA_PPM == 1000.0
    assert _drift(-12000.0, 3.0) == "drift -12000 +- 3 ppm"
    assert _drift(8337.0, 1000.0) == "drift +8337 +- 1000 ppm"
    # a realtime preflight's MoCap server clock after ~1 s of frames (the emulator's is exact)
    assert _drift(8337.0, 15085.0) == "drift not measured yet (+- 15085 ppm)"
    assert _drift(25.0, math.inf) == "drift +25 ppm (first estimate)"

"""Every failsafe fired in a real lockstep flight through the byte path, and every safety limit
tried on both sides.

The flights run the whole ground station (FlightCtrl over a pty, TiltServo on dynamixel-sdk
over a pty, NatNet over UDP, the UKF, the loop that fills the state machine's health snapshot)
against the emulated vehicle in its own process; the faults are the emulator's scheduled faults
(``battery-sag``, ``tilt-kick``, ``imu-rate``, ``imu-gap``, ``mocap-jump``, ``mocap-dropout``,
``fc-disconnect``, ``servo-silent``), injected at simulated times, so every flight is
deterministic: a flight whose limits are not crossed is byte-identical to the same flight with
looser limits, which lets a reference flight tell where each limit is crossed to the tick.

Each failsafe test asserts the transition and its reason, when it fired against the configured
limit (one tick = 2 ms; the battery and the IMU rate are judged every ``LINK_CHECK_TICKS``
ticks, the documented delay), and what the vehicle then did, from the record's true state.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from controller.missions import Mission
from groundstation.configs import load_mission, load_vehicle
from groundstation.flight import FlightState
from groundstation.loop import IMU_MIN_RATE_FRACTION, IMU_RATE_WINDOW_SAMPLES, LINK_CHECK_TICKS
from groundstation.record import read_record
from groundstation.session import FlightSession, SessionOutcome
from groundstation.session_config import load_session

TICK_S = 0.002  # 500 Hz: one loop tick, one IMU sample
CHECK_S = LINK_CHECK_TICKS * TICK_S  # battery and IMU-rate checks: every 0.1 s
RATE_WINDOW_S = IMU_RATE_WINDOW_SAMPLES * TICK_S  # the IMU rate over the last 0.5 s
GROUND_Z_M = 0.1  # O_B at rest on the landing gear (the mission's start height)

#: take off at ~2 s (preflight 1 s, spin-up 1 s), hover, tilt step to 10 deg, planned landing
#: from ~7.5 s, on the ground at ~11 s
MISSION = """\
schema: fasthex.mission
version: 1
name: failsafe-hover
description: short hover with a tilt step, for the failsafe flights
start_pos_w_m: [0.1, -0.1, 0.1]
segments:
  - kind: takeoff
    duration_s: 2.0
    height_m: 0.7
    alpha: {kind: constant, value_deg: 0.0}
  - kind: hold
    duration_s: 0.5
    measured: false
  - kind: hold
    duration_s: 3.0
    alpha: {kind: steps, times_s: [0.0, 1.0], values_deg: [0.0, 10.0]}
  - kind: land
    duration_s: 3.5
    alpha: {kind: constant, value_deg: 0.0}
  - kind: hold
    duration_s: 0.5
    measured: false
"""

SESSION = """\
schema: fasthex.session
version: 1
name: failsafe-{name}
vehicle: fasthex
mission: failsafe-hover.yaml
backend:
  kind: emulated
  clock: lockstep
  seed: {seed}
  disturbances: paper-calibrated
  faults: [{faults}]
safety:
  geofence_min_m: [-2.0, -2.0, -0.5]
  geofence_max_m: [{xmax}, 2.0, 2.5]
  max_body_tilt_deg: {max_tilt}
  mocap_timeout_s: {mocap_timeout}
  imu_timeout_s: {imu_timeout}
  min_battery_v: {min_battery}
  failsafe_action: {action}
  servo_fault_action: {servo_action}
estimator:
  diverged_pos_sigma_m: {diverged_sigma}
telemetry:
  rerun: "off"
"""

LOOSE: dict[str, Any] = {"xmax": 2.0, "max_tilt": 60.0, "mocap_timeout": 1.0,
                         "imu_timeout": 0.1, "min_battery": 10.0, "action": "land",
                         "servo_action": "hold", "diverged_sigma": 0.5}


@dataclass
class Flight:
    out: SessionOutcome
    rows: np.ndarray
    events: str

    @property
    def transitions(self) -> list[tuple[FlightState, FlightState, str]]:
        return [(t.from_state, t.to_state, t.reason) for t in self.out.result.transitions]

    @property
    def states(self) -> list[FlightState]:
        return [t.to_state for t in self.out.result.transitions]

    def fired(self, prefix: str) -> Any:
        """The one transition whose reason starts with ``prefix``."""
        hits = [t for t in self.out.result.transitions if t.reason.startswith(prefix)]
        assert len(hits) == 1, (prefix, self.transitions)
        return hits[0]

    @property
    def extremes(self) -> dict[str, Any]:
        return self.out.result.health_extremes

    def row_at(self, t_s: float) -> int:
        return int(np.searchsorted(self.rows["t_s"], t_s - 1e-9))

    @property
    def final_true_pos_w_m(self) -> np.ndarray:
        return np.asarray(self.rows["pos_w_m"][-1])


def fly(tmp_path: Path, name: str, faults: str = "", seed: int = 3, **limits: Any) -> Flight:
    (tmp_path / "failsafe-hover.yaml").write_text(MISSION)
    path = tmp_path / f"{name}.yaml"
    path.write_text(SESSION.format(name=name, seed=seed, faults=faults, **(LOOSE | limits)))
    session = FlightSession(load_session(path), load_vehicle("fasthex"),
                            Mission(load_mission(tmp_path / "failsafe-hover.yaml")),
                            record_path=tmp_path / f"{name}.fhr", echo_events=False)
    out = session.run()
    return Flight(out, read_record(out.record_path).rows, out.events_path.read_text())


def body_tilt_deg(q_wb: np.ndarray) -> np.ndarray:
    """The angle between the body z axis and the world z axis, as the loop computes it."""
    q = np.asarray(q_wb)
    r33 = 1.0 - 2.0 * (q[:, 1] ** 2 + q[:, 2] ** 2)
    return np.degrees(np.arccos(np.clip(r33, -1.0, 1.0)))


def state_at(flight: Flight, t_s: float) -> FlightState:
    """The state ``flight`` was in at ``t_s``."""
    state = FlightState.PREFLIGHT
    for t in flight.out.result.transitions:
        if t.t_s <= t_s:
            state = t.to_state
    return state


def landed_near(flight: Flight, xy_m: Any, tol_m: float) -> None:
    """The session ended on the ground (touchdown confirmed), at ``xy_m`` within ``tol_m``."""
    assert flight.states[-1] is FlightState.DISARMED
    assert flight.transitions[-1][2] == "touchdown"
    final = flight.final_true_pos_w_m
    assert final[2] == pytest.approx(GROUND_Z_M, abs=0.03)
    assert math.dist(final[:2], xy_m) < tol_m


def controlled_descent(flight: Flight, after_s: float) -> None:
    """After ``after_s`` the vehicle came down under control: no free fall (the true vertical
    speed stays within the landing's descent rate plus the controller's transients)."""
    rows = flight.rows[flight.row_at(after_s):]
    assert rows["vel_w_m_s"][:, 2].min() > -0.6


# -- a reference flight, the same flight just inside every limit, and just outside each ------
#: the MoCap room recalibrated 0.3 m along x during the takeoff (the UKF refuses the jumped
#: poses, then re-seeds on them: the estimate jumps, the mission's reference moves with it, so
#: the vehicle stays where it is and lands where it took off; it used to fly back 0.3 m, at up
#: to 42 deg of tilt for a 0.5 m jump), a blow to the airframe in the hover, a MoCap dropout, a
#: battery cell failing in the planned landing: each stays inside the loose limits
REFERENCE_FAULTS = ("mocap-jump@3.5:0.3, tilt-kick@5.0:200, mocap-dropout@6.0:0.3, "
                    "battery-sag@8.0:0.3")
JUMP_S, JUMP_M, KICK_S, DROPOUT_S, SAG_S = 3.5, 0.3, 5.0, 6.0, 8.0
LANDING_XY_M = (0.1, -0.1)  # the mission's start: the vehicle did not move with the jump
#: the battery is read at 1 Hz (FlightCtrlConfig.battery_rate_hz) and judged every check
BATTERY_DELAY_S = 1.0 + CHECK_S


@pytest.fixture(scope="module")
def reference(tmp_path_factory: pytest.TempPathFactory) -> Flight:
    flight = fly(tmp_path_factory.mktemp("reference"), "reference", REFERENCE_FAULTS)
    # the jump is listed (the flight goes on through it); nothing else is a fault
    assert [f.split(": ", 1)[1] for f in flight.out.result.faults] == [
        f"MoCap jumped {JUMP_M:.2f} m: the mission goes on in the tracker's new frame"]
    return flight


NOMINAL = [(FlightState.ARMED, "operator: arm"), (FlightState.TAKEOFF, "motors at idle speed"),
           (FlightState.MISSION, "takeoff complete"),
           (FlightState.LANDING, "mission complete"), (FlightState.DISARMED, "touchdown")]


def test_that_a_flight_just_inside_every_limit_takes_no_action(
        tmp_path: Path, reference: Flight) -> None:
    # Fixture: each limit a hair beyond the closest the reference flight came to it
    x = reference.extremes
    assert x["mocap_age_max_s"] > 0.3  # the 0.3 s dropout was seen
    assert 8.0 < x["body_tilt_max_deg"] < 35.0  # the kick (hover: 1.5)
    assert x["battery_min_v"] < 16.0 - 0.25  # the sag was read
    limits = {"mocap_timeout": x["mocap_age_max_s"] + TICK_S,
              "max_tilt": x["body_tilt_max_deg"] + 0.1,
              "min_battery": x["battery_min_v"] - 0.01,
              "xmax": x["pos_max_w_m"][0] + 0.005}
    # Test
    inside = fly(tmp_path, "inside", REFERENCE_FAULTS, **limits)
    # Assert: no fault but the jump, the nominal sequence, and the very same flight as with
    # loose limits
    assert inside.out.result.faults == reference.out.result.faults
    assert [(s, r) for _, s, r in inside.transitions] == NOMINAL
    assert inside.rows.tobytes() == reference.rows.tobytes()
    landed_near(inside, LANDING_XY_M, 0.05)


def test_that_body_tilt_just_over_its_limit_lands_at_the_first_tick_over_it(
        tmp_path: Path, reference: Flight) -> None:
    limit = reference.extremes["body_tilt_max_deg"] - 0.5
    tilt = body_tilt_deg(reference.rows["est_q_wb"])
    first = int(np.argmax(tilt > limit))  # the reference flight is this flight until then
    assert tilt[first] > limit and reference.rows["t_s"][first] > JUMP_S
    out = fly(tmp_path, "tilt", REFERENCE_FAULTS, max_tilt=limit)
    tr = out.fired("failsafe: body tilt")
    # the kick in the hover (the jump no longer tilts it: the reference moved with it)
    assert (tr.from_state, tr.to_state) == (state_at(reference, tr.t_s), FlightState.LANDING)
    assert tr.t_s == pytest.approx(float(reference.rows["t_s"][first]), abs=1e-9)
    assert tr.reason == f"failsafe: body tilt {tilt[first]:.1f} deg > {limit:g} deg"
    # it landed where it was when the failsafe fired (the kick had pushed it a little)
    at = out.rows["pos_w_m"][out.row_at(tr.t_s)]
    landed_near(out, at[:2], 0.1)
    controlled_descent(out, tr.t_s)


def test_that_a_mocap_dropout_just_over_the_timeout_lands_one_tick_after_the_limit(
        tmp_path: Path, reference: Flight) -> None:
    timeout = reference.extremes["mocap_age_max_s"] - 0.01
    out = fly(tmp_path, "mocap", REFERENCE_FAULTS, mocap_timeout=timeout)
    tr = out.fired("failsafe: MoCap lost for")
    age = float(tr.reason.split("for ")[1].split(" s")[0])
    assert timeout - 0.005 <= age <= timeout + TICK_S + 0.005  # printed to 10 ms, rounded
    # the age counts from the capture time of the last pose, which was just before the dropout
    assert (tr.from_state, tr.to_state) == (FlightState.MISSION, FlightState.LANDING)
    fault = next(f for f in out.out.result.faults if "MoCap lost" in f)
    assert float(fault.split(" s:")[0]) == pytest.approx(tr.t_s)
    assert DROPOUT_S + timeout - 0.03 <= tr.t_s <= DROPOUT_S + timeout + TICK_S
    at = out.rows["pos_w_m"][out.row_at(tr.t_s)]
    landed_near(out, at[:2], 0.1)  # landed on the estimate (dead reckoning, then MoCap again)
    controlled_descent(out, tr.t_s)


def test_that_a_battery_just_under_its_limit_in_the_planned_landing_lands_here(
        tmp_path: Path, reference: Flight) -> None:
    # the sagged pack reads within 0.03 V of the flight's minimum, which comes later, at the
    # landing's higher load near the ground
    limit = reference.extremes["battery_min_v"] + 0.03
    out = fly(tmp_path, "battery", REFERENCE_FAULTS, min_battery=limit)
    tr = out.fired("failsafe: battery low")
    # a failsafe in the mission's own landing: it gives up the planned path and lands here
    assert (tr.from_state, tr.to_state) == (FlightState.LANDING, FlightState.LANDING)
    volts = float(tr.reason.split("(")[1].split(" V")[0])
    # the reason prints the volts to 0.01 V
    assert reference.extremes["battery_min_v"] - 0.005 <= volts < limit + 0.005
    assert SAG_S < tr.t_s <= SAG_S + BATTERY_DELAY_S + 1e-9  # t_s is k * 2 ms in floats
    assert "LANDING -> LANDING: failsafe: battery low" in out.events
    at = out.rows["pos_w_m"][out.row_at(tr.t_s)]
    landed_near(out, at[:2], 0.05)
    controlled_descent(out, tr.t_s)  # not at idle: the landing reference took over


def test_that_an_estimate_just_beyond_the_geofence_lands_at_the_first_tick_beyond_it(
        tmp_path: Path, reference: Flight) -> None:
    # the MoCap jump carries the estimate 0.3 m along x, during the takeoff
    xmax = reference.extremes["pos_max_w_m"][0] - 0.02
    x = reference.rows["est_pos_w_m"][:, 0]
    first = int(np.argmax(x > xmax))
    assert reference.rows["t_s"][first] > JUMP_S
    out = fly(tmp_path, "geofence", REFERENCE_FAULTS, xmax=xmax)
    tr = out.fired("failsafe: geofence breached")
    assert (tr.from_state, tr.to_state) == (FlightState.TAKEOFF, FlightState.LANDING)
    assert tr.t_s == pytest.approx(float(reference.rows["t_s"][first]), abs=1e-9)
    # landed straight down from where it was (the estimate 0.3 m off the truth since the jump)
    at = out.rows["pos_w_m"][out.row_at(tr.t_s)]
    landed_near(out, at[:2], 0.1)
    controlled_descent(out, tr.t_s)


# -- the IMU link: a degraded rate and a gap, judged on the board's sequence numbers ---------
def test_that_an_imu_link_just_inside_its_limits_takes_no_action(tmp_path: Path) -> None:
    # a 90 ms gap (imu_timeout_s 0.1; 82 % of the samples in its rate window), then 90 % of
    # the samples from 4 s on (the driver may also drop the sample after a lost one when its
    # wall-clock arrival looks too early: a rate a little below 90 % results)
    out = fly(tmp_path, "imu-inside", "imu-gap@3.0:0.09, imu-rate@4.0:0.9")
    assert out.out.result.faults == []
    assert [(s, r) for _, s, r in out.transitions] == NOMINAL
    x = out.extremes
    assert IMU_MIN_RATE_FRACTION <= x["imu_rate_min_fraction"] <= 0.92
    assert 0.09 <= x["imu_gap_max_s"] <= 0.1
    assert out.out.result.counters["imu_missing"] > 300  # the loop bridged every lost sample
    # the longest gap fly --json reports: in lockstep the board's missing samples (it was 0)
    c = out.out.result.counters
    assert 90_000 <= c["imu_gap_max_us"] <= 100_000
    assert 3.09 <= c["imu_gap_max_at_ms"] / 1e3 <= 3.1 + TICK_S
    landed_near(out, (0.1, -0.1), 0.05)


def test_that_an_imu_rate_below_80_percent_cuts_within_two_rate_windows(tmp_path: Path) -> None:
    out = fly(tmp_path, "imu-rate", "imu-rate@6.0:0.7")
    tr = out.fired("IMU/link lost")
    assert (tr.from_state, tr.to_state) == (FlightState.MISSION, FlightState.CUT)
    assert out.out.result.faults[-1] == f"{tr.t_s:.3f} s: IMU rate below 80 % of the set rate"
    # the rate over the window falls below 80 % two thirds into it (0.2 / 0.3 of a window),
    # and the next check sees it
    assert 6.0 + RATE_WINDOW_S * 0.2 / 0.3 < tr.t_s <= 6.0 + RATE_WINDOW_S + CHECK_S + TICK_S
    assert out.states[-1] is FlightState.DISARMED
    assert np.all(out.rows["spin_cmd_hz"][-1] == 0.0)  # the last tick sent the motors off
    assert out.rows["pos_w_m"][-1][2] > 0.5  # cut in the air, as configured for IMU loss


def test_that_an_imu_gap_just_over_the_timeout_cuts(tmp_path: Path) -> None:
    out = fly(tmp_path, "imu-gap", "imu-gap@6.0:0.15")
    tr = out.fired("IMU/link lost")
    assert (tr.from_state, tr.to_state) == (FlightState.MISSION, FlightState.CUT)
    (fault,) = out.out.result.faults
    age_ms = float(fault.split("age ")[1].split(" ms")[0])
    assert 100.0 < age_ms <= 100.0 + 1e3 * TICK_S + 0.5  # imu_timeout_s 0.1, one tick
    # stamped with the last sample received, the one before the gap
    assert tr.t_s == pytest.approx(6.0 - TICK_S, abs=1e-6)
    assert out.states[-1] is FlightState.DISARMED
    assert out.out.result.end_reason == "IMU stream lost"


# -- the tilt servo, the estimator ----------------------------------------------------------
def test_that_a_silent_servo_holds_the_measured_tilt_and_the_mission_goes_on(
        tmp_path: Path) -> None:
    out = fly(tmp_path, "servo-hold", "servo-silent@6.0", servo_action="hold")
    (fault,) = out.out.result.faults
    # the fault line names what the driver said: the servo stopped answering (no reply, or
    # stale when the loop read it after the stale limit: a loaded host)
    assert fault.endswith(("tilt servo fault: holding the measured tilt (no reply)",
                           "tilt servo fault: holding the measured tilt (stale)")), fault
    t_fault = float(fault.split(" s:")[0])
    assert 6.0 < t_fault <= 6.0 + 10 * TICK_S  # the next servo cycle (every 10 ticks)
    assert [(s, r) for _, s, r in out.transitions] == NOMINAL
    rows = out.rows[out.row_at(t_fault):]
    held = rows["alpha_rad"]
    # the fault struck in the middle of the tilt ramp to 10 deg: held there, to the end
    assert 2.0 < math.degrees(held[0]) < 9.0
    assert held[0] == out.rows["alpha_rad"][out.row_at(t_fault) - 1]
    assert np.all(held == held[0])
    landed_near(out, (0.1, -0.1), 0.05)


def test_that_a_silent_servo_lands_when_configured_to(tmp_path: Path) -> None:
    out = fly(tmp_path, "servo-land", "servo-silent@6.0", servo_action="land")
    tr = out.fired("failsafe: tilt servo fault")
    assert (tr.from_state, tr.to_state) == (FlightState.MISSION, FlightState.LANDING)
    assert 6.0 < tr.t_s <= 6.0 + 10 * TICK_S
    at = out.rows["pos_w_m"][out.row_at(tr.t_s)]
    landed_near(out, at[:2], 0.05)
    controlled_descent(out, tr.t_s)


def test_that_a_diverged_estimator_lands_before_the_mocap_timeout(tmp_path: Path) -> None:
    # MoCap out for 2 s against a 5 s timeout: the UKF's position sigma (dead reckoning)
    # passes its 4 mm DIVERGED limit first
    out = fly(tmp_path, "estimator", "mocap-dropout@6.0:2.0", mocap_timeout=5.0,
              diverged_sigma=0.004)
    tr = out.fired("failsafe: estimator unhealthy")
    assert (tr.from_state, tr.to_state) == (FlightState.MISSION, FlightState.LANDING)
    assert 6.0 + 0.1 < tr.t_s < 8.0
    at = out.rows["pos_w_m"][out.row_at(tr.t_s)]
    landed_near(out, at[:2], 0.1)
    controlled_descent(out, tr.t_s)


# -- preflight: each check refuses the flight ------------------------------------------------
def test_that_a_silent_servo_a_slow_imu_and_a_displaced_vehicle_each_refuse_the_flight(
        tmp_path: Path) -> None:
    out = fly(tmp_path, "preflight-1", "servo-silent@0.0, imu-rate@14.0:0.5, mocap-jump@0.0:0.5")
    assert out.out.result.end_reason == "preflight checks failed"
    assert out.transitions == [(FlightState.PREFLIGHT, FlightState.DISARMED,
                                "operator: stop before arming")]
    assert out.transitions and out.out.result.transitions[0].t_s > 15.0  # the timeout
    report = {name: (ok, value) for name, ok, value in out.out.preflight}
    assert report["flight-ctrl streaming IMU at 80-125 % of the set rate"][0] is False
    assert report["servo answers, multi-turn, at the commanded angle"][0] is False
    start_ok, start_value = report["vehicle at the mission's start position"]
    assert start_ok is False and start_value == "500 mm away"
    assert report["MoCap sees the body at >= 80 % of its rate"][0] is True
    assert report["estimator converged"][0] is True
    assert np.all(out.rows["spin_cmd_hz"] == 0.0)  # the motors never started
    assert "preflight FAIL: servo answers" in out.events


def test_that_no_mocap_refuses_the_flight_and_no_check_passes_on_the_placeholder_estimate(
        tmp_path: Path) -> None:
    # the vehicle stands exactly at the mission's start, and the UKF's placeholder state is at
    # the origin: before the fix the start-position check compared the two and could pass
    out = fly(tmp_path, "preflight-2", "mocap-dropout@0.0:30")
    assert out.out.result.end_reason == "preflight checks failed"
    report = {name: (ok, value) for name, ok, value in out.out.preflight}
    assert report["MoCap sees the body at >= 80 % of its rate"][0] is False
    assert report["estimator converged"][0] is False
    assert report["vehicle at the mission's start position"] == (False, "no estimate yet")
    assert report["servo answers, multi-turn, at the commanded angle"][0] is True
    assert report["flight-ctrl streaming IMU at 80-125 % of the set rate"][0] is True
    assert np.all(out.rows["spin_cmd_hz"] == 0.0)

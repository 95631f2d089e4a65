"""The flight state machine: the nominal sequence, every failsafe and the operator requests."""

from __future__ import annotations

import itertools
from dataclasses import replace
from typing import Any

import pytest

from groundstation.flight import (
    FlightState,
    FlightStateMachine,
    HealthSnapshot,
    ReferenceSource,
    SafetyLimits,
    ServoHealth,
)

LIMITS = SafetyLimits(
    geofence_min_m=(-2.0, -2.0, -0.2), geofence_max_m=(2.0, 2.0, 2.5), max_body_tilt_deg=40.0,
    mocap_timeout_s=1.0, imu_timeout_s=0.05, min_battery_v=14.0, failsafe_action="land",
    servo_fault_action="hold", spin_up_s=1.0,
)
OK = HealthSnapshot(
    imu_age_s=0.002, imu_rate_ok=True, mocap_age_s=0.01, estimator_ok=True,
    servo=ServoHealth.OK, battery_v=16.0, pos_w_m=(0.0, 0.0, 1.0), body_tilt_deg=1.0,
    on_ground=False, mission_phase="mission", motors_spinning=True,
)


def _flying(**limits: Any) -> FlightStateMachine:
    sm = FlightStateMachine(replace(LIMITS, **limits))
    assert sm.request(0.0, "arm") == (True, "armed")
    sm.update(1.0, replace(OK, mission_phase="takeoff", on_ground=True))
    sm.update(2.0, OK)
    assert sm.state is FlightState.MISSION
    return sm


def test_that_a_nominal_flight_goes_through_every_state_in_order() -> None:
    sm = FlightStateMachine(LIMITS)
    assert sm.update(0.0, replace(OK, on_ground=True)).reference is ReferenceSource.NONE
    sm.request(0.5, "arm")
    assert sm.update(1.0, replace(OK, mission_phase="takeoff")).state is FlightState.ARMED
    d = sm.update(1.5, replace(OK, mission_phase="takeoff"))
    assert (d.state, d.motors_on, d.reference) == (FlightState.TAKEOFF, True,
                                                   ReferenceSource.MISSION)
    assert sm.update(5.0, OK).state is FlightState.MISSION
    d = sm.update(75.0, replace(OK, mission_phase="land"))
    assert (d.state, d.reference) == (FlightState.LANDING, ReferenceSource.MISSION)
    d = sm.update(80.0, replace(OK, mission_phase="done", on_ground=True))
    assert (d.state, d.motors_on) == (FlightState.DISARMED, False)
    assert [(t.to_state, t.reason) for t in sm.transitions] == [
        (FlightState.ARMED, "operator: arm"),
        (FlightState.TAKEOFF, "motors at idle speed"),
        (FlightState.MISSION, "takeoff complete"),
        (FlightState.LANDING, "mission complete"),
        (FlightState.DISARMED, "touchdown"),
    ]
    assert [t.t_s for t in sm.transitions] == [0.5, 1.5, 5.0, 75.0, 80.0]
    assert sm.faults == [] and sm.finished


@pytest.mark.parametrize(("change", "reason"), [
    ({"mocap_age_s": 3.0}, "failsafe: MoCap lost for 3.00 s (> 1 s)"),
    ({"pos_w_m": (2.5, 0.0, 1.0)}, "failsafe: geofence breached at (2.50, 0.00, 1.00) m"),
    ({"body_tilt_deg": 55.0}, "failsafe: body tilt 55.0 deg > 40 deg"),
    ({"battery_v": 13.2}, "failsafe: battery low (13.20 V < 14 V)"),
    ({"estimator_ok": False}, "failsafe: estimator unhealthy"),
])
def test_that_each_failsafe_lands_on_the_estimate(change: dict[str, Any], reason: str) -> None:
    sm = _flying()
    d = sm.update(10.0, replace(OK, **change))
    assert (d.state, d.reference, d.motors_on) == (FlightState.LANDING,
                                                   ReferenceSource.LAND_HERE, True)
    assert sm.transitions[-1].reason == reason
    assert len(sm.faults) == 1


def test_that_a_short_mocap_dropout_does_not_end_the_flight() -> None:
    sm = _flying()
    assert sm.update(10.0, replace(OK, mocap_age_s=0.3)).state is FlightState.MISSION
    assert sm.faults == []


def test_that_losing_the_imu_cuts_the_motors_and_ends_the_session() -> None:
    sm = _flying()
    d = sm.update(10.0, replace(OK, imu_age_s=0.2))
    assert (d.state, d.motors_on) == (FlightState.CUT, False)
    assert sm.update(10.002, OK).state is FlightState.DISARMED
    assert sm.faults == ["10.000 s: IMU stream lost (age 200 ms)"]


def test_that_the_failsafe_action_cut_stops_the_motors() -> None:
    sm = _flying(failsafe_action="cut")
    assert sm.update(10.0, replace(OK, pos_w_m=(0.0, 0.0, 3.0))).state is FlightState.CUT


def test_that_a_servo_fault_holds_the_tilt_or_lands_as_configured() -> None:
    sm = _flying(servo_fault_action="hold")
    d = sm.update(10.0, replace(OK, servo=ServoHealth.FAULT))
    assert (d.state, d.hold_tilt) == (FlightState.MISSION, True)
    assert sm.faults == ["10.000 s: tilt servo fault: holding the measured tilt"]
    sm = _flying(servo_fault_action="land")
    assert sm.update(10.0, replace(OK, servo=ServoHealth.FAULT)).state is FlightState.LANDING


def test_that_a_servo_fault_names_what_the_driver_said_in_the_fault_not_the_transition(
        ) -> None:
    fault = replace(OK, servo=ServoHealth.FAULT, servo_detail="no reply")
    sm = _flying(servo_fault_action="hold")
    sm.update(10.0, fault)
    assert sm.faults == ["10.000 s: tilt servo fault: holding the measured tilt (no reply)"]
    sm = _flying(servo_fault_action="land")
    assert sm.update(10.0, fault).state is FlightState.LANDING
    assert sm.faults == ["10.000 s: tilt servo fault (no reply)"]
    assert sm.transitions[-1].reason == "failsafe: tilt servo fault"


def test_that_ctrl_c_lands_and_a_second_ctrl_c_cuts() -> None:
    sm = _flying()
    assert sm.request(10.0, "stop") == (True, "landing")
    assert sm.update(10.002, OK).reference is ReferenceSource.LAND_HERE
    assert sm.request(11.0, "stop") == (True, "motors cut")
    assert sm.state is FlightState.CUT
    assert [t.reason for t in sm.transitions[-2:]] == ["operator: land",
                                                       "operator: second stop request"]


def test_that_requests_in_the_wrong_state_are_refused() -> None:
    sm = FlightStateMachine(LIMITS)
    assert sm.request(0.0, "disarm") == (True, "disarmed")
    sm = _flying()
    assert sm.request(5.0, "arm") == (False, "cannot arm in MISSION")
    assert sm.request(5.0, "disarm") == (False, "cannot disarm while MISSION; land first")
    assert sm.request(5.0, "cut") == (True, "motors cut")
    assert sm.request(5.1, "cut") == (False, "motors are not running (CUT)")


def test_that_a_landing_failsafe_does_not_repeat_while_landing_on_the_estimate() -> None:
    sm = _flying()
    sm.update(10.0, replace(OK, mocap_age_s=3.0))
    sm.update(10.002, replace(OK, mocap_age_s=3.002))
    assert len(sm.faults) == 1 and sm.state is FlightState.LANDING


def test_that_takeoff_waits_until_every_motor_spins() -> None:
    sm = FlightStateMachine(LIMITS)
    sm.request(0.0, "arm")
    starting = replace(OK, mission_phase="takeoff", on_ground=True, motors_spinning=False)
    assert sm.update(3.0, starting).state is FlightState.ARMED  # past spin_up_s, not spinning
    assert sm.update(3.1, replace(starting, motors_spinning=True)).state is FlightState.TAKEOFF


# -- each limit on both sides of its boundary (a value at the limit is inside) ---------------
@pytest.mark.parametrize(("inside", "outside"), [
    ({"mocap_age_s": 1.0}, {"mocap_age_s": 1.0 + 1e-9}),
    ({"body_tilt_deg": 40.0}, {"body_tilt_deg": 40.0 + 1e-9}),
    ({"battery_v": 14.0}, {"battery_v": 14.0 - 1e-9}),
    ({"pos_w_m": (2.0, 0.0, 1.0)}, {"pos_w_m": (2.0 + 1e-9, 0.0, 1.0)}),
    ({"pos_w_m": (-2.0, 0.0, 1.0)}, {"pos_w_m": (-2.0 - 1e-9, 0.0, 1.0)}),
    ({"pos_w_m": (0.0, 2.0, 1.0)}, {"pos_w_m": (0.0, 2.0 + 1e-9, 1.0)}),
    ({"pos_w_m": (0.0, -2.0, 1.0)}, {"pos_w_m": (0.0, -2.0 - 1e-9, 1.0)}),
    ({"pos_w_m": (0.0, 0.0, 2.5)}, {"pos_w_m": (0.0, 0.0, 2.5 + 1e-9)}),
    ({"pos_w_m": (0.0, 0.0, -0.2)}, {"pos_w_m": (0.0, 0.0, -0.2 - 1e-9)}),
])
def test_that_a_value_at_a_limit_flies_on_and_one_beyond_it_lands(
        inside: dict[str, Any], outside: dict[str, Any]) -> None:
    sm = _flying()
    assert sm.update(10.0, replace(OK, **inside)).state is FlightState.MISSION
    assert sm.faults == [] and len(sm.transitions) == 3
    d = sm.update(10.002, replace(OK, **outside))
    assert (d.state, d.reference) == (FlightState.LANDING, ReferenceSource.LAND_HERE)
    assert sm.transitions[-1].t_s == 10.002 and sm.transitions[-1].reason.startswith("failsafe")
    assert sm.faults[0].startswith("10.002 s: ")


def test_that_the_imu_age_at_its_timeout_flies_on_and_beyond_it_cuts() -> None:
    sm = _flying()
    assert sm.update(10.0, replace(OK, imu_age_s=0.05)).state is FlightState.MISSION
    d = sm.update(10.002, replace(OK, imu_age_s=0.05 + 1e-9))
    assert (d.state, d.motors_on, d.reference) == (FlightState.CUT, False, ReferenceSource.NONE)
    assert sm.transitions[-1].reason == "IMU/link lost: motors stop"
    assert sm.faults == ["10.002 s: IMU stream lost (age 50 ms)"]


def test_that_a_low_imu_rate_cuts_and_a_lost_link_is_named() -> None:
    sm = _flying()
    assert sm.update(10.0, replace(OK, imu_rate_ok=False)).state is FlightState.CUT
    assert sm.faults == ["10.000 s: IMU rate below 80 % of the set rate"]
    sm = _flying()
    sm.update(10.0, replace(OK, imu_age_s=float("inf")))
    assert sm.faults == ["10.000 s: Flight-Ctrl link lost"]
    assert sm.update(10.002, OK).state is FlightState.DISARMED
    assert sm.transitions[-1].reason == "motors stopped"


def test_that_on_the_ground_armed_only_a_lost_imu_acts() -> None:
    sm = FlightStateMachine(LIMITS)
    sm.request(0.0, "arm")
    bad = replace(OK, mission_phase="takeoff", motors_spinning=False, mocap_age_s=5.0,
                  battery_v=1.0, body_tilt_deg=90.0, estimator_ok=False,
                  servo=ServoHealth.FAULT, pos_w_m=(9.0, 9.0, 9.0))
    assert sm.update(0.5, bad).state is FlightState.ARMED and sm.faults == []
    assert sm.update(0.6, replace(bad, imu_rate_ok=False)).state is FlightState.CUT


def test_that_the_failsafes_are_checked_in_order_and_only_in_flight() -> None:
    sm = FlightStateMachine(LIMITS)
    assert sm.update(0.0, replace(OK, imu_age_s=1.0, battery_v=0.0)).state \
        is FlightState.PREFLIGHT  # nothing to stop before arming
    sm = _flying()
    sm.update(10.0, replace(OK, mocap_age_s=2.0, estimator_ok=False, battery_v=1.0))
    assert sm.transitions[-1].reason == "failsafe: MoCap lost for 2.00 s (> 1 s)"
    sm = _flying()
    sm.update(10.0, replace(OK, estimator_ok=False, body_tilt_deg=80.0))
    assert sm.transitions[-1].reason == "failsafe: estimator unhealthy"
    sm = _flying()
    sm.update(10.0, replace(OK, pos_w_m=(3.0, 0.0, 1.0), body_tilt_deg=80.0))
    assert sm.transitions[-1].reason.startswith("failsafe: geofence")
    sm = _flying()
    sm.update(10.0, replace(OK, body_tilt_deg=80.0, battery_v=1.0))
    assert sm.transitions[-1].reason.startswith("failsafe: body tilt")
    sm = _flying()
    sm.update(10.0, replace(OK, battery_v=1.0, servo=ServoHealth.FAULT))
    assert sm.transitions[-1].reason.startswith("failsafe: battery low")


def test_that_a_degraded_servo_flies_on_and_a_held_tilt_is_not_reported_twice() -> None:
    sm = _flying(servo_fault_action="hold")
    assert sm.update(10.0, replace(OK, servo=ServoHealth.DEGRADED)).hold_tilt is False
    sm.update(10.002, replace(OK, servo=ServoHealth.FAULT))
    d = sm.update(10.004, replace(OK, servo=ServoHealth.FAULT))
    assert (d.state, d.hold_tilt) == (FlightState.MISSION, True)
    assert len(sm.faults) == 1
    # and with the tilt held, a later servo fault does not land either
    assert sm.update(10.006, replace(OK, servo=ServoHealth.FAULT)).state is FlightState.MISSION


def test_that_a_failsafe_in_the_planned_landing_switches_to_landing_here_once() -> None:
    sm = _flying()
    d = sm.update(20.0, replace(OK, mission_phase="land"))
    assert (d.state, d.reference) == (FlightState.LANDING, ReferenceSource.MISSION)
    d = sm.update(20.5, replace(OK, mission_phase="land", battery_v=13.0))
    assert (d.state, d.reference, d.motors_on) == (FlightState.LANDING,
                                                   ReferenceSource.LAND_HERE, True)
    last = sm.transitions[-1]
    assert (last.t_s, last.from_state, last.to_state, last.reason) == (
        20.5, FlightState.LANDING, FlightState.LANDING, "failsafe: battery low (13.00 V < 14 V)")
    sm.update(20.6, replace(OK, mission_phase="land", battery_v=12.0))
    assert len(sm.transitions) == 5 and len(sm.faults) == 1
    assert sm.update(21.0, replace(OK, on_ground=True)).state is FlightState.DISARMED


def test_that_a_failsafe_with_the_action_cut_in_a_landing_cuts() -> None:
    sm = _flying(failsafe_action="cut")
    sm.update(20.0, replace(OK, mission_phase="land"))
    d = sm.update(20.5, replace(OK, mission_phase="land", body_tilt_deg=50.0))
    assert (d.state, d.motors_on) == (FlightState.CUT, False)
    assert sm.transitions[-1].reason == "failsafe (cut): body tilt 50.0 deg > 40 deg"


def test_that_spin_up_takes_its_time_and_takeoff_ends_with_its_phase() -> None:
    sm = FlightStateMachine(LIMITS)
    sm.request(1.0, "arm")
    takeoff = replace(OK, mission_phase="takeoff")
    assert sm.update(1.999, takeoff).state is FlightState.ARMED
    assert sm.update(2.0, takeoff).state is FlightState.TAKEOFF
    assert sm.update(2.002, takeoff).state is FlightState.TAKEOFF
    assert sm.update(2.004, OK).state is FlightState.MISSION
    assert sm.update(2.006, replace(OK, mission_phase="done")).state is FlightState.LANDING
    assert sm.update(2.008, replace(OK, mission_phase="done")).reference is \
        ReferenceSource.MISSION
    assert not sm.finished
    assert sm.update(2.010, replace(OK, mission_phase="done", on_ground=True)).state \
        is FlightState.DISARMED
    assert sm.finished


@pytest.mark.parametrize(("state_path", "what", "answer", "to"), [
    ((), "land", (True, "session ended"), FlightState.DISARMED),
    ((), "stop", (True, "session ended"), FlightState.DISARMED),
    ((), "cut", (False, "motors are not running (PREFLIGHT)"), FlightState.PREFLIGHT),
    (("arm",), "land", (True, "disarmed"), FlightState.DISARMED),
    (("arm",), "cut", (True, "motors cut"), FlightState.CUT),
    (("arm",), "disarm", (True, "disarmed"), FlightState.DISARMED),
    (("arm", "disarm"), "disarm", (False, "already disarmed"), FlightState.DISARMED),
    (("arm", "disarm"), "land", (False, "already DISARMED"), FlightState.DISARMED),
])
def test_that_operator_requests_on_the_ground_do_what_they_say(
        state_path: tuple[str, ...], what: Any, answer: tuple[bool, str],
        to: FlightState) -> None:
    sm = FlightStateMachine(LIMITS)
    for step in state_path:
        sm.request(0.0, step)  # type: ignore[arg-type]
    assert sm.request(0.5, what) == answer
    assert sm.state is to


def test_that_operator_land_in_a_landing_is_refused_and_stop_then_cuts() -> None:
    sm = _flying()
    sm.update(20.0, replace(OK, mission_phase="land"))
    assert sm.request(20.1, "land") == (False, "already LANDING")
    assert sm.request(20.2, "stop") == (False, "already LANDING")
    assert sm.request(20.3, "stop") == (True, "motors cut")
    assert sm.transitions[-1].reason == "operator: second stop request"
    assert sm.request(20.4, "stop") == (False, "already CUT")


def test_that_the_states_are_numbered_as_the_mavlink_custom_mode() -> None:
    # the loop publishes int(state); the MAVLink side reads it back as a FlightPhase
    from groundstation.operator import FlightPhase

    assert [(s.name, int(s)) for s in FlightState] == [(p.name, int(p)) for p in FlightPhase]
    assert [int(s) for s in FlightState] == list(range(7))


def test_that_the_default_spin_up_is_one_second() -> None:
    limits = SafetyLimits(
        geofence_min_m=(-2.0, -2.0, -0.2), geofence_max_m=(2.0, 2.0, 2.5),
        max_body_tilt_deg=40.0, mocap_timeout_s=1.0, imu_timeout_s=0.05, min_battery_v=14.0,
        failsafe_action="land", servo_fault_action="hold")
    sm = FlightStateMachine(limits)
    sm.request(0.0, "arm")
    assert sm.update(0.998, replace(OK, mission_phase="takeoff")).state is FlightState.ARMED
    assert sm.update(1.0, replace(OK, mission_phase="takeoff")).state is FlightState.TAKEOFF


def test_that_a_low_rate_at_the_imu_timeout_is_reported_as_the_rate() -> None:
    sm = _flying()
    sm.update(10.0, replace(OK, imu_age_s=0.05, imu_rate_ok=False))
    assert sm.faults == ["10.000 s: IMU rate below 80 % of the set rate"]


def test_that_a_planned_landing_ended_aloft_lands_here_once() -> None:
    sm = _flying()
    sm.update(10.0, replace(OK, mission_phase="land"))
    d = sm.update(12.0, replace(OK, mission_phase="done"))  # not yet judged ended aloft
    assert (d.state, d.reference) == (FlightState.LANDING, ReferenceSource.MISSION)
    d = sm.update(13.0, replace(OK, mission_phase="done", ended_aloft=True))
    assert (d.state, d.reference) == (FlightState.LANDING, ReferenceSource.LAND_HERE)
    sm.update(13.002, replace(OK, mission_phase="done", ended_aloft=True))
    assert [(t.t_s, t.from_state, t.to_state, t.reason) for t in sm.transitions[-2:]] == [
        (10.0, FlightState.MISSION, FlightState.LANDING, "mission complete"),
        (13.0, FlightState.LANDING, FlightState.LANDING,
         "failsafe: the mission ended with the vehicle in the air: landing here")]
    assert sm.faults == ["13.000 s: the mission ended with the vehicle in the air"]


def test_that_a_session_limit_lands_here_disarms_on_the_ground_or_cuts() -> None:
    sm = _flying()
    sm.limit(20.0, "session time limit (20 s)")
    d = sm.update(20.0, OK)
    assert (d.state, d.reference) == (FlightState.LANDING, ReferenceSource.LAND_HERE)
    assert sm.transitions[-1].reason == "failsafe: session time limit (20 s)"
    sm.limit(140.0, "no touchdown", cut=True)
    assert sm.state is FlightState.CUT
    assert sm.transitions[-1].reason == "failsafe (cut): no touchdown"
    armed = FlightStateMachine(LIMITS)
    armed.request(0.0, "arm")
    armed.limit(0.5, "session time limit (0.5 s)")
    assert armed.state is FlightState.DISARMED
    assert armed.transitions[-1].reason == "session time limit (0.5 s): disarmed before take-off"
    preflight = FlightStateMachine(LIMITS)
    preflight.limit(0.5, "flight record lost")
    assert preflight.state is FlightState.DISARMED and preflight.finished
    assert preflight.transitions[-1].reason == "flight record lost: session ended before arming"
    assert preflight.faults == ["0.500 s: flight record lost"]
    preflight.limit(0.6, "again")  # after the session: nothing
    assert len(preflight.transitions) == 1 and len(preflight.faults) == 1


@pytest.mark.parametrize("z0_m", [2.5, 1.0, 0.4, 0.25, 0.12])
def test_that_a_landing_here_flares_to_its_touchdown_speed_above_the_ground(z0_m: float) -> None:
    from controller.pipeline import LandHere

    land = LandHere(10.0, (0.3, -0.2, z0_m), (1.0, 0.0, 0.0, 0.0), 0.1)
    dt = 0.001
    refs = [land.reference(10.0 + k * dt, 0.0) for k in range(20_000)]
    z = [r.pos_w_m[2] for r in refs]
    vz = [r.vel_w_m_s[2] for r in refs]
    az = [r.acc_w_m_s2[2] for r in refs]
    # straight down, never up, to 5 cm under the gear, and held there
    assert all(r.pos_w_m[:2] == (0.3, -0.2) for r in refs)
    assert all(b <= a + 1e-12 for a, b in itertools.pairwise(z))
    assert z[-1] == pytest.approx(0.05)
    # no faster than the descent speed; at the ground height no faster than the touchdown's
    assert min(vz) >= -0.3 - 1e-9
    at_ground = next(k for k, h in enumerate(z) if h <= 0.1)
    assert -0.12 - 1e-9 <= vz[at_ground] < 0.0
    # the velocity is the position's derivative and the acceleration the velocity's (up to the
    # stop at the end, where the reference holds)
    end = next(k for k, h in enumerate(z) if h <= 0.05 + 1e-12)
    for k in range(1, end - 1):
        assert (z[k + 1] - z[k - 1]) / (2 * dt) == pytest.approx(vz[k], abs=2e-3)
        if abs(az[k + 1] - az[k - 1]) < 1e-9:  # away from the flare's step in acceleration
            assert (vz[k + 1] - vz[k - 1]) / (2 * dt) == pytest.approx(az[k], abs=1e-2)


@pytest.mark.parametrize("z0_m", [2.5, 1.0, 0.4, 0.25, 0.12, 0.1])
def test_that_a_blind_landing_sinks_at_its_deep_speed_once_under_the_ground(z0_m: float) -> None:
    from controller.pipeline import LandHere

    # Fixture: the blind landing's reference (ground at 0.1 m, 1 m of sink, 0.3 m/s deep)
    land = LandHere(10.0, (0.3, -0.2, z0_m), (1.0, 0.0, 0.0, 0.0), 0.1, sink_m=1.0,
                    deep_m_s=0.3)
    plain = replace(land, deep_m_s=None)
    dt = 0.001
    # Test
    refs = [land.reference(10.0 + k * dt, 0.0) for k in range(30_000)]
    z = [r.pos_w_m[2] for r in refs]
    vz = [r.vel_w_m_s[2] for r in refs]
    az = [r.acc_w_m_s2[2] for r in refs]
    # Assert: down to its whole sink, never up, no faster than the deep speed
    assert all(b <= a + 1e-12 for a, b in itertools.pairwise(z))
    assert z[-1] == pytest.approx(0.1 - 1.0)
    assert min(vz) >= -0.3 - 1e-9
    # it is the plain landing's until 5 cm under the ground (or the end of the ease-in from
    # lower), arriving there at the touchdown speed
    deep = next(k for k, r in enumerate(refs) if r != plain.reference(10.0 + k * dt, 0.0))
    assert z[deep] <= 0.05 + 1e-9
    assert z[deep] >= 0.05 - 1e-3 or deep * dt == pytest.approx(1.0, abs=2e-3)
    assert -0.12 - 1e-9 <= vz[deep - 1] < 0.0
    # deeper, it speeds up to 0.3 m/s within (0.3 - 0.12) / 0.5 s and holds it to the end
    fast = next(k for k, v in enumerate(vz) if k > deep and v <= -0.3 + 1e-9)
    assert (fast - deep) * dt <= (0.3 - 0.12) / 0.5 + 2e-3
    end = next(k for k, h in enumerate(z) if h <= 0.1 - 1.0 + 1e-12)
    assert all(v == pytest.approx(-0.3) for v in vz[fast:end - 1])
    # the velocity is the position's derivative and the acceleration the velocity's (away from
    # the acceleration's steps)
    for k in range(1, end - 1):
        assert (z[k + 1] - z[k - 1]) / (2 * dt) == pytest.approx(vz[k], abs=2e-3)
        if abs(az[k + 1] - az[k - 1]) < 1e-9:
            assert (vz[k + 1] - vz[k - 1]) / (2 * dt) == pytest.approx(az[k], abs=1e-2)

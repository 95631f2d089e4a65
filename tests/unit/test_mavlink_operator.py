"""The operator vocabulary: state rules, the reference command sink, the parameter table."""

from __future__ import annotations

import math
import threading

import pytest

from groundstation.operator import (
    MAX_TAKEOFF_ALT_M,
    MAX_TILT_RAD,
    Arm,
    CommandResult,
    Disarm,
    EmergencyStop,
    FlightPhase,
    Land,
    OperatorCommand,
    OperatorCommandSink,
    ParamSpec,
    PoseSetpoint,
    RuleBasedCommandSink,
    SetParam,
    SetTilt,
    Takeoff,
    decide,
    operator_params,
)

P = FlightPhase
R = CommandResult
FLYING = (P.TAKEOFF, P.MISSION, P.LANDING)
GROUND_DISARMED = (P.PREFLIGHT, P.DISARMED)


def test_that_arm_is_accepted_only_on_the_ground_disarmed_with_preflight_passed() -> None:
    for phase in GROUND_DISARMED:
        assert decide(Arm(), phase) is R.ACCEPTED
        assert decide(Arm(), phase, preflight_ok=False) is R.TEMPORARILY_REJECTED
    assert decide(Arm(), P.ARMED) is R.ACCEPTED  # already armed: no-op
    for phase in (*FLYING, P.CUT):
        assert decide(Arm(), phase) is R.DENIED


def test_that_disarm_is_denied_in_flight_and_accepted_on_the_ground() -> None:
    for phase in FLYING:
        assert decide(Disarm(), phase) is R.DENIED
    for phase in (P.PREFLIGHT, P.ARMED, P.DISARMED, P.CUT):
        assert decide(Disarm(), phase) is R.ACCEPTED


def test_that_takeoff_needs_armed_and_a_sane_altitude() -> None:
    assert decide(Takeoff(1.0), P.ARMED) is R.ACCEPTED
    for phase in (*GROUND_DISARMED, *FLYING):
        assert decide(Takeoff(1.0), phase) is R.TEMPORARILY_REJECTED
    for alt in (0.0, -1.0, math.nan, math.inf, MAX_TAKEOFF_ALT_M + 0.1):
        assert decide(Takeoff(alt), P.ARMED) is R.DENIED


def test_that_land_is_accepted_only_when_flying() -> None:
    for phase in FLYING:
        assert decide(Land(), phase) is R.ACCEPTED
    for phase in (*GROUND_DISARMED, P.ARMED, P.CUT):
        assert decide(Land(), phase) is R.TEMPORARILY_REJECTED


def test_that_emergency_stop_is_always_accepted() -> None:
    for phase in P:
        assert decide(EmergencyStop(), phase) is R.ACCEPTED


def test_that_tilt_setpoints_and_params_are_checked_and_refused_after_a_cut() -> None:
    assert decide(SetTilt(0.3), P.MISSION) is R.ACCEPTED
    assert decide(SetTilt(MAX_TILT_RAD + 1e-6), P.MISSION) is R.DENIED
    assert decide(SetTilt(-0.01), P.ARMED) is R.DENIED
    assert decide(SetTilt(0.1), P.MISSION, max_tilt_rad=0.05) is R.DENIED
    assert decide(SetTilt(0.1), P.CUT) is R.DENIED
    assert decide(PoseSetpoint(pos_w_m=(0.0, 0.0, 1.0)), P.MISSION) is R.ACCEPTED
    assert decide(PoseSetpoint(pos_w_m=(0.0, 0.0, 1.0)), P.TAKEOFF) is R.TEMPORARILY_REJECTED
    assert decide(PoseSetpoint(pos_w_m=(math.nan, 0.0, 1.0)), P.MISSION) is R.DENIED
    assert decide(PoseSetpoint(), P.MISSION) is R.DENIED
    assert decide(SetParam("KP_POS_XY", 2.0), P.PREFLIGHT) is R.ACCEPTED
    assert decide(SetParam("KP_POS_XY", math.inf), P.PREFLIGHT) is R.DENIED
    assert decide(SetParam("KP_POS_XY", 2.0), P.CUT) is R.DENIED


def test_that_the_reference_sink_walks_a_whole_flight_and_records_every_command() -> None:
    # Fixture
    seen: list[FlightPhase] = []
    sink = RuleBasedCommandSink(on_change=seen.append)
    assert isinstance(sink, OperatorCommandSink)
    script: list[tuple[OperatorCommand, CommandResult]] = [
        (Takeoff(1.0), R.TEMPORARILY_REJECTED), (Arm(), R.ACCEPTED), (Takeoff(1.0), R.ACCEPTED),
        (Disarm(), R.DENIED), (Land(), R.ACCEPTED), (EmergencyStop(), R.ACCEPTED),
        (Arm(), R.DENIED),
    ]
    # Test
    results = [sink.submit(cmd) for cmd, _ in script]
    # Assert
    assert results == [r for _, r in script]
    assert seen == [P.ARMED, P.TAKEOFF, P.LANDING, P.CUT]
    assert sink.phase is P.CUT
    assert sink.submissions == list(zip([c for c, _ in script], results, strict=True))
    assert sink.accepted == [Arm(), Takeoff(1.0), Land(), EmergencyStop()]


def test_that_waiting_on_the_sink_wakes_when_a_command_arrives_from_another_thread() -> None:
    sink = RuleBasedCommandSink()
    t = threading.Thread(target=sink.submit, args=(Arm(),))
    t.start()
    assert sink.wait_for(lambda log: any(isinstance(c, Arm) for c, _ in log), timeout_s=30.0)
    t.join()
    assert sink.phase is P.ARMED


def test_that_operator_params_have_mavlink_names_and_only_lower_the_tilt_limits() -> None:
    params = operator_params(kp_pos=(10.0, 10.0, 20.0), kv_pos=(5.0, 5.0, 8.0),
                             ki_pos=(1.0, 1.0, 2.0), kr_att=(3.0, 3.0, 1.0),
                             kw_att=(0.5, 0.5, 0.2), max_tilt_deg=35.0, max_tilt_rate_deg_s=10.0)
    names = [p.name for p in params]
    assert len(set(names)) == len(names)
    assert all(len(n) <= 16 and n.isascii() for n in names)
    by_name = {p.name: p for p in params}
    assert by_name["KP_POS_Z"].value == 20.0
    assert by_name["KP_POS_Z"].accepts(60.0) and not by_name["KP_POS_Z"].accepts(60.1)
    assert not by_name["TILT_MAX_DEG"].accepts(35.5)
    assert by_name["TILT_MAX_DEG"].accepts(20.0)
    assert not by_name["KV_POS_XY"].accepts(math.nan)


def test_that_a_parameter_name_longer_than_sixteen_characters_is_refused() -> None:
    with pytest.raises(ValueError, match=r"1\.\.16"):
        ParamSpec("A_VERY_LONG_NAME_X", 1.0, 0.0, 2.0)
    with pytest.raises(ValueError, match="outside"):
        ParamSpec("GAIN", 3.0, 0.0, 2.0)


def test_that_the_phases_have_the_flight_state_machines_names_and_numbers() -> None:
    # the bridge's custom_mode must mean the same thing as the session's state column
    from groundstation.flight import FlightState

    assert {p.name: int(p) for p in FlightPhase} == {s.name: int(s) for s in FlightState}

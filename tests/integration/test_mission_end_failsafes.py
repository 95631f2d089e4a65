"""How a flight ends when its mission does not bring it down: a mission file that ends in the
air is refused at load, a mission spec that does (only a fragment built in code can) is landed
by the ground station itself, and the session time limit (``safety.session_time_limit_s``)
lands the vehicle once instead of cutting its motors in the air.

Real lockstep flights through the byte path (tests/flight_support.py); the vehicle's true
height comes from the record (the emulator's truth, merged in lockstep).
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from config.schema import ConfigError, load_config_text
from controller.missions import MISSION_SCHEMA, Mission, MissionSpec
from groundstation.flight import FlightState
from groundstation.loop import ENDED_ALOFT_S
from groundstation.record import read_record
from groundstation.session import FlightSession
from groundstation.session_config import load_session
from tests.flight_support import SESSION, SHORT_MISSION, short_session

GROUND_Z_M = 0.1  # the short mission's start height (O_B at rest)
TICK_S = 0.002

#: take off to 0.8 m and hold: no land (a spec fragment; a mission file like it is refused)
NO_LAND = SHORT_MISSION[:SHORT_MISSION.index("  - kind: land")]


def _transitions(outcome: object) -> list[tuple[float, FlightState, FlightState, str]]:
    result = outcome.result  # type: ignore[attr-defined]
    return [(tr.t_s, tr.from_state, tr.to_state, tr.reason) for tr in result.transitions]


def test_that_a_mission_file_ending_in_the_air_is_refused_by_the_session(
        tmp_path: Path) -> None:
    # Fixture: the short session with its mission's land segment removed
    short_session(tmp_path)  # writes the session file and its mission
    (tmp_path / "short-hover.yaml").write_text(NO_LAND)
    # Test / Assert: the error names the mission file and its last segment, nothing opens
    with pytest.raises(ConfigError) as err:
        load_session(tmp_path / "flight.yaml")
    assert err.value.file == str(tmp_path / "short-hover.yaml")
    assert err.value.key == "segments[2]"
    assert "ends in the air (z = 0.8 m): expected a land segment" in err.value.message


def test_that_a_mission_ending_in_the_air_is_landed_where_it_ends(tmp_path: Path) -> None:
    # Fixture: the mission ends at 2 s + 7.5 s of mission time, the vehicle at 0.8 m; a 30 s
    # session limit bounds the flight should the failsafe not fire (it would land at 30 s)
    cfg, params, _ = short_session(tmp_path)
    cfg = replace(cfg, safety=replace(cfg.safety, session_time_limit_s=30.0))
    mission = Mission(load_config_text(NO_LAND, MissionSpec, schema=MISSION_SCHEMA))
    # Test
    outcome = FlightSession(cfg, params, mission, record_path=tmp_path / "aloft.fhr",
                            echo_events=False).run()
    # Assert: the planned landing (the mission's end) then, ENDED_ALOFT_S later, the failsafe
    # landing from where the vehicle is, and the touchdown
    trs = _transitions(outcome)
    takeoff_t = next(t for t, _, to, _ in trs if to is FlightState.TAKEOFF)
    end_t = next(t for t, _, to, why in trs if to is FlightState.LANDING)
    aloft = [(t, why) for t, fr, to, why in trs
             if fr is FlightState.LANDING and to is FlightState.LANDING]
    assert len(aloft) == 1, trs
    t_fs, why = aloft[0]
    assert why == "failsafe: the mission ended with the vehicle in the air: landing here"
    assert end_t == pytest.approx(takeoff_t + mission.duration_s, abs=0.1)
    assert t_fs == pytest.approx(end_t + ENDED_ALOFT_S, abs=5 * TICK_S)
    assert trs[-1][2] is FlightState.DISARMED and trs[-1][3] == "touchdown"
    assert any("the mission ended with the vehicle in the air" in f
               for f in outcome.result.faults)
    rec = read_record(tmp_path / "aloft.fhr").rows
    z = rec["pos_w_m"][:, 2]
    t = rec["t_s"]
    # in the air (0.8 m) when the failsafe fired; on its gear at the end, having come down at
    # the failsafe's 0.3 m/s (0.7 m in ~3 s with its 1 s ease-in), no faster than a planned land
    assert z[np.searchsorted(t, t_fs)] == pytest.approx(0.8, abs=0.05)
    assert z[-1] == pytest.approx(GROUND_Z_M, abs=0.02)
    assert t[-1] - t_fs < 6.0
    assert np.min(rec["vel_w_m_s"][:, 2]) > -0.45


def test_that_the_session_time_limit_lands_once_and_names_itself(tmp_path: Path) -> None:
    # Fixture: the session file sets the limit (file -> config), the flight takes the value
    # from the config; 6 s is shorter than the mission (refused in a file, so replaced here)
    (tmp_path / "short-hover.yaml").write_text(SHORT_MISSION)
    path = tmp_path / "limit.yaml"
    path.write_text(SESSION.format(seed=3, faults="", corrupt=0.0, zmax=2.5,
                                   servo_action="hold").replace(
        "  servo_fault_action: hold\n",
        "  servo_fault_action: hold\n  session_time_limit_s: 600\n"))
    cfg = load_session(path)
    assert cfg.safety.session_time_limit_s == 600.0
    cfg = replace(cfg, safety=replace(cfg.safety, session_time_limit_s=6.0))
    _, params, mission = short_session(tmp_path, name="other")
    # Test
    outcome = FlightSession(cfg, params, mission, record_path=tmp_path / "limit.fhr",
                            echo_events=False).run()
    # Assert: one failsafe landing at the limit (not a cut 2 ms later), then the touchdown
    trs = _transitions(outcome)
    landing = [(t, why) for t, _, to, why in trs if to is FlightState.LANDING]
    # the first tick past the limit
    assert landing == [(pytest.approx(6.0 + TICK_S, abs=TICK_S / 2),
                        "failsafe: session time limit (6 s)")]
    assert not any(to is FlightState.CUT for _, _, to, _ in trs)
    assert trs[-1][2] is FlightState.DISARMED and trs[-1][3] == "touchdown"
    assert outcome.result.end_reason == "failsafe: session time limit (6 s)"
    assert len(outcome.result.faults) == 1
    assert outcome.result.faults[0].endswith(" s: session time limit (6 s)")


def test_that_a_time_limit_shorter_than_the_mission_is_refused(tmp_path: Path) -> None:
    # Fixture: 12 s, against 2 s of preflight and spin-up plus the 12.5 s mission
    (tmp_path / "short-hover.yaml").write_text(SHORT_MISSION)
    path = tmp_path / "short.yaml"
    path.write_text(SESSION.format(seed=3, faults="", corrupt=0.0, zmax=2.5,
                                   servo_action="hold").replace(
        "  servo_fault_action: hold\n", "  servo_fault_action: hold\n  session_time_limit_s: 12\n"))
    # Test / Assert
    with pytest.raises(ConfigError) as err:
        load_session(path)
    assert err.value.key == "safety.session_time_limit_s"
    assert err.value.line == path.read_text().splitlines().index(
        "  session_time_limit_s: 12") + 1
    assert err.value.message == ("12 s ends the session before its mission (12.5 s after 2 s "
                                 "of preflight and spin-up): expected >= 14.5 s")


def test_that_a_landing_on_the_estimate_touches_down_slowly_and_stays_down(
        tmp_path: Path) -> None:
    # Fixture: the short session, an operator landing (land on the estimate) mid-hover, 0.8 m up
    cfg, params, mission = short_session(tmp_path)
    # Test
    outcome = FlightSession(cfg, params, mission, record_path=tmp_path / "here.fhr",
                            echo_events=False, scripted_requests=((6.0, "land"),)).run()
    # Assert: the flare brings the true vehicle to the ground at the landing's touchdown speed
    # (0.12 m/s, under the 0.18 m/s a land segment may reach), and it does not rise again (at
    # 0.3 m/s it touched down, the estimate kept descending and the controller lifted it by
    # 4-7 mm, climbing at 0.10-0.14 m/s)
    trs = _transitions(outcome)
    assert [why for _, _, to, why in trs if to is FlightState.LANDING] == ["operator: land"]
    assert trs[-1][2] is FlightState.DISARMED and trs[-1][3] == "touchdown"
    rec = read_record(tmp_path / "here.fhr").rows
    z, vz = rec["pos_w_m"][:, 2], rec["vel_w_m_s"][:, 2]
    last_aloft = int(np.where(z > GROUND_Z_M + 0.2)[0][-1])
    contact = last_aloft + int(np.argmax(z[last_aloft:] <= GROUND_Z_M + 0.001))
    assert -0.15 < vz[contact - 1] < -0.08
    assert np.max(z[contact:]) - z[contact] < 0.001


def test_that_a_landing_on_an_estimate_stuck_in_the_air_ends_on_the_imus_touchdown(
        tmp_path: Path) -> None:
    # Fixture: MoCap frozen at 5 s (it keeps streaming the pose of then, with its noise): the
    # estimate stays near it, MoCap and IMU disagree, the failsafe lands on that estimate,
    # which never comes near the ground. A 30 s limit bounds the flight should the IMU's
    # touchdown not end it (it idled on the ground until the one-hour limit)
    cfg, params, mission = short_session(tmp_path)
    cfg = replace(cfg, backend=replace(cfg.backend, faults=("mocap-freeze@5",)),
                  safety=replace(cfg.safety, session_time_limit_s=30.0))
    # Test
    outcome = FlightSession(cfg, params, mission, record_path=tmp_path / "stuck.fhr",
                            echo_events=False).run()
    # Assert: disarmed by the IMU (still at low thrust for 1 s), on the ground, soon after
    trs = _transitions(outcome)
    t_land, _, _, why = next(tr for tr in trs if tr[2] is FlightState.LANDING)
    assert why.startswith("failsafe: MoCap and IMU disagree")
    t_end, frm, to, why = trs[-1]
    assert (frm, to, why) == (FlightState.LANDING, FlightState.DISARMED,
                              "touchdown (IMU: still at low thrust)")
    assert t_end - t_land < 6.0
    assert any("touchdown seen by the IMU only" in f for f in outcome.result.faults)
    rec = read_record(tmp_path / "stuck.fhr").rows
    assert rec["pos_w_m"][-1][2] == pytest.approx(GROUND_Z_M, abs=0.01)  # truth: on its gear
    assert rec["est_pos_w_m"][-1][2] > GROUND_Z_M + 0.1  # the estimate: still up

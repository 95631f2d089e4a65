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
from controller.missions import MAX_TOUCHDOWN_SPEED_M_S, MISSION_SCHEMA, Mission, MissionSpec
from groundstation.configs import load_vehicle
from groundstation.flight import FlightState
from groundstation.loop import BLIND_THRUST_FRACTION, ENDED_ALOFT_S, GROUND_CONTACT_S
from groundstation.record import read_record
from groundstation.session import FlightSession
from groundstation.session_config import load_session
from tests.flight_support import SESSION, SHORT_MISSION, fly, short_session

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


def _contact(rec: np.ndarray) -> tuple[int, float]:
    """The row of the last touchdown (the true vehicle back on its gear) and the vertical speed
    it came down at (m/s, positive down)."""
    z, vz = rec["pos_w_m"][:, 2], rec["vel_w_m_s"][:, 2]
    last_aloft = int(np.where(z > GROUND_Z_M + 0.02)[0][-1])
    contact = last_aloft + int(np.argmax(z[last_aloft:] <= GROUND_Z_M + 0.001))
    return contact, float(-vz[contact - 1])


def test_that_a_landing_after_the_mocap_froze_runs_on_the_imu_and_ends_on_its_touchdown(
        tmp_path: Path) -> None:
    # Fixture: MoCap frozen at 5 s in the hover (it keeps streaming the pose of then, with its
    # noise). The UKF fuses it, dragged along; MoCap compared with the IMU alone turns and
    # changes velocity as the IMU does not feel it: MoCap and IMU disagree, the failsafe
    # lands. Landing on that estimate, held near the frozen pose, brought the vehicle down at
    # idle, 1.2-1.5 m/s; the estimate goes back to before the comparison's horizon and runs
    # on the IMU alone from there. Before the comparison only repeated re-seeds told, 1.5-3 s
    # after a freeze. A 30 s limit bounds the flight should the landing not end.
    cfg, params, mission = short_session(tmp_path)
    cfg = replace(cfg, backend=replace(cfg.backend, faults=("mocap-freeze@5",)),
                  safety=replace(cfg.safety, session_time_limit_s=30.0))
    events: list[str] = []
    # Test
    outcome = FlightSession(cfg, params, mission, record_path=tmp_path / "frozen.fhr",
                            echo_events=False, on_event=events.append).run()
    # Assert: found within a second by the comparison, landed on the IMU alone, disarmed by
    # the IMU's touchdown (the estimate's own is not trusted then), soon after
    trs = _transitions(outcome)
    t_land, _, _, why = next(tr for tr in trs if tr[2] is FlightState.LANDING)
    assert why.startswith("failsafe: MoCap and IMU disagree")
    assert 5.0 < t_land < 5.0 + 1.0
    assert any("MoCap disagrees with the IMU alone over the last 1.10 s" in e for e in events)
    assert any("MoCap disagrees with the IMU: its poses are no longer fused" in e
               for e in events)
    t_end, frm, to, why = trs[-1]
    assert (frm, to, why) == (FlightState.LANDING, FlightState.DISARMED,
                              "touchdown (IMU: still at low thrust)")
    assert t_end - t_land < 9.0  # 0.7 m at 0.3 m/s, the flare, the IMU's 1 s and the thrust's
    # descent to 60 % of the weight on the ground
    rec = read_record(tmp_path / "frozen.fhr").rows
    contact, speed = _contact(rec)
    assert speed < MAX_TOUCHDOWN_SPEED_M_S        # truth: a landing, not a fall
    assert np.max(rec["pos_w_m"][contact:, 2]) - GROUND_Z_M < 0.002   # and it stayed down
    assert rec["pos_w_m"][-1][2] == pytest.approx(GROUND_Z_M, abs=0.01)
    drift = np.hypot(*(rec["pos_w_m"][-1][:2] - rec["pos_w_m"][0][:2]))
    # dead reckoned for ~7 s (from 1.7 s before the failsafe to the touchdown): 0.13 m here;
    # found by the re-seeds, dead reckoned from 3 s back for ~10 s: 1.2 m
    assert drift < 0.3


def test_that_a_tracker_frozen_in_a_steady_hover_is_found_by_a_velocity_the_imu_did_not_feel(
        tmp_path: Path) -> None:
    # Fixture: MoCap frozen at 7.5 s, the vehicle holding its attitude in the hover: MoCap's
    # rotation agrees with the gyro's for a while. The vehicle, its estimate held still,
    # drifts off at a growing speed (0.08 m/s after 1 s) that MoCap does not show and the
    # accelerometer feels. Found by the repeated re-seeds, it was 3 s later, 0.5 m away.
    events: list[str] = []
    out = fly(tmp_path, faults="mocap-freeze@7.5", on_event=events.append)
    trs = _transitions(out)
    t_land, _, _, why = next(tr for tr in trs if tr[2] is FlightState.LANDING)
    assert why.startswith("failsafe: MoCap and IMU disagree")
    assert 7.5 < t_land < 7.5 + 1.2
    seen = next(e for e in events if "MoCap disagrees with the IMU alone" in e)
    assert "changed velocity" in seen
    assert trs[-1][1:] == (FlightState.LANDING, FlightState.DISARMED,
                           "touchdown (IMU: still at low thrust)")
    rec = read_record(out.record_path).rows
    _, speed = _contact(rec)
    assert speed < MAX_TOUCHDOWN_SPEED_M_S
    assert np.hypot(*(rec["pos_w_m"][-1][:2] - rec["pos_w_m"][0][:2])) < 0.15


def test_that_a_dead_reckoned_landing_stands_still_on_the_ground_and_disarms_there(
        tmp_path: Path) -> None:
    # Fixture: seed 1, MoCap frozen at 6 s in the hover. The landing runs on the IMU alone
    # and its estimate drifts on the ground (0.1 m in the first second). Chasing it, the
    # controller asked for the attitude a horizontal force needs: 5 N m of torque 0.8 s after
    # the touchdown, the motors saturated, the vehicle rocked on its gear (no longer still to
    # the IMU) and the IMU rate check cut the motors 5 s later, the vehicle 1.4 m from where it
    # had landed. The touchdown rule also waited for the reference to sink 0.3 m below the
    # ground (2.4 s at the touchdown's 0.12 m/s)
    events: list[str] = []
    out = fly(tmp_path, seed=1, faults="mocap-freeze@6", on_event=events.append)
    trs = _transitions(out)
    assert next(tr for tr in trs if tr[2] is FlightState.LANDING)[3].startswith(
        "failsafe: MoCap and IMU disagree")
    assert not any(tr[2] is FlightState.CUT for tr in trs)
    t_end, frm, to, why = trs[-1]
    assert (frm, to, why) == (FlightState.LANDING, FlightState.DISARMED,
                              "touchdown (IMU: still at low thrust)")
    rec = read_record(out.record_path).rows
    contact, speed = _contact(rec)
    assert speed < MAX_TOUCHDOWN_SPEED_M_S
    t = rec["t_s"]
    # disarmed 1 s (the IMU held still) after the thrust fell under 0.9 of the weight: it
    # falls from the weight as the reference sinks past the estimate (0.3 s here)
    assert t_end - t[contact] < 1.6
    # on the ground: once the ground's support has been felt for GROUND_CONTACT_S (the IMU
    # still, the thrust under 0.9 of the weight), no horizontal chase: no torque beyond
    # holding the attitude (1.3 N m in the 0.25 s before; 5 N m 0.8 s after the contact
    # without the hold), the gear flat on the ground
    weight_n = load_vehicle("fasthex").mass_kg * 9.81
    low = contact + int(np.argmax(rec["u_f_b_n"][contact:, 2] < BLIND_THRUST_FRACTION
                                  * weight_n))
    felt = low + int((GROUND_CONTACT_S + 0.01) / TICK_S)
    assert t[felt] - t[contact] < 0.5
    torque = np.linalg.norm(rec["u_tau_b_n_m"][felt:], axis=1)
    assert np.max(torque) < 0.5
    q = rec["q_wb"][contact:]
    tilt_deg = np.degrees(2.0 * np.arcsin(np.minimum(1.0, np.hypot(q[:, 1], q[:, 2]))))
    assert np.max(tilt_deg) < 1.0
    moved = np.hypot(*(rec["pos_w_m"][-1][:2] - rec["pos_w_m"][contact][:2]))
    assert moved < 0.005


def test_that_a_dead_reckoned_landing_that_never_touches_down_is_cut(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # Fixture: the frozen-MoCap landing above, with the dead reckoning made wrong on purpose
    # (from the rewind on, every accelerometer sample reads 0.5 m/s^2 low on z: the estimate
    # believes it sinks faster than it does, so the controller holds the true vehicle up
    # while the estimate goes down through the ground). Only the IMU's touchdown ends a blind
    # landing, and it never comes: the landing is bounded, the motors are cut once the
    # reference has sunk BLIND_SINK_M below the ground (a fly-away on a drifting estimate
    # climbed to 150 km in the simulator without the bound)
    import groundstation.loop as loop_mod

    original = loop_mod.FlightLoop._dead_reckon

    def wrong_dead_reckoning(self: loop_mod.FlightLoop, t_s: float) -> float:
        back = original(self, t_s)
        predict = self.ukf.predict

        def low_accel(t: float, gyro: object, accel: tuple[float, float, float],
                      force: object = None) -> None:
            predict(t, gyro, (accel[0], accel[1], accel[2] - 0.5), force)

        self.ukf.predict = low_accel  # type: ignore[method-assign]
        return back

    monkeypatch.setattr(loop_mod.FlightLoop, "_dead_reckon", wrong_dead_reckoning)
    cfg, params, mission = short_session(tmp_path)
    cfg = replace(cfg, backend=replace(cfg.backend, faults=("mocap-freeze@5",)),
                  safety=replace(cfg.safety, session_time_limit_s=30.0))
    # Test
    outcome = FlightSession(cfg, params, mission, record_path=tmp_path / "lost.fhr",
                            echo_events=False).run()
    # Assert: cut by the bound (not by the session time limit), while the vehicle was in the
    # air: the reference needs ~(0.8 m + 1 m) / 0.12-0.3 m/s to get there
    trs = _transitions(outcome)
    t_land = next(tr[0] for tr in trs if tr[2] is FlightState.LANDING)
    t_cut, frm, _, why = next(tr for tr in trs if tr[2] is FlightState.CUT)
    assert (frm, why) == (FlightState.LANDING, "failsafe (cut): no touchdown felt by the IMU "
                          f"{loop_mod.BLIND_SINK_M:g} m below the ground on the dead-reckoned "
                          "estimate")
    assert 5.0 < t_cut - t_land < 15.0
    assert trs[-1][2] is FlightState.DISARMED
    rec = read_record(tmp_path / "lost.fhr").rows
    assert rec["pos_w_m"][-1][2] > GROUND_Z_M + 0.1  # truth: still up when cut (the bound)
    assert max(rec["spin_hz"][-1]) == 0.0


def test_that_a_blind_landing_presses_on_the_ground_at_its_impact_and_not_at_a_jolt_aloft(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # Fixture: seed 5, tracker frozen at 6 s on a 0.5 % corrupted IMU link: a blind landing
    # whose dead reckoning still sinks at ~0.07 m/s after the touchdown. Without the impact's
    # press the thrust stayed at 0.95-0.98 of the weight on the ground (over the touchdown
    # rule's 0.9), the controller chased the estimate's drift (0.35 m/s sideways, its attitude
    # 4-6 deg off), rocked the vehicle on its gear to 56 deg and the IMU rate check cut it
    # 1.1 s after the touchdown. A jolt on the IMU at 8.3 s, 0.5 m up (+4.5 m/s^2 on z for two
    # samples, the touchdown's impact read +5.7 for three), is not the ground: the press it
    # starts reads no ground's support and ends. (The jolt also kicks the dead reckoning: with
    # +6 m/s^2 for three samples the touchdown came at 0.20 m/s, with or without the press.)
    import dataclasses

    import groundstation.loop as loop_mod

    jolt_seq = range(4150, 4152)  # 8.300-8.302 s
    original = loop_mod.FlightLoop._next_imu

    def jolted(self: loop_mod.FlightLoop, timeout_s: float) -> object:
        imu = original(self, timeout_s)
        if imu is not None and imu.seq in jolt_seq:
            ax, ay, az = imu.accel_m_s2
            imu = dataclasses.replace(imu, accel_m_s2=(ax, ay, az + 4.5))
        return imu

    monkeypatch.setattr(loop_mod.FlightLoop, "_next_imu", jolted)
    events: list[str] = []
    # Test
    out = fly(tmp_path, seed=5, faults="mocap-freeze@6", corrupt=0.005, on_event=events.append)
    # Assert: the jolt pressed for IMPACT_CONFIRM_S, then the landing went on; the touchdown's
    # impact pressed, the IMU read the ground's support, disarmed standing, level, in place
    impacts = [float(e.split(" s ")[0]) for e in events if "the IMU felt an impact" in e]
    aloft = [float(e.split(" s ")[0]) for e in events if "not the ground" in e]
    assert len(impacts) == 2 and len(aloft) == 1, events
    assert impacts[0] == pytest.approx(8.302, abs=0.003)
    assert aloft[0] - impacts[0] == pytest.approx(loop_mod.IMPACT_CONFIRM_S, abs=0.003)
    trs = _transitions(out)
    assert not any(tr[2] is FlightState.CUT for tr in trs), trs
    assert trs[-1][1:] == (FlightState.LANDING, FlightState.DISARMED,
                           "touchdown (IMU: still at low thrust)")
    rec = read_record(out.record_path).rows
    t = rec["t_s"]
    contact, speed = _contact(rec)
    assert speed < MAX_TOUCHDOWN_SPEED_M_S
    assert impacts[1] - t[contact] < 0.05
    # pressed: the thrust under 0.8 of the weight from 0.05 s after the touchdown on (without
    # the press it stayed at 0.95-0.98 of it for 0.4 s, then the rocking began)
    weight_n = load_vehicle("fasthex").mass_kg * 9.81
    pressed = rec["u_f_b_n"][contact + int(0.05 / TICK_S):, 2]
    assert np.max(pressed) < 0.8 * weight_n
    assert trs[-1][0] - t[contact] < 1.6
    q = rec["q_wb"][contact + int(0.1 / TICK_S):]  # after the touchdown's own rocking
    tilt_deg = np.degrees(2.0 * np.arcsin(np.minimum(1.0, np.hypot(q[:, 1], q[:, 2]))))
    assert np.max(tilt_deg) < 2.0
    moved = np.hypot(*(rec["pos_w_m"][-1][:2] - rec["pos_w_m"][contact][:2]))
    assert moved < 0.005


def test_that_a_blind_landing_on_an_estimate_sinking_under_the_vehicle_still_comes_down(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # Fixture: MoCap frozen at 6 s in the hover (found 0.5 s later: the landing runs on the
    # IMU alone), and the accelerometer's z reading 0.12 m/s^2 low over 7-8 s (a kick the
    # dead reckoning cannot tell from motion): the estimate's height sinks 0.12 m/s faster
    # than the vehicle's from then on, and reaches the ground with the vehicle 0.23 m up.
    # Sinking on into the ground at the touchdown's 0.12 m/s, the vehicle hovered there for
    # 7 s, slid 2.5 m on its attitude's drift, and the cut 1 m under the ground dropped it
    # from 0.18 m (1.9 m/s; seen so on a 0.5 % corrupted link, seed 9, MoCap frozen at 4.5 s).
    import dataclasses

    import groundstation.loop as loop_mod

    kicked_seq = range(3500, 4000)  # 7.0-8.0 s
    original = loop_mod.FlightLoop._next_imu

    def kicked(self: loop_mod.FlightLoop, timeout_s: float) -> object:
        imu = original(self, timeout_s)
        if imu is not None and imu.seq in kicked_seq:
            ax, ay, az = imu.accel_m_s2
            imu = dataclasses.replace(imu, accel_m_s2=(ax, ay, az - 0.12))
        return imu

    monkeypatch.setattr(loop_mod.FlightLoop, "_next_imu", kicked)
    events: list[str] = []
    # Test
    out = fly(tmp_path, seed=1, faults="mocap-freeze@6", on_event=events.append)
    # Assert: a blind landing whose reference went deep, ended by its touchdown (no cut)
    assert any("MoCap disagrees with the IMU:" in e for e in events), events
    trs = _transitions(out)
    assert not any(tr[2] is FlightState.CUT for tr in trs), trs
    assert trs[-1][1:] == (FlightState.LANDING, FlightState.DISARMED,
                           "touchdown (IMU: still at low thrust)"), trs
    rec = read_record(out.record_path).rows
    # the estimate was under the vehicle: the reference went deep before the touchdown
    contact, speed = _contact(rec)
    assert np.min(rec["pos_ref_w_m"][:contact, 2]) < GROUND_Z_M - 0.15
    assert out.truth is not None and out.truth["landed"] and not out.truth["crash"]
    assert speed < 0.3  # no faster than the deep sink (the drift makes it slower)
    assert trs[-1][0] - rec["t_s"][contact] < 1.6
    assert np.hypot(*(rec["pos_w_m"][-1][:2] - rec["pos_w_m"][0][:2])) < 0.6

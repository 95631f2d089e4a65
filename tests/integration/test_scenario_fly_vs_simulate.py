"""One scenario file, flown twice: in-process (``simulate``'s ``fly_mission`` with the UKF) and
through the byte path (an emulated lockstep session naming it in ``backend.scenario``).

The two differ by the byte path (the drivers, the MoCap over UDP, the servo over a pty, the
ground station's take-off logic) and by when the mission starts in simulated time, so the
comparison is on the scenario's own effects, with tolerances:

- the plant (a payload) shows the same in both: the hover spins agree within 1 %;
- the gust (2 N, 1 - cos over 1 s) moves the vehicle the same way: peak deviation within 30 %,
  at the same mission time within 0.1 s;
- the mean position error of the hover around the gust agrees within 20 %.

The preset is the paper-calibrated one without its Ornstein-Uhlenbeck force: that random force
is drawn per physics step from the start of the simulation, and the two flights start their
missions at different simulated times, so it would differ between them by chance alone.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from flight_support import SESSION

from config import find_config
from controller.missions import Mission
from groundstation.configs import load_disturbances, load_mission, load_scenario, load_vehicle
from groundstation.flight import FlightState
from groundstation.record import RecordWriter, read_record
from groundstation.session import FlightSession
from groundstation.session_config import load_session
from sim_backend.closed_loop import UkfStateSource, fly_mission

MISSION = """\
schema: fasthex.mission
version: 1
name: gust-hover
description: take off, hover through a gust, land
start_pos_w_m: [0.0, 0.0, 0.1]
segments:
  - kind: takeoff
    duration_s: 2.5
    height_m: 0.8
    alpha: {kind: constant, value_deg: 0.0}
  - kind: hold
    duration_s: 7.0
  - kind: land
    duration_s: 4.5
  - kind: hold
    duration_s: 0.5
    measured: false
"""

SCENARIO = """\
schema: fasthex.scenario
version: 1
name: payload-and-gust
plant:
  payload_kg: 0.2
disturbances:
  - kind: gust
    frame: world
    force_n: [0.0, 2.0, 0.0]
    start_s: 5.0
    duration_s: 1.0
"""

GUST_START_S, GUST_END_S = 5.0, 6.0
#: the hover whose mean error is compared: settled after the take-off, before the landing
HOVER_S = (3.5, 9.5)


def _preset_without_ou(tmp_path: Path) -> Path:
    text = find_config("disturbances", "paper-calibrated").read_text()
    text = text.replace("name: paper-calibrated", "name: paper-calibrated-no-ou")
    text = text.replace("ou_force_rms_n: 0.3", "ou_force_rms_n: 0.0")
    path = tmp_path / "no-ou.yaml"
    path.write_text(text)
    return path


def _summary(t_mission_s: np.ndarray, pos: np.ndarray, ref: np.ndarray,
             spins: np.ndarray) -> dict[str, float]:
    err = pos - ref
    hover = (t_mission_s >= HOVER_S[0]) & (t_mission_s < HOVER_S[1])
    gust = (t_mission_s >= GUST_START_S) & (t_mission_s < GUST_END_S + 1.0)
    before = (t_mission_s >= HOVER_S[0]) & (t_mission_s < GUST_START_S)
    k = int(np.argmax(np.abs(err[gust, 1])))
    return {
        "hover_err_mean_mm": 1e3 * float(np.linalg.norm(err[hover], axis=1).mean()),
        "gust_peak_dev_y_mm": 1e3 * float(err[gust, 1][k]),
        "gust_peak_t_s": float(t_mission_s[gust][k]),
        "hover_spin_mean_hz": float(spins[before].mean()),
    }


def test_that_a_scenario_flies_the_same_in_simulate_and_in_emulated_fly(
        tmp_path: Path) -> None:
    # Fixture
    (tmp_path / "gust-hover.yaml").write_text(MISSION)
    (tmp_path / "scenario.yaml").write_text(SCENARIO)
    preset_path = _preset_without_ou(tmp_path)
    session_text = SESSION.format(seed=4, faults="", corrupt=0.0, zmax=2.5,
                                  servo_action="hold")
    session_text = session_text.replace("mission: short-hover.yaml", "mission: gust-hover.yaml")
    session_text = session_text.replace("disturbances: paper-calibrated",
                                        f"disturbances: {preset_path.name}\n"
                                        "  scenario: scenario.yaml")
    (tmp_path / "session.yaml").write_text(session_text)
    params = load_vehicle("fasthex")
    mission = Mission(load_mission(tmp_path / "gust-hover.yaml"))
    scenario = load_scenario(tmp_path / "scenario.yaml", vehicle=params,
                             mission_duration_s=mission.duration_s)
    preset = load_disturbances(preset_path)

    # Test: simulate
    writer = RecordWriter(None, {})
    fly_mission(params, mission, preset, seed=4, sink=writer, scenario=scenario,
                state_source=UkfStateSource(params.mass_kg, params.gravity_m_s2),
                preroll_s=1.0)
    sim_rows = writer.close().rows
    simulated = _summary(sim_rows["t_s"], sim_rows["pos_w_m"], sim_rows["pos_ref_w_m"],
                         sim_rows["spin_cmd_hz"])

    # Test: emulated fly, lockstep
    cfg = load_session(tmp_path / "session.yaml")
    out = FlightSession(cfg, params, mission, record_path=tmp_path / "fly.fhr",
                        echo_events=False).run()
    takeoff_s = next(t.t_s for t in out.result.transitions if t.to_state is FlightState.TAKEOFF)
    fly_rows = read_record(out.record_path).rows
    flown = _summary(fly_rows["t_s"] - takeoff_s, fly_rows["pos_w_m"], fly_rows["pos_ref_w_m"],
                     fly_rows["spin_cmd_hz"])
    print(f"simulate: {simulated}\nfly:      {flown}")  # the measured agreement, with -s

    # Assert
    assert out.result.faults == []
    assert flown["hover_spin_mean_hz"] == pytest.approx(simulated["hover_spin_mean_hz"],
                                                        rel=0.01)
    # the gust pushes along +y in both, by a similar amount, at the same time
    assert simulated["gust_peak_dev_y_mm"] > 10.0 and flown["gust_peak_dev_y_mm"] > 10.0
    assert abs(flown["gust_peak_dev_y_mm"] / simulated["gust_peak_dev_y_mm"] - 1.0) < 0.3
    assert abs(flown["gust_peak_t_s"] - simulated["gust_peak_t_s"]) < 0.1
    assert abs(flown["hover_err_mean_mm"] / simulated["hover_err_mean_mm"] - 1.0) < 0.2

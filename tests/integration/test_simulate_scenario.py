"""Scenarios flown in-process (``fly_mission``, what ``fasthex simulate --scenario`` runs): the
plant the controller does not know, scheduled forces and scheduled faults, checked on values.

Most flights use the ``ideal`` preset and the true state, so that what is measured is the
scenario's effect alone and a prediction from statics holds to the integrators' settling.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from config.schema import load_config_text
from controller.missions import MISSION_SCHEMA, Mission, MissionSpec
from groundstation.cli import main
from groundstation.configs import load_disturbances, load_vehicle
from groundstation.record import RecordWriter
from sim_backend.closed_loop import UkfStateSource, fly_mission
from sim_backend.scenario import DisturbanceEvent, PlantOverrides, Scenario

PARAMS = load_vehicle("fasthex")
IDEAL = load_disturbances("ideal")
TAKEOFF_S = 3.0


def hover_mission(hold_s: float, alpha_deg: float = 0.0) -> Mission:
    """Take off to 1 m in 3 s at a constant tilt, hold ``hold_s`` (no landing: the rows end at
    the mission's end)."""
    text = f"""\
schema: fasthex.mission
version: 1
name: hover
start_pos_w_m: [0.0, 0.0, 0.1]
segments:
  - kind: takeoff
    duration_s: {TAKEOFF_S}
    height_m: 1.0
    alpha: {{kind: constant, value_deg: {alpha_deg}}}
  - kind: hold
    duration_s: {hold_s}
"""
    return Mission(load_config_text(text, MissionSpec, schema=MISSION_SCHEMA))


def fly(scenario: Scenario | None, mission: Mission, **kwargs: object) -> np.ndarray:
    """The flight record's rows of the mission (``t_s`` is mission time)."""
    writer = RecordWriter(None, {})
    fly_mission(PARAMS, mission, kwargs.pop("preset", IDEAL), seed=3,  # type: ignore[arg-type]
                sink=writer, scenario=scenario, duration_s=mission.duration_s,
                **kwargs)  # type: ignore[arg-type]
    return writer.close().rows


def mean_spins_hz(rows: np.ndarray, t_from_s: float, t_to_s: float) -> np.ndarray:
    k = (rows["t_s"] >= t_from_s) & (rows["t_s"] < t_to_s)
    return np.asarray(rows["spin_hz"][k].mean(axis=0))


def test_that_a_heavier_plant_raises_the_hover_spin_by_the_root_of_the_mass_ratio() -> None:
    # Fixture: 300 g the controller does not know about
    mission = hover_mission(12.0)
    heavy = Scenario(name="payload", plant=PlantOverrides(payload_kg=0.3))
    # Test
    nominal = mean_spins_hz(fly(None, mission), 12.0, 15.0)
    loaded = mean_spins_hz(fly(heavy, mission), 12.0, 15.0)
    # Assert: thrust ~ spin^2 carries m g; the position integral finds the extra weight
    # (measured: 1.047268 against sqrt(3.4/3.1) = 1.047270)
    expected = math.sqrt((PARAMS.mass_kg + 0.3) / PARAMS.mass_kg)
    np.testing.assert_allclose(loaded / nominal, expected, rtol=1e-3)


def test_that_a_weak_rotor_spins_faster_by_the_root_of_its_thrust_coefficient() -> None:
    # Fixture: at 30 deg the allocation is square and invertible, so equilibrium fixes every
    # rotor's actual thrust: rotor 3 with 90 % of c_f must spin 1/sqrt(0.9) faster
    mission = hover_mission(15.0, alpha_deg=30.0)
    weak = Scenario(name="weak-rotor-3",
                    plant=PlantOverrides(thrust_coeff_scale=(1.0, 1.0, 0.9, 1.0, 1.0, 1.0)))
    # Test
    nominal = mean_spins_hz(fly(None, mission), 15.0, 18.0)
    ratio = mean_spins_hz(fly(weak, mission), 15.0, 18.0) / nominal
    # Assert (measured: rotor 3 1.05408 against 1.05409; the others within 0.6 %, the
    # attitude integral still settling)
    assert ratio[2] == pytest.approx(1.0 / math.sqrt(0.9), rel=2e-3)
    others = np.delete(ratio, 2)
    np.testing.assert_allclose(others, 1.0, atol=0.015)


def test_that_a_step_gust_pushes_the_vehicle_its_way_and_the_controller_brings_it_back(
        ) -> None:
    # Fixture: 2 N along world x from 6 s on (hover settled at 1 m by then)
    start_s = 6.0
    mission = hover_mission(15.0)
    gust = Scenario(name="step", disturbances=(
        DisturbanceEvent(kind="step", force_n=(2.0, 0.0, 0.0), start_s=start_s),))
    # Test
    rows = fly(gust, mission)
    # Assert
    t, err = rows["t_s"], rows["pos_w_m"] - rows["pos_ref_w_m"]
    before, after = t < start_s, t >= start_s
    assert np.abs(err[before & (t > 5.0)]).max() < 1e-3  # settled, nothing pushes yet
    k = int(np.argmax(np.linalg.norm(err[after], axis=1)))
    peak = err[after][k]
    # along the force: F / K_p = 40 mm static, 49 mm measured with the overshoot
    assert 0.03 < peak[0] < 0.06 and abs(peak[1]) < 1e-3 and abs(peak[2]) < 2e-3
    dist = np.linalg.norm(err, axis=1)
    last_out = t[after & (dist >= 0.01)].max()
    recovery_s = last_out - start_s
    print(f"step gust 2 N: peak {1e3 * peak[0]:.1f} mm at {t[after][k] - start_s:.2f} s, "
          f"back under 10 mm after {recovery_s:.2f} s")
    # the integral's slow pole (K_i / K_p = 0.4 /s) sets it: measured 3.51 s
    assert 2.0 < recovery_s < 5.0
    assert dist[-1] < 1e-3


def test_that_a_centre_of_mass_offset_needs_a_steady_torque_the_integral_supplies() -> None:
    # Fixture: the centre of mass 2 cm towards rotor 1 (+x body), alpha = 0
    c_m = 0.02
    mission = hover_mission(30.0)
    offset = Scenario(name="com", plant=PlantOverrides(com_offset_b_m=(c_m, 0.0, 0.0)))
    # Test
    rows = fly(offset, mission)
    # Assert: the rotors carry m g and the moment m g c about O_B: minimum-norm thrusts
    # f_i = m g / 6 (1 + 2 c cos(yaw_i) / l), so the spins go as the root of that
    end_s = rows["t_s"][-1]
    spins = mean_spins_hz(rows, end_s - 3.0, end_s)
    yaw = np.arange(6) * math.pi / 3.0
    predicted = np.sqrt(1.0 + 2.0 * c_m * np.cos(yaw) / PARAMS.geometry.arm_length_m)
    np.testing.assert_allclose(spins / spins.mean(), predicted / predicted.mean(), rtol=5e-3)
    assert spins[0] > spins[1] > spins[2] > spins[3]  # rotor 1 under the offset works most
    # the controller's torque about y is the moment of the weight, -m g c
    tau_y = rows["u_tau_b_n_m"][rows["t_s"] > end_s - 3.0][:, 1].mean()
    weight_moment = PARAMS.mass_kg * PARAMS.gravity_m_s2 * c_m
    assert tau_y == pytest.approx(-weight_moment, rel=0.02)
    # supplied by the integral: the attitude error (the proportional part) decays from the
    # K_R-only value m g c / K_R (2.3 deg) towards zero
    def pitch_error_rad(t_s: float) -> float:
        i = int(np.argmin(np.abs(rows["t_s"] - t_s)))
        qd, qb = rows["q_wd"][i], rows["q_wb"][i]
        # angle(R_d, R_B): 2 asin |vec(q_d^-1 q_b)|, all of it about y here
        dot = abs(float(np.dot(qd, qb)))
        return 2.0 * math.acos(min(1.0, dot))
    kr_y = PARAMS.controller.kr_att[1]
    errors = [pitch_error_rad(t) for t in (5.0, 15.0, 25.0, end_s)]
    assert errors[0] > errors[1] > errors[2] > errors[3]
    assert kr_y * errors[-1] < 0.2 * weight_moment  # > 80 % from the integral at the end


def test_that_a_scheduled_mocap_dropout_degrades_the_ukf_estimate_over_its_window() -> None:
    # Fixture: paper-calibrated sensors, the UKF; the same flight with and without 0.5 s of
    # occluded markers from 8 s
    preset = load_disturbances("paper-calibrated")
    mission = hover_mission(6.0)
    t0_s, dur_s = 8.0, 0.5
    runs = []
    for faults in ((), (f"mocap-dropout@{t0_s}:{dur_s}",)):
        rows = fly(Scenario(name="dropout", faults=faults), mission, preset=preset,
                   state_source=UkfStateSource(PARAMS.mass_kg, PARAMS.gravity_m_s2),
                   preroll_s=1.0)
        runs.append(rows)
    base, drop = runs
    t = base["t_s"]
    assert np.array_equal(t, drop["t_s"])
    err_base = np.linalg.norm(base["est_pos_w_m"] - base["pos_w_m"], axis=1)
    err_drop = np.linalg.norm(drop["est_pos_w_m"] - drop["pos_w_m"], axis=1)
    # Assert: the flights are the same until the first missing frame would have arrived
    # (capture at t0 + latency, taken at the next tick)
    differs = np.flatnonzero(np.any(base["est_pos_w_m"] != drop["est_pos_w_m"], axis=1))
    latency_s, tick_s = preset.mocap_latency_s, 1.0 / 500.0
    first = t[differs[0]]
    assert t0_s <= first <= t0_s + latency_s + 1.0 / preset.mocap_rate_hz + tick_s
    # dead reckoning on the IMU over the window: the error grows, worst at its end
    window = (t >= t0_s) & (t < t0_s + dur_s)
    assert err_drop[window].max() > 3.0 * err_base[window].max()
    worst = t[window][int(np.argmax(err_drop[window]))]
    assert worst > t0_s + dur_s - 0.05
    # and the first frames after the window bring it back to the undisturbed level
    after = (t >= t0_s + dur_s + 0.15) & (t < t0_s + dur_s + 2.0)
    assert err_drop[after].max() < 1.5 * err_base[after].max()


def test_that_simulate_flies_a_named_scenario_and_refuses_a_wrong_one_at_its_line(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # Fixture: a scenario whose gust starts after the mission (Exp. 1: 87 s)
    late = tmp_path / "late.yaml"
    late.write_text("schema: fasthex.scenario\nversion: 1\nname: late\ndisturbances:\n"
                    "  - {kind: gust, force_n: [1, 0, 0], start_s: 90.0, duration_s: 1.0}\n")
    # Test
    code = main(["simulate", "exp1-hover-tilt-steps", "--preset", "ideal", "--duration", "2",
                 "--scenario", "payload-gust", "--json"])
    out = json.loads(capsys.readouterr().out)
    bad = main(["simulate", "exp1-hover-tilt-steps", "--scenario", str(late), "--json"])
    err = capsys.readouterr().err
    # Assert
    assert code == 0 and out["scenario"] == "payload-gust"
    assert bad == 2
    assert f"{late}:5: disturbances[0].start_s: 90..91 s is not within the mission" in err

"""The scenario layer's pieces: the file and its validation, the disturbance profiles, the fault
text, and what the simulator does with a plant and a schedule (no closed loop here; flights
are in tests/integration/test_simulate_scenario.py)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from config.schema import ConfigError
from controller.missions import Mission
from groundstation.configs import load_disturbances, load_mission, load_scenario, load_vehicle
from sim_backend.faults import ScheduledFault
from sim_backend.scenario import (
    DisturbanceEvent,
    PlantOverrides,
    Scenario,
    plant_params,
)
from sim_backend.simulator import FastHexSimulator

PARAMS = load_vehicle("fasthex")
IDEAL = load_disturbances("ideal")

HEADER = "schema: fasthex.scenario\nversion: 1\nname: t\n"


def write(tmp_path: Path, body: str) -> Path:
    path = tmp_path / "scenario.yaml"
    path.write_text(HEADER + body)
    return path


def test_that_the_shipped_scenario_validates_against_the_vehicle_and_mission() -> None:
    mission = Mission(load_mission("exp1-hover-tilt-steps"))
    sc = load_scenario("payload-gust", vehicle=PARAMS, mission_duration_s=mission.duration_s)
    assert sc.plant.payload_kg == 0.3 and sc.disturbances[0].kind == "gust"
    assert [f.kind for f in sc.scheduled_faults()] == ["mocap-dropout"]


@pytest.mark.parametrize(("body", "line", "message"), [
    ("plant:\n  mass_kg: 0.0\n", 5, "plant.mass_kg: expected a number >= 0.1 and <= 100, "
     "got 0.0"),
    ("plant:\n  inertia_kg_m2: [0.1, 0.1, -0.2]\n", 5,
     "plant.inertia_kg_m2: expected positive moments of inertia"),
    ("plant:\n  inertia_kg_m2: [0.1, 0.0, 0.0, 0.0, 0.1, 0.2, 0.0, 0.2, 0.1]\n", 5,
     "plant.inertia_kg_m2: expected a positive definite matrix"),
    ("plant:\n  inertia_kg_m2: [0.1, 0.0, 0.0, 0.0, 0.1, 0.01, 0.0, 0.0, 0.1]\n", 5,
     "plant.inertia_kg_m2: expected a symmetric matrix"),
    ("plant:\n  inertia_kg_m2: [0.01, 0.01, 0.1]\n", 5,
     "plant.inertia_kg_m2: principal moments violate the triangle inequality"),
    ("plant:\n  thrust_coeff_scale: [1, 1, 2.0, 1, 1, 1]\n", 5,
     "plant.thrust_coeff_scale[2]: expected a number >= 0.5 and <= 1.5, got 2.0"),
    ("plant:\n  rotor_time_constant_s: 0.0001\n", 5,
     "plant.rotor_time_constant_s: expected 0 (no lag) or >= 0.001 s"),
    ("disturbances:\n  - kind: gust\n    force_n: [1, 0, 0]\n    start_s: 1.0\n", 5,
     "disturbances[0].duration_s: a gust needs a positive duration_s"),
    ("disturbances:\n  - kind: pulse\n    frame: wind\n    force_n: [1, 0, 0]\n", 6,
     "disturbances[0].frame: expected one of 'world', 'body'"),
    ("faults: [fc-disconnect@3]\n", 4, "faults[0]: fc-disconnect only exists on the emulated "
     "byte path"),
    ("faults: [rotor-thrust@3:0.5:7]\n", 4, "faults[0]: fault 'rotor-thrust@3:0.5:7': ROTOR "
     "is one of 1..6"),
])
def test_that_a_wrong_scenario_is_refused_at_its_line(tmp_path: Path, body: str, line: int,
                                                      message: str) -> None:
    path = write(tmp_path, body)
    with pytest.raises(ConfigError) as exc:
        load_scenario(path)
    assert str(exc.value).startswith(f"{path}:{line}: {message}")


@pytest.mark.parametrize(("body", "line", "message"), [
    # 2 kg more: 5.1 kg needs 60 N with the 20 % margin, the rotors give 50.6 N at 35 deg
    ("plant:\n  payload_kg: 2.0\n", 5, "plant.payload_kg: the plant (5.1 kg) fails the "
     "vehicle's check of mass_kg"),
    ("plant:\n  com_offset_b_m: [0.2, 0.0, 0.0]\n", 5, "plant.com_offset_b_m: expected "
     "|offset| <= 0.1525 m"),
    ("disturbances:\n  - kind: step\n    force_n: [1, 0, 0]\n    start_s: 20.0\n", 7,
     "disturbances[0].start_s: 20..20 s is not within the mission (0..15 s)"),
    ("faults: [mocap-dropout@14.8:1.0]\n", 4, "faults[0]: 14.8..15.8 s is not within the "
     "mission"),
])
def test_that_a_scenario_is_checked_against_the_vehicle_and_the_mission(
        tmp_path: Path, body: str, line: int, message: str) -> None:
    path = write(tmp_path, body)
    with pytest.raises(ConfigError) as exc:
        load_scenario(path, vehicle=PARAMS, mission_duration_s=15.0)
    assert str(exc.value).startswith(f"{path}:{line}: {message}")


def test_that_the_profiles_step_ramp_pulse_and_gust_have_their_shapes() -> None:
    f = (1.0, 0.0, 0.0)
    step = DisturbanceEvent(kind="step", force_n=f, start_s=2.0)
    ramp = DisturbanceEvent(kind="ramp", force_n=f, start_s=2.0, duration_s=4.0)
    pulse = DisturbanceEvent(kind="pulse", force_n=f, start_s=2.0, duration_s=0.5)
    gust = DisturbanceEvent(kind="gust", force_n=f, start_s=2.0, duration_s=1.0)
    assert [step.factor(t) for t in (1.99, 2.0, 100.0)] == [0.0, 1.0, 1.0]
    assert [ramp.factor(t) for t in (1.0, 3.0, 4.0, 9.0)] == [0.0, 0.25, 0.5, 1.0]
    assert [pulse.factor(t) for t in (1.9, 2.2, 2.5)] == [0.0, 1.0, 0.0]
    assert gust.factor(2.5) == pytest.approx(1.0)
    assert gust.factor(2.25) == pytest.approx(0.5)
    assert gust.factor(2.0) == 0.0 and gust.factor(3.0) == 0.0


def test_that_the_fault_text_takes_a_rotor_and_a_latency_step() -> None:
    assert ScheduledFault.parse("rotor-thrust@4:0.7:3") == \
        ScheduledFault("rotor-thrust", 4.0, 0.7, 3)
    assert ScheduledFault.parse("rotor-thrust@4:0.5").rotor is None
    assert ScheduledFault.parse("mocap-latency@2:0.05").value == 0.05
    with pytest.raises(ValueError, match="only rotor-thrust takes a third field"):
        ScheduledFault.parse("mocap-dropout@2:0.5:1")
    with pytest.raises(ValueError, match="latency of at most"):
        ScheduledFault.parse("mocap-latency@2:0.9")


def test_that_the_plant_params_carry_mass_payload_and_inertia_and_nominal_is_the_vehicle(
        ) -> None:
    assert plant_params(PARAMS, PlantOverrides()) is PARAMS
    p = plant_params(PARAMS, PlantOverrides(mass_kg=3.0, payload_kg=0.25,
                                            inertia_kg_m2=(0.1, 0.1, 0.17)))
    assert p.mass_kg == 3.25 and p.inertia_diag_kg_m2 == (0.1, 0.1, 0.17)
    assert p.controller == PARAMS.controller


def _coast(sim: FastHexSimulator, seconds: float) -> None:
    """Lift off with the rotors at hover speed, then let it fly ``seconds``."""
    spin = math.sqrt(PARAMS.weight_n / 6.0 / PARAMS.rotors.thrust_coeff_n_per_hz2)
    sim.command_rotor_speeds_hz([spin * 1.01] * 6)
    sim.advance(0.1)
    sim.command_rotor_speeds_hz([spin] * 6)
    sim.advance(seconds)


def test_that_a_full_inertia_with_a_diagonal_matrix_flies_as_the_diagonal() -> None:
    a = FastHexSimulator(PARAMS, IDEAL, seed=1)
    j = PARAMS.inertia_diag_kg_m2
    b = FastHexSimulator(PARAMS, IDEAL, seed=1, plant=PlantOverrides(
        inertia_kg_m2=(j[0], 0.0, 0.0, 0.0, j[1], 0.0, 0.0, 0.0, j[2])))
    c = FastHexSimulator(PARAMS, IDEAL, seed=1, plant=PlantOverrides(
        inertia_kg_m2=(j[0], 0.01, 0.0, 0.01, j[1], 0.0, 0.0, 0.0, j[2])))
    for sim in (a, b, c):
        _coast(sim, 0.1)
        sim.kick_body_rate((0.5, 0.0, 0.0))
        sim.advance(0.2)
    assert a.state() == b.state()
    # a product of inertia couples roll into pitch: J w' = -w x J w with w along x
    assert abs(c.state().omega_b_rad_s[1]) > 1e-4 > abs(a.state().omega_b_rad_s[1])


def test_that_a_centre_of_mass_offset_is_reported_at_o_b_and_pitches_the_free_vehicle() -> None:
    start = (0.3, -0.2, 0.1)
    sim = FastHexSimulator(PARAMS, IDEAL, seed=1, start_pos_w_m=start,
                           plant=PlantOverrides(com_offset_b_m=(0.02, 0.0, -0.01)))
    # on the ground: O_B where it was put, the MoCap sees O_B
    np.testing.assert_allclose(sim.state().pos_w_m, start, atol=1e-12)
    np.testing.assert_allclose(sim.true_pose().pos_w_m, start, atol=1e-12)
    # in the air, equal thrusts about a centre of mass ahead of O_B: the nose (+x) drops,
    # i.e. a positive pitch rate about body y
    _coast(sim, 0.3)
    assert sim.state().omega_b_rad_s[1] > 0.05


def test_that_scheduled_forces_act_from_the_scenario_start_in_their_frames() -> None:
    def accel_after(event: DisturbanceEvent, started: bool) -> tuple[float, float, float]:
        sim = FastHexSimulator(PARAMS, IDEAL, seed=1, disturbances=(event,))
        _coast(sim, 0.05)
        if started:
            sim.start_scenario(sim.now_s() - 1.0)  # the event's 1 s is now
        v0 = sim.state().vel_w_m_s
        sim.advance(0.1)
        v1 = sim.state().vel_w_m_s
        return tuple((b - a) / 0.1 for a, b in zip(v0, v1, strict=True))  # type: ignore

    world = DisturbanceEvent(kind="step", force_n=(3.1, 0.0, 0.0), start_s=1.0)
    assert accel_after(world, started=False)[0] == pytest.approx(0.0, abs=1e-3)
    assert accel_after(world, started=True)[0] == pytest.approx(1.0, rel=0.02)  # F / m
    # body y is world y while level: the same force in the body frame pushes along y
    body = DisturbanceEvent(kind="step", frame="body", force_n=(0.0, 3.1, 0.0), start_s=1.0)
    assert accel_after(body, started=True)[1] == pytest.approx(1.0, rel=0.02)


def test_that_a_rotor_thrust_fault_weakens_only_its_rotor() -> None:
    sim = FastHexSimulator(PARAMS, IDEAL, seed=1)
    before = list(sim.c_f_actual)
    sim.scale_rotor_thrust(0.5, 2)
    assert sim.c_f_actual == [c * (0.5 if i == 1 else 1.0) for i, c in enumerate(before)]


def test_that_a_session_resolves_and_validates_its_scenario(
        tmp_path: Path) -> None:
    from flight_support import SESSION, SHORT_MISSION

    from groundstation.session_config import EmulatedBackend, load_session

    (tmp_path / "short-hover.yaml").write_text(SHORT_MISSION)
    text = SESSION.format(seed=1, faults="", corrupt=0.0, zmax=2.5, servo_action="hold")
    text = text.replace("  disturbances: paper-calibrated\n",
                        "  disturbances: paper-calibrated\n  scenario: nowhere.yaml\n")
    path = tmp_path / "session.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as exc:
        load_session(path)
    assert str(exc.value) == (f"{path}:11: backend.scenario: no such file 'nowhere.yaml' "
                              "(relative to the session file)")
    # a scenario that outlasts the mission (11 s) is refused at its own line
    write(tmp_path, "faults: [imu-gap@30:0.1]\n").rename(tmp_path / "late.yaml")
    path.write_text(text.replace("nowhere.yaml", "late.yaml"))
    with pytest.raises(ConfigError, match=r"late.yaml:4: faults\[0\]: 30..30.1 s is not "):
        load_session(path)
    # a good one is resolved to its file for the emulator
    write(tmp_path, "plant: {payload_kg: 0.1}\n").rename(tmp_path / "good.yaml")
    path.write_text(text.replace("nowhere.yaml", "good.yaml"))
    backend = load_session(path).backend
    assert isinstance(backend, EmulatedBackend)
    assert Path(backend.scenario) == tmp_path / "good.yaml"


def test_that_a_scenario_default_is_the_nominal_plant_and_nothing_scheduled() -> None:
    sc = Scenario(name="x")
    assert sc.plant.is_nominal and sc.disturbances == () and sc.scheduled_faults() == ()


def test_that_the_emulated_backend_builds_the_plant_and_anchors_the_schedule_on_request(
        tmp_path: Path) -> None:
    from sim_backend.backend import BackendOptions, EmulatedVehicleBackend

    # Fixture: a payload, a pulse at 2 s and three faults, in mission seconds
    sc = Scenario(name="b", plant=PlantOverrides(payload_kg=0.2),
                  disturbances=(DisturbanceEvent(kind="pulse", force_n=(1.0, 0.0, 0.0),
                                                 start_s=2.0, duration_s=0.5),),
                  faults=("rotor-thrust@1:0.5:2", "mocap-latency@1.5:0.05", "imu-gap@3:0.1"))
    backend = EmulatedVehicleBackend(BackendOptions(
        vehicle=PARAMS, preset=IDEAL, start_pos_w_m=(0.0, 0.0, 0.1), seed=5,
        link_dir=tmp_path, scenario=sc))
    try:
        sim = backend.sim
        assert sim.params.mass_kg == pytest.approx(PARAMS.mass_kg + 0.2)
        c_f = list(sim.c_f_actual)
        backend.vehicle.advance(0.5)
        # Test: nothing scheduled before the ground station's start, then from its time on
        assert backend.vehicle.scheduled == [] and sim.schedule.t0_s is None
        t0 = backend.start_scenario()
        assert t0 == pytest.approx(0.5) and backend.start_scenario() == t0  # once
        assert [round(t - t0, 6) for t, _ in backend.vehicle.scheduled] == [1.0, 1.5, 3.0]
        backend.vehicle.advance(1.6)
        # Assert: rotor 2 halved, the MoCap's latency stepped, an IMU gap at mission 3 s
        assert sim.c_f_actual == [c * (0.5 if i == 1 else 1.0) for i, c in enumerate(c_f)]
        assert backend.mocap.config.latency_s == 0.05
        wire = backend.flight_ctrl.imu_wire_fault
        assert wire is not None and wire(0, t0 + 3.05) and not wire(0, t0 + 2.9)
        assert sim.schedule.wrench(t0 + 2.2) is not None
        assert sim.schedule.wrench(t0 + 1.9) is None
    finally:
        backend.stop()


def test_that_in_process_faults_freeze_the_tilt_step_the_latency_and_lose_imu_samples(
        ) -> None:
    from sim_backend.scenario import InProcessFaults

    # Fixture: mission time 0 at simulated 1 s
    sim = FastHexSimulator(PARAMS, IDEAL, seed=1)
    sim.advance(1.0)
    faults = InProcessFaults(sim, [ScheduledFault.parse(f) for f in (
        "servo-silent@0.5", "mocap-latency@0.5:0.05", "imu-rate@1:0.5")], t0_s=1.0)
    # Test
    sim.command_tilt_rad(math.radians(10.0))
    for _ in range(250):  # 0.5 s in 2 ms ticks, as the closed loop runs them
        faults.run_due(sim.now_s())
        sim.advance(0.002)
    faults.run_due(sim.now_s())
    tilt_at_silence = sim.tilt_rad()
    sim.command_tilt_rad(math.radians(30.0))  # not heard
    sim.poll_mocap()
    sim.advance(0.5)
    frames = sim.poll_mocap()
    lost = [faults.imu_lost(1.0 + 0.002 * k) for k in range(1000)]
    # Assert: the servo went on to its last goal (5 deg at 10 deg/s in 0.5 s, then 10 deg)
    assert math.degrees(tilt_at_silence) == pytest.approx(5.0, abs=0.1)
    assert math.degrees(sim.tilt_rad()) == pytest.approx(10.0, abs=1e-6)
    # frames now arrive 50 ms after their capture
    assert frames and all(sim.now_s() - f.t_s >= 0.05 - 1e-9 for f in frames)
    assert min(sim.now_s() - f.t_s for f in frames) < 0.06
    # half of the IMU samples from mission time 1 s on, none before
    assert not any(lost[:500]) and sum(lost[500:]) == 250

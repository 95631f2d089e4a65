"""A fixed-tilt airframe is expressible (``min_tilt_deg == max_tilt_deg``, ``max_rate_deg_s: 0``)
and honoured: the planner holds the tilt whatever the mission asks, the simulator is built at it,
and a mission that writes down another alpha is refused instead of silently clamped."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from config import find_config
from config.schema import ConfigError
from controller.tilt_planner import TiltPlanner
from groundstation.cli import main
from groundstation.configs import load_mission, load_vehicle
from groundstation.record import read_record
from sim_backend.disturbances import DisturbancePreset
from sim_backend.simulator import FastHexSimulator

GOOD = find_config("vehicles", "fasthex").read_text()
FIXED_DEG = 20.0

HOVER = """\
schema: fasthex.mission
version: 1
name: fixed-hover
start_pos_w_m: [0.0, 0.0, 0.1]
segments:
  - kind: takeoff
    duration_s: 3.0
    height_m: 1.0
  - kind: hold
    duration_s: 3.0
  - kind: land
    duration_s: 4.0
  - kind: hold
    duration_s: 1.0
    measured: false
"""


def _fixed_vehicle(tmp_path: Path, tilt_deg: float = FIXED_DEG, rate: str = "0.0") -> Path:
    text = GOOD.replace("max_tilt_deg: 35.0           # |alpha| in [0, 35] deg",
                        f"max_tilt_deg: {tilt_deg}\n  min_tilt_deg: {tilt_deg}")
    text = text.replace("max_rate_deg_s: 10.0", f"max_rate_deg_s: {rate}")
    path = tmp_path / "fixed.yaml"
    path.write_text(text)
    return path


def test_that_a_fixed_tilt_vehicle_loads_and_the_planner_holds_its_tilt(tmp_path: Path) -> None:
    # Fixture
    params = load_vehicle(_fixed_vehicle(tmp_path))
    sut = TiltPlanner(params)
    # Test: references below and above the tilt, and auto with no and a huge demand
    out = [sut.step(0.0, 0.0), sut.step(1.0, math.radians(35.0)), sut.step(2.0, None, 0.0),
           sut.step(3.0, None, 1e3)]
    # Assert
    assert params.tilt.is_fixed and params.tilt.max_rate_deg_s == 0.0
    assert out == pytest.approx([math.radians(FIXED_DEG)] * 4, abs=1e-12)


def test_that_a_minimum_tilt_is_a_floor_for_the_planner(tmp_path: Path) -> None:
    # Fixture: 10..35 deg at 10 deg/s
    path = tmp_path / "floor.yaml"
    path.write_text(GOOD.replace("mechanical_limit_deg: 35.0",
                                 "mechanical_limit_deg: 35.0\n  min_tilt_deg: 10.0"))
    sut = TiltPlanner(load_vehicle(path))
    # Test: a zero reference from the start, then 30 deg for 1 s, then zero again for 3 s
    start = sut.step(0.0, 0.0)
    up = sut.step(1.0, math.radians(30.0))
    down = sut.step(4.0, 0.0)
    # Assert: starts at the floor, moves at 10 deg/s, comes back to the floor only
    assert math.degrees(start) == pytest.approx(10.0)
    assert math.degrees(up) == pytest.approx(20.0)
    assert math.degrees(down) == pytest.approx(10.0)


def test_that_the_simulator_builds_a_fixed_tilt_vehicle_at_its_tilt(tmp_path: Path) -> None:
    params = load_vehicle(_fixed_vehicle(tmp_path))
    preset = DisturbancePreset(name="t", cardan_chain=False)
    sim = FastHexSimulator(params, preset, seed=0)
    sim.command_tilt_rad(0.0)  # a zero-rate drive cannot move
    sim.advance(0.2)
    assert math.degrees(sim.tilt_rad()) == pytest.approx(FIXED_DEG, abs=1e-9)


def test_that_simulate_flies_a_fixed_tilt_vehicle_at_its_tilt(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # Fixture: a mission that writes down no alpha (the vehicle decides)
    vehicle = _fixed_vehicle(tmp_path)
    mission = tmp_path / "hover.yaml"
    mission.write_text(HOVER)
    log = tmp_path / "fixed.fhr"
    # Test
    code = main(["simulate", str(mission), "--vehicle", str(vehicle), "--preset", "ideal",
                 "--json", "--log", str(log)])
    summary = json.loads(capsys.readouterr().out)
    rows = read_record(log).rows
    # Assert: the tilt never left 20 deg (the record stores float32: 1e-3 deg), and the
    # vehicle tracks: the ideal preset is the controller's own model, so the error is the
    # 500 Hz discretisation's, far below 1 mm, and it lands softly
    assert code == 0
    alpha_deg = [math.degrees(float(a)) for a in rows["alpha_rad"]]
    assert min(alpha_deg) == pytest.approx(FIXED_DEG, abs=1e-3)
    assert max(alpha_deg) == pytest.approx(FIXED_DEG, abs=1e-3)
    assert summary["all_pos_err_max_mm"] < 1.0
    assert summary["max_touchdown_speed_m_s"] < 0.5


def test_that_an_alpha_outside_the_fixed_tilt_is_an_error_at_the_mission_line(
        tmp_path: Path) -> None:
    # Fixture
    params = load_vehicle(_fixed_vehicle(tmp_path))
    mission = tmp_path / "m.yaml"
    mission.write_text(HOVER.replace("    height_m: 1.0\n",
                                     "    height_m: 1.0\n    alpha: {kind: constant, "
                                     "value_deg: 30.0}\n"))
    # Test
    with pytest.raises(ConfigError) as info:
        load_mission(mission, vehicle=params)
    # Assert
    assert str(info.value) == (f"{mission}:9: segments[0].alpha.value_deg: 30 deg is outside "
                               "vehicle 'fasthex''s tilt (a fixed tilt of 20 deg)")


@pytest.mark.parametrize(("rate", "tilt", "message"), [
    ("10.0", FIXED_DEG, "tilt.max_rate_deg_s: a fixed tilt (min_tilt_deg = max_tilt_deg = 20) "
     "does not move; expected 0, got 10"),
])
def test_that_a_fixed_tilt_with_a_rate_is_refused(tmp_path: Path, rate: str, tilt: float,
                                                 message: str) -> None:
    with pytest.raises(ConfigError) as info:
        load_vehicle(_fixed_vehicle(tmp_path, tilt, rate))
    assert str(info.value).endswith(message)


def test_that_a_zero_rate_on_a_tilt_range_is_refused_with_the_fix(tmp_path: Path) -> None:
    path = tmp_path / "v.yaml"
    path.write_text(GOOD.replace("max_rate_deg_s: 10.0", "max_rate_deg_s: 0"))
    with pytest.raises(ConfigError) as info:
        load_vehicle(path)
    assert str(info.value).endswith(
        "tilt.max_rate_deg_s: expected >= 0.5 deg/s for a tilt range of 0 to 35 deg, got 0 "
        "(a fixed tilt: set min_tilt_deg equal to max_tilt_deg)")

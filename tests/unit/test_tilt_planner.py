"""The tilt planner: limits, rate limit and the auto mode."""

from __future__ import annotations

import itertools
import math

import pytest

from controller.tilt_planner import TiltPlanner
from groundstation.configs import load_vehicle

PARAMS = load_vehicle("fasthex")


def test_that_the_command_moves_at_the_rate_limit_and_stays_within_the_range() -> None:
    # Fixture
    sut = TiltPlanner(PARAMS)
    # Test: ask for 50 deg (beyond 35) for 5 s at 500 Hz
    cmds = [sut.step(k * 0.002, math.radians(50.0)) for k in range(2501)]
    # Assert
    rates = [(b - a) / 0.002 for a, b in itertools.pairwise(cmds)]
    assert max(rates) <= math.radians(10.0) + 1e-9
    assert cmds[500] == pytest.approx(math.radians(10.0), abs=1e-9)
    assert cmds[-1] == pytest.approx(math.radians(35.0))
    assert sut.step(6.0, -1.0) < cmds[-1]  # heads down towards 0, never below
    assert sut.step(100.0, -1.0) == 0.0


def test_that_auto_picks_the_smallest_tilt_covering_the_demand() -> None:
    # Fixture
    sut = TiltPlanner(PARAMS)
    r20 = sut.capability.radius_n(math.radians(20.0))
    # Test / Assert
    assert sut.alpha_for_lateral_force(0.0) == 0.0
    assert math.degrees(sut.alpha_for_lateral_force(r20)) == pytest.approx(20.0, abs=0.06)
    assert sut.alpha_for_lateral_force(1e3) == pytest.approx(math.radians(35.0))
    below = sut.alpha_for_lateral_force(r20 - 0.01)
    assert sut.capability.radius_n(below) >= r20 - 0.01 > sut.capability.radius_n(below - 1e-3)


def test_that_auto_holds_its_target_between_demand_updates() -> None:
    # Fixture
    sut = TiltPlanner(PARAMS)
    # Test: demand 4 N + 0.5 N margin once, then no new demand for 4 s
    sut.step(0.0, None, 4.0, 0.5)
    for k in range(1, 2001):
        alpha = sut.step(k * 0.002, None)
    # Assert
    assert alpha == pytest.approx(sut.alpha_for_lateral_force(4.5))
    assert sut.capability.radius_n(alpha) >= 4.5

"""The Tikhonov wrench mapper and its per-alpha cache."""

from __future__ import annotations

import math

import numpy as np
import pytest

from controller.model import VehicleModel
from controller.wrench import WrenchMapper, tikhonov_gamma
from groundstation.configs import load_vehicle

MODEL = VehicleModel(load_vehicle("fasthex"))


def test_that_gamma_follows_the_hyperbola_of_paper_notes_item_10() -> None:
    assert tikhonov_gamma(0.0, 4e-6, 0.02) == pytest.approx(2e-4)
    assert tikhonov_gamma(math.radians(30.0), 4e-6, 0.02) == pytest.approx(7.35e-6, rel=1e-2)


def test_that_at_full_tilt_the_map_reproduces_any_wrench() -> None:
    # Fixture
    sut = WrenchMapper(MODEL)
    alpha = math.radians(30.0)
    wrench = (2.0, -1.5, 31.0, 0.3, -0.2, 0.1)
    # Test
    u = sut.thrusts_n(alpha, wrench[:3], wrench[3:])
    # Assert: F u = w within the regularisation bias (< 1 %)
    assert MODEL.allocation(alpha) @ np.array(u) == pytest.approx(wrench, rel=1e-2, abs=1e-3)


def test_that_at_zero_tilt_yaw_keeps_most_of_its_authority() -> None:
    # Fixture
    sut = WrenchMapper(MODEL)
    # Test
    u = sut.thrusts_n(0.0, (0.0, 0.0, 30.0), (0.0, 0.0, 0.1))
    # Assert: ~92 % of the yaw torque, the lift intact, no lateral force
    wrench = MODEL.allocation(0.0) @ np.array(u)
    assert wrench[5] / 0.1 == pytest.approx(0.92, abs=0.03)
    assert wrench[2] == pytest.approx(30.0, rel=1e-3)
    assert wrench[:2] == pytest.approx([0.0, 0.0], abs=1e-9)


def test_that_the_map_is_computed_once_per_alpha() -> None:
    # Fixture
    sut = WrenchMapper(MODEL)
    # Test
    for _ in range(100):
        sut.thrusts_n(0.3, (0.0, 0.0, 30.0), (0.0, 0.0, 0.0))
    first = sut.recomputations
    sut.thrusts_n(0.3 + 5e-5, (0.0, 0.0, 30.0), (0.0, 0.0, 0.0))
    within = sut.recomputations
    sut.thrusts_n(0.31, (0.0, 0.0, 30.0), (0.0, 0.0, 0.0))
    # Assert
    assert first == 1
    assert within == 1
    assert sut.recomputations == 2
    assert sut.matrix(0.31) == pytest.approx(
        np.linalg.solve(MODEL.allocation(0.31).T @ MODEL.allocation(0.31)
                        + tikhonov_gamma(0.31, 4e-6, 0.02) * np.eye(6),
                        MODEL.allocation(0.31).T))

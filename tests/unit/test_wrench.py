"""The Tikhonov wrench mapper and its per-alpha cache."""

from __future__ import annotations

import math

import numpy as np
import pytest

from controller import compiled
from controller.model import VehicleModel
from controller.wrench import WrenchMapper, tikhonov_gamma, tikhonov_map
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


@pytest.mark.parametrize("vehicle", ["fasthex", "fasthex-mini"])
def test_that_the_compiled_map_equals_the_numpy_one_up_to_rounding(vehicle: str) -> None:
    # Fixture
    if not compiled.AVAILABLE:
        pytest.skip("numba not installed: the numpy map is all there is")
    model = VehicleModel(load_vehicle(vehicle))
    mapper = WrenchMapper(model)
    work, out = np.empty((6, 6)), np.empty((6, 6))
    for alpha in np.linspace(-0.1, math.radians(40.0), 50):
        gamma = tikhonov_gamma(alpha, mapper.k1, mapper.k2_rad)
        # Test
        compiled.wrench_map(alpha, gamma, *mapper._geometry, work, out)
        # Assert: the same allocation; the solve rounds otherwise (cond ~ 1e4 near alpha = 0)
        np.testing.assert_array_equal(work, model.allocation(alpha))
        want = tikhonov_map(model.allocation(alpha), gamma)
        np.testing.assert_allclose(out, want, rtol=0.0, atol=1e-10 * np.abs(want).max())


def test_that_the_jitted_map_equals_its_python_source() -> None:
    # Fixture: the plain-Python function is what runs where numba is absent
    if not compiled.AVAILABLE:
        pytest.skip("numba not installed: the Python source is all there is")
    mapper = WrenchMapper(MODEL)
    outs = []
    for fn in (compiled.wrench_map, compiled.wrench_map.py_func):  # type: ignore[attr-defined]
        work, out = np.empty((6, 6)), np.empty((6, 6))
        # Test
        fn(0.3, 1e-5, *mapper._geometry, work, out)
        outs.append(out)
    # Assert
    np.testing.assert_allclose(outs[0], outs[1], rtol=0.0, atol=1e-12)


def test_that_a_warm_up_builds_the_map_the_first_tick_uses() -> None:
    # Fixture
    sut = WrenchMapper(MODEL)
    alpha = math.radians(12.0)
    # Test
    sut.warm_up(alpha)
    sut.thrusts_n(alpha, (0.0, 0.0, 30.0), (0.0, 0.0, 0.0))
    # Assert: computed once, before the tick
    assert sut.recomputations == 1

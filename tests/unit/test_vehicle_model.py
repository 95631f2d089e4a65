"""The vehicle model against the paper's numbers (Table I, Sec. II-III, paper-notes 1-4) and
against first-principles physics."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from controller.model import LateralBound, VehicleModel, cardan_tilts_rad
from controller.params import VehicleParams
from groundstation.configs import load_vehicle

DEG = math.pi / 180.0


def test_that_the_allocation_has_rank_4_at_zero_tilt_and_6_above(fasthex_model: VehicleModel
                                                                  ) -> None:
    assert fasthex_model.rank(0.0) == 4
    for tilt_deg in (0.5, 1.0, 5.0, 10.0, 20.0, 30.0, 35.0):
        assert fasthex_model.rank(tilt_deg * DEG) == 6, tilt_deg


def test_that_f1_at_zero_tilt_is_the_collinear_hexarotor(fasthex_model: VehicleModel) -> None:
    f1, _ = fasthex_model.allocation_parts(0.0)
    np.testing.assert_allclose(f1, np.vstack([np.zeros(6), np.zeros(6), np.ones(6)]), atol=1e-15)


def test_that_yaw_controllability_is_lost_at_minus_3_56_deg(fasthex_model: VehicleModel) -> None:
    # tan(alpha) = -c_tau / l: thrust and drag yaw moments cancel (paper Sec. III-B).
    expected_deg = -math.degrees(math.atan(0.019 / 0.305))
    assert expected_deg == pytest.approx(-3.56, abs=0.01)
    sv = fasthex_model.singular_values(-3.56 * DEG)
    assert sv[-1] < 1e-4 * sv[0]
    assert fasthex_model.rank(-3.56 * DEG) == 5
    assert fasthex_model.singular_values(expected_deg * DEG)[-1] < 1e-9
    # and not elsewhere on the negative side nearby
    assert fasthex_model.rank(-2.0 * DEG) == 6
    assert fasthex_model.rank(-5.0 * DEG) == 6


def test_that_a_clockwise_propeller_1_moves_the_yaw_rank_loss_to_plus_3_56_deg(
        fasthex_params: VehicleParams) -> None:
    # Fixture: the mirrored spins (valid only with tilts below 3.56 deg; the model evaluates
    # any tilt): mirroring the spins mirrors the tilt, so the loss moves to +atan(c_tau / l)
    mirrored = dataclasses.replace(
        fasthex_params, rotors=dataclasses.replace(fasthex_params.rotors, first_rotor_ccw=False),
        tilt=dataclasses.replace(fasthex_params.tilt, max_tilt_deg=3.0))
    sut = VehicleModel(mirrored)
    cancel = math.atan(0.019 / 0.305)
    # Test / Assert: the yaw row vanishes there, and its sign flips across it
    assert sut.singular_values(cancel)[-1] < 1e-9
    assert sut.rank(-cancel) == 6
    _, f2_below = sut.allocation_parts(0.5 * cancel)
    _, f2_above = sut.allocation_parts(10.0 * DEG)
    _, f2_stock = VehicleModel(fasthex_params).allocation_parts(10.0 * DEG)
    assert np.all(np.sign(f2_below[2]) == -np.sign(f2_above[2]))
    # above it the tilted thrust's yaw opposes the drag torque: l sin a - c_tau cos a per newton
    # instead of l sin a + c_tau cos a
    a = 10.0 * DEG
    np.testing.assert_allclose(np.abs(f2_above[2]), 0.305 * math.sin(a) - 0.019 * math.cos(a),
                               rtol=1e-12)
    np.testing.assert_allclose(np.abs(f2_stock[2]), 0.305 * math.sin(a) + 0.019 * math.cos(a),
                               rtol=1e-12)


@pytest.mark.parametrize("tilt_deg", [0.0, 5.0, 12.5, 20.0, 30.0, 35.0])
def test_that_hover_efficiency_is_cos_alpha(fasthex_model: VehicleModel, tilt_deg: float) -> None:
    a = tilt_deg * DEG
    u = fasthex_model.hover_thrusts(a)
    assert fasthex_model.force_efficiency(a, u) == pytest.approx(math.cos(a), abs=1e-9)
    assert fasthex_model.force_efficiency(a, np.full(6, 4.2)) == pytest.approx(math.cos(a))


def test_that_efficiency_is_0_82_at_35_deg(fasthex_model: VehicleModel) -> None:
    a = 35.0 * DEG
    assert fasthex_model.force_efficiency(a, fasthex_model.hover_thrusts(a)) == \
        pytest.approx(0.82, abs=0.005)


def test_that_the_spin_limits_give_10_3_n_per_rotor_and_61_8_n_lift(fasthex_model: VehicleModel
                                                                    ) -> None:
    assert fasthex_model.max_thrust_n == pytest.approx(10.3, abs=0.01)
    assert fasthex_model.max_lift_n(0.0) == pytest.approx(61.8, abs=0.01)
    # Tilting spends lift on internal forces: 61.8 cos(alpha).
    assert fasthex_model.max_lift_n(30.0 * DEG) == pytest.approx(61.8 * math.cos(30 * DEG),
                                                                 abs=0.02)


def test_that_thrust_and_spin_maps_are_inverse(fasthex_model: VehicleModel) -> None:
    spins = np.array([16.0, 40.0, 60.0, 80.0, 100.0, 102.0])
    np.testing.assert_allclose(fasthex_model.spin_from_thrust(
        fasthex_model.thrust_from_spin(spins)), spins)
    assert fasthex_model.spin_from_thrust(-1.0) == 0.0


def test_that_the_lateral_force_radii_match_the_checked_values(fasthex_model: VehicleModel
                                                               ) -> None:
    # paper-notes item 3 (16..102 Hz): 0 / 1.26 / 2.55 / 3.88 / 5.03 / 5.97 / 6.67 / 7.08 N
    expected = [0.0, 1.26, 2.55, 3.88, 5.03, 5.97, 6.67, 7.08]
    got = [fasthex_model.lateral_force_radius_n(a * DEG) for a in range(0, 40, 5)]
    np.testing.assert_allclose(got, expected, atol=0.006)
    # "several newtons at 30 deg (the paper quotes about 6 N)"
    assert 5.0 < got[6] < 8.0


def test_that_the_conservative_spin_limits_give_the_papers_6_n(fasthex_params: VehicleParams
                                                               ) -> None:
    from dataclasses import replace

    rotors = replace(fasthex_params.rotors, min_spin_hz=20.0, max_spin_hz=98.0)
    model = VehicleModel(replace(fasthex_params, rotors=rotors))
    assert model.lateral_force_radius_n(35.0 * DEG) == pytest.approx(5.71, abs=0.01)


def test_that_the_exact_polygon_agrees_with_a_support_function_lp(fasthex_model: VehicleModel
                                                                  ) -> None:
    for tilt_deg in (3.0, 17.0, 30.0):
        a = tilt_deg * DEG
        exact = fasthex_model.lateral_force_polygon(a)
        sampled = fasthex_model._lateral_force_polygon_lp(a, n_dirs=72)
        assert len(exact) == 6
        # every sampled support point is a vertex of the exact polygon
        for p in sampled:
            assert np.min(np.linalg.norm(exact - p, axis=1)) < 1e-6


def test_that_the_lateral_bound_fit_matches_the_checked_quadratic(fasthex_model: VehicleModel
                                                                  ) -> None:
    coeffs, residual = fasthex_model.fit_lateral_bound(np.arange(0.0, 35.01, 0.5))
    assert coeffs[0] == pytest.approx(-0.218, abs=2e-3)
    assert coeffs[1] == pytest.approx(0.320, abs=2e-3)
    assert coeffs[2] == pytest.approx(-0.00306, abs=2e-5)
    assert residual == pytest.approx(0.22, abs=0.01)


def test_that_the_lateral_bound_has_a_dead_zone_and_scale(fasthex_model: VehicleModel) -> None:
    bound = LateralBound.for_model(fasthex_model)
    assert bound.radius_n(0.0) == 0.0
    assert bound.radius_n(1.9 * DEG) == 0.0
    c0, c1, c2 = bound.coeffs_n
    assert bound.radius_n(30 * DEG) == pytest.approx(0.8 * (c0 + 30 * c1 + 900 * c2))
    assert bound.radius_n(30 * DEG) < fasthex_model.lateral_force_radius_n(30 * DEG)


def test_that_the_cardan_chain_errors_match_the_paper() -> None:
    tilts = np.radians(np.linspace(0.0, 35.0, 3501))
    actual = cardan_tilts_rad(tilts, 0.05, 30.0 * DEG)
    # signs alternate like the propellers' tilt directions
    assert np.all(actual[1:, 0::2] > 0) and np.all(actual[1:, 1::2] < 0)
    peak = np.degrees(np.max(np.abs(np.abs(actual) - tilts[:, None]), axis=0))
    # paper: "approximately 1 deg" for 3 and 4; paper-notes: 1.01 / 0.61 / 0.21 deg
    np.testing.assert_allclose(peak, [0.21, 0.61, 1.01, 1.01, 0.61, 0.21], atol=0.005)
    assert np.argmin(peak) in (0, 5)


def test_that_the_cardan_chain_is_exact_without_bending() -> None:
    tilts = np.radians(np.linspace(0.0, 35.0, 101))
    actual = cardan_tilts_rad(tilts, 0.05, 0.0)
    np.testing.assert_allclose(np.abs(actual), np.repeat(tilts[:, None], 6, axis=1), atol=1e-12)


def _first_principles_wrench(params: VehicleParams, tilt_rad: float, thrusts_n: np.ndarray
                             ) -> np.ndarray:
    """Sum each propeller's force and torque, built independently of controller.model."""
    force = np.zeros(3)
    torque = np.zeros(3)
    l_m, c_tau = params.geometry.arm_length_m, params.rotors.drag_coeff_m
    for i in range(6):  # paper index i + 1
        tilt_i = (-1) ** i * tilt_rad
        r_pi = Rotation.from_rotvec([0, 0, i * math.pi / 3]).as_matrix() @ \
            Rotation.from_rotvec([tilt_i, 0, 0]).as_matrix()
        axis = r_pi @ np.array([0.0, 0.0, 1.0])
        f_vec = thrusts_n[i] * axis
        pos = l_m * np.array([math.cos(i * math.pi / 3), math.sin(i * math.pi / 3), 0.0])
        # propeller i+1 spins with (-1)^i w about its axis (1, 3, 5 counter-clockwise); the air
        # drags it back, and the motor reacts on the body against the spin direction.
        spin_dir = (-1) ** i
        drag_torque = -spin_dir * c_tau * thrusts_n[i] * axis
        force += f_vec
        torque += np.cross(pos, f_vec) + drag_torque
    return np.concatenate([force, torque])


@settings(max_examples=60, deadline=None)
@given(
    tilt_deg=st.floats(min_value=-35.0, max_value=35.0),
    thrusts=st.lists(st.floats(min_value=0.0, max_value=10.3), min_size=6, max_size=6),
)
def test_that_f_times_u_equals_the_summed_propeller_wrench(tilt_deg: float,
                                                           thrusts: list[float]) -> None:
    params = load_vehicle("fasthex")
    model = VehicleModel(params)
    u = np.array(thrusts)
    np.testing.assert_allclose(model.allocation(tilt_deg * DEG) @ u,
                               _first_principles_wrench(params, tilt_deg * DEG, u), atol=1e-12)


def test_that_the_second_airframe_differs_and_keeps_the_structure() -> None:
    mini = VehicleModel(load_vehicle("fasthex-mini"))
    assert mini.rank(0.0) == 4 and mini.rank(10 * DEG) == 6
    assert mini.max_thrust_n == pytest.approx(5.0e-4 * 120.0**2)
    assert mini.max_lift_n(0.0) == pytest.approx(6 * 5.0e-4 * 120.0**2, rel=1e-6)
    assert 0.0 < mini.lateral_force_radius_n(30 * DEG) < 7.0

"""Quaternion helpers against scipy's Rotation (an independent implementation)."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy.spatial.transform import Rotation

from estimator.quaternion import (
    angle_between,
    quat_exp,
    quat_from_euler_zyx,
    quat_log,
    quat_mul,
    quat_normalize,
    quat_to_rot,
    rot_to_quat,
)

finite = st.floats(-10.0, 10.0, allow_nan=False)
quats = arrays(np.float64, 4, elements=finite).filter(lambda q: np.linalg.norm(q) > 1e-3)
rotvecs = arrays(np.float64, 3, elements=st.floats(-3.0, 3.0, allow_nan=False)).filter(
    lambda v: np.linalg.norm(v) < 3.1)


def scipy_rot(q: np.ndarray) -> Rotation:
    return Rotation.from_quat(np.asarray(q)[..., [1, 2, 3, 0]])


@settings(max_examples=200, deadline=None)
@given(quats, quats)
def test_that_the_hamilton_product_composes_rotations_like_scipy(a: np.ndarray,
                                                                 b: np.ndarray) -> None:
    # Fixture
    a, b = quat_normalize(a), quat_normalize(b)
    # Test
    ours = quat_to_rot(quat_mul(a, b))
    # Assert
    np.testing.assert_allclose(ours, (scipy_rot(a) * scipy_rot(b)).as_matrix(), atol=1e-12)


@settings(max_examples=200, deadline=None)
@given(rotvecs)
def test_that_log_inverts_exp_and_exp_matches_scipy(v: np.ndarray) -> None:
    q = quat_exp(v)
    np.testing.assert_allclose(quat_to_rot(q), Rotation.from_rotvec(v).as_matrix(), atol=1e-12)
    np.testing.assert_allclose(quat_log(q), v, atol=1e-12)


def test_that_exp_and_log_are_exact_at_and_near_zero_angle() -> None:
    for scale in (0.0, 1e-150, 1e-12, 1e-6):
        v = np.array([1.0, -2.0, 0.5]) * scale
        np.testing.assert_allclose(quat_log(quat_exp(v)), v, rtol=1e-14, atol=0)
    np.testing.assert_array_equal(quat_exp(np.zeros(3)), [1.0, 0.0, 0.0, 0.0])


def test_that_log_picks_the_short_way_for_a_negated_quaternion() -> None:
    v = np.array([0.3, -0.2, 0.1])
    np.testing.assert_allclose(quat_log(-quat_exp(v)), v, atol=1e-15)


def test_that_batched_calls_match_single_calls() -> None:
    rng = np.random.default_rng(0)
    qs = quat_normalize(rng.normal(size=(31, 4)))
    ps = quat_normalize(rng.normal(size=(31, 4)))
    batched = quat_mul(qs, ps)
    for k in range(31):
        np.testing.assert_allclose(batched[k], quat_mul(qs[k], ps[k]), atol=1e-15)


def test_that_euler_and_matrix_conversions_agree_with_scipy() -> None:
    q = quat_from_euler_zyx(0.1, -0.2, 2.5)
    expected = Rotation.from_euler("ZYX", [2.5, -0.2, 0.1])
    np.testing.assert_allclose(quat_to_rot(q), expected.as_matrix(), atol=1e-14)
    np.testing.assert_allclose(rot_to_quat(expected.as_matrix()), quat_normalize(q), atol=1e-14)
    assert abs(float(angle_between(q, quat_mul(q, quat_exp(np.array([0, 0, 0.01]))))) - 0.01) \
        < 1e-14

"""World z-up / body FLU <-> MAVLink NED / FRD conversions."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from drivers.mavlink.frames import (
    flu_to_frd,
    q_from_euler,
    q_to_euler,
    q_world_to_ned,
    rotate_inverse,
    world_to_ned,
)

angle = st.floats(-math.pi, math.pi, allow_nan=False)
comp = st.floats(-10.0, 10.0, allow_nan=False)


def _axis_angle(axis: tuple[float, float, float], a: float) -> tuple[float, float, float, float]:
    s = math.sin(a / 2)
    return (math.cos(a / 2), axis[0] * s, axis[1] * s, axis[2] * s)


def _rot(q: tuple[float, float, float, float]) -> np.ndarray:
    w, x, y, z = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def test_that_a_point_above_the_origin_has_a_negative_ned_down_coordinate() -> None:
    assert world_to_ned((1.0, 2.0, 1.5)) == (1.0, -2.0, -1.5)


def test_that_rolling_left_side_up_is_positive_roll_and_nose_down_is_negative_pitch() -> None:
    a = 0.2
    # roll about world x (forward): the left side goes up = the right side goes down (+roll)
    assert np.allclose(q_to_euler(q_world_to_ned(_axis_angle((1, 0, 0), a))), (a, 0, 0))
    # rotation about y-left by +a tilts the nose down: FRD pitch is nose up, so -a
    assert np.allclose(q_to_euler(q_world_to_ned(_axis_angle((0, 1, 0), a))), (0, -a, 0))
    # counter-clockwise seen from above is +yaw about z up, -yaw about NED down
    assert np.allclose(q_to_euler(q_world_to_ned(_axis_angle((0, 0, 1), a))), (0, 0, -a))


@given(angle, st.floats(-1.5, 1.5), angle, comp, comp, comp)
def test_that_the_ned_attitude_rotates_frd_vectors_as_the_world_attitude_rotates_flu_ones(
        roll: float, pitch: float, yaw: float, vx: float, vy: float, vz: float) -> None:
    q_wb = q_from_euler(roll, pitch, yaw)
    v_b = (vx, vy, vz)
    v_w = _rot(q_wb) @ np.array(v_b)
    v_ned = _rot(q_world_to_ned(q_wb)) @ np.array(flu_to_frd(v_b))
    assert np.allclose(v_ned, world_to_ned(tuple(v_w)), atol=1e-9)
    assert np.allclose(q_world_to_ned(q_world_to_ned(q_wb)), q_wb)


@given(angle, st.floats(-1.5, 1.5), angle)
def test_that_euler_angles_survive_a_round_trip_through_the_quaternion(
        roll: float, pitch: float, yaw: float) -> None:
    r, p, y = q_to_euler(q_from_euler(roll, pitch, yaw))
    assert math.isclose(p, pitch, abs_tol=1e-6)
    if abs(pitch) < 1.4:  # away from gimbal lock roll and yaw are unique
        assert math.isclose(math.remainder(r - roll, 2 * math.pi), 0.0, abs_tol=1e-6)
        assert math.isclose(math.remainder(y - yaw, 2 * math.pi), 0.0, abs_tol=1e-6)


@given(angle, st.floats(-1.5, 1.5), angle, comp, comp, comp)
def test_that_rotate_inverse_is_the_transpose_rotation(
        roll: float, pitch: float, yaw: float, vx: float, vy: float, vz: float) -> None:
    q = q_from_euler(roll, pitch, yaw)
    assert np.allclose(rotate_inverse(q, (vx, vy, vz)), _rot(q).T @ np.array([vx, vy, vz]))

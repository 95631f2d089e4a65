"""MoCap axes/units -> ground-station world frame (z up, q_wb body -> world), hand-checked."""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from config.schema import ConfigError, ConfigValueError, load_config_text
from drivers.mocap.frames import (
    FrameConfig,
    FrameTransform,
    quat_angle_rad,
    quat_from_axis_angle,
    quat_rotate,
)

S = math.sqrt(0.5)
EPS = 1e-12


def _close(a: tuple[float, ...], b: tuple[float, ...], tol: float = 1e-9) -> bool:
    return all(abs(x - y) <= tol for x, y in zip(a, b, strict=True))


def _same_rotation(a: tuple[float, float, float, float], b: tuple[float, float, float, float]
                   ) -> bool:
    return quat_angle_rad(a, b) < 1e-7


def test_that_a_motive_y_up_position_maps_to_z_up_with_motive_z_to_minus_world_y() -> None:
    # Fixture: Motive Y-up, metres; a body 1.5 m above the floor, 2 m along Motive +z
    sut = FrameTransform(FrameConfig(up_axis="y"))
    # Test
    pos, q = sut.to_world((1.0, 1.5, 2.0), (0.0, 0.0, 0.0, 1.0))
    # Assert: (x, y, z)_Motive -> (x, -z, y)_world
    assert _close(pos, (1.0, -2.0, 1.5))
    assert _same_rotation(q, (1.0, 0.0, 0.0, 0.0))


def test_that_a_yaw_about_motive_up_becomes_a_yaw_about_world_z() -> None:
    sut = FrameTransform(FrameConfig(up_axis="y"))
    # 90 deg about Motive y, wire order (x, y, z, w)
    _, q = sut.to_world((0.0, 0.0, 0.0), (0.0, S, 0.0, S))
    assert _same_rotation(q, (S, 0.0, 0.0, S))
    # body x axis now points to world +y
    assert _close(quat_rotate(q, (1.0, 0.0, 0.0)), (0.0, 1.0, 0.0))


def test_that_a_rotation_about_motive_z_becomes_a_rotation_about_world_minus_y() -> None:
    sut = FrameTransform(FrameConfig(up_axis="y"))
    _, q = sut.to_world((0.0, 0.0, 0.0), (0.0, 0.0, S, S))  # 90 deg about Motive z
    assert _same_rotation(q, (S, 0.0, -S, 0.0))
    # Motive x rotated about Motive z goes to Motive y (up) -> world z
    assert _close(quat_rotate(q, (1.0, 0.0, 0.0)), (0.0, 0.0, 1.0))


def test_that_z_up_millimetres_are_scaled_and_the_quaternion_is_reordered_only() -> None:
    sut = FrameTransform(FrameConfig(up_axis="z", units="mm"))
    # 30 deg roll about x, wire (x, y, z, w)
    c, s = math.cos(math.radians(15.0)), math.sin(math.radians(15.0))
    pos, q = sut.to_world((1000.0, -500.0, 250.0), (s, 0.0, 0.0, c))
    assert _close(pos, (1.0, -0.5, 0.25))
    assert _close(q, (c, s, 0.0, 0.0))


def test_that_the_mocap_to_world_rotation_and_origin_are_applied_after_the_axis_change() -> None:
    # MoCap origin at world (10, 0, 0), MoCap x pointing to world +y (yaw 90 deg)
    sut = FrameTransform(FrameConfig(up_axis="z", world_from_mocap_q=(S, 0.0, 0.0, S),
                                     mocap_origin_w_m=(10.0, 0.0, 0.0)))
    pos, q = sut.to_world((1.0, 0.0, 0.5), (0.0, 0.0, 0.0, 1.0))
    assert _close(pos, (10.0, 1.0, 0.5))
    assert _same_rotation(q, (S, 0.0, 0.0, S))


def test_that_the_rigid_body_to_body_offset_moves_the_origin_in_the_rotated_frame() -> None:
    # Rigid body yawed 90 deg in world; the vehicle centre is 0.1 m along the rigid body's x,
    # and the vehicle's x axis is the rigid body's y axis (q_rb_b = yaw +90 deg).
    sut = FrameTransform(FrameConfig(up_axis="z", rb_to_body_q=(S, 0.0, 0.0, S),
                                     body_origin_rb_m=(0.1, 0.0, 0.0)))
    pos, q = sut.to_world((0.0, 0.0, 1.0), (0.0, 0.0, S, S))
    assert _close(pos, (0.0, 0.1, 1.0))
    assert _same_rotation(q, (0.0, 0.0, 0.0, 1.0))  # 180 deg yaw in total


def test_that_a_zero_quaternion_is_refused() -> None:
    with pytest.raises(ValueError):
        FrameTransform().to_world((0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 0.0))


def test_that_a_non_unit_configured_quaternion_is_a_config_error() -> None:
    with pytest.raises(ConfigValueError, match="world_from_mocap_q"):
        FrameConfig(world_from_mocap_q=(1.0, 1.0, 0.0, 0.0))


def test_that_a_frame_config_loads_from_yaml_and_bad_values_name_the_line() -> None:
    text = ("schema: mocap_frames\nversion: 1\nup_axis: z\nunits: mm\n"
            "world_from_mocap_q: [1.0, 0.0, 0.0, 0.0]\nmocap_origin_w_m: [0.0, 0.0, 0.1]\n"
            "rb_to_body_q: [1.0, 0.0, 0.0, 0.0]\nbody_origin_rb_m: [0.0, 0.0, -0.05]\n")
    cfg = load_config_text(text, FrameConfig, schema="mocap_frames")
    assert cfg.up_axis == "z" and cfg.scale_to_m == 0.001
    with pytest.raises(ConfigError, match="up_axis"):
        load_config_text(text.replace("up_axis: z", "up_axis: x"), FrameConfig,
                         schema="mocap_frames")


unit = st.floats(-1.0, 1.0)
coord = st.floats(-50.0, 50.0)


@given(p=st.tuples(coord, coord, coord), axis=st.tuples(unit, unit, unit),
       angle=st.floats(-math.pi, math.pi), up=st.sampled_from(["y", "z"]),
       units=st.sampled_from(["m", "mm"]))
def test_that_to_mocap_inverts_to_world(p: tuple[float, float, float],
                                        axis: tuple[float, float, float], angle: float,
                                        up: str, units: str) -> None:
    cfg = FrameConfig(up_axis=up, units=units,  # type: ignore[arg-type]
                      world_from_mocap_q=quat_from_axis_angle((0.0, 0.0, 1.0), 0.3),
                      mocap_origin_w_m=(1.0, 2.0, 0.0),
                      rb_to_body_q=quat_from_axis_angle((1.0, 0.0, 0.0), 0.2),
                      body_origin_rb_m=(0.0, 0.0, -0.05))
    sut = FrameTransform(cfg)
    q = quat_from_axis_angle(axis, angle)
    p_m, q_m = sut.to_mocap(p, q)
    p2, q2 = sut.to_world(p_m, q_m)
    assert _close(p2, p, 1e-8)
    assert quat_angle_rad(q2, q) < 1e-7


@given(p=st.tuples(coord, coord, coord), up=st.sampled_from(["y", "z"]),
       units=st.sampled_from(["m", "mm"]))
def test_that_a_marker_point_maps_as_a_body_at_it_with_no_origin_offset(
        p: tuple[float, float, float], up: str, units: str) -> None:
    """A marker is a point: the rigid body's origin offset and attitude do not move it. With no
    offset it is exactly the position to_mocap gives a body there (the emulated NatNet frames'
    bytes did not change when the markers moved to point_to_mocap)."""
    common = {"up_axis": up, "units": units,
              "world_from_mocap_q": quat_from_axis_angle((0.0, 0.0, 1.0), 0.3),
              "mocap_origin_w_m": (1.0, 2.0, 0.0)}
    plain = FrameTransform(FrameConfig(**common))  # type: ignore[arg-type]
    offset = FrameTransform(FrameConfig(**common,  # type: ignore[arg-type]
                                        rb_to_body_q=quat_from_axis_angle((1.0, 0.0, 0.0), 0.2),
                                        body_origin_rb_m=(0.0, 0.0, -0.05)))
    assert plain.point_to_mocap(p) == plain.to_mocap(p, (1.0, 0.0, 0.0, 0.0))[0]
    assert offset.point_to_mocap(p) == plain.point_to_mocap(p)
    # and back: a body at the marker with no offset lands on the point
    back, _ = plain.to_world(plain.point_to_mocap(p), (0.0, 0.0, 0.0, 1.0))
    assert _close(back, p, 1e-8)

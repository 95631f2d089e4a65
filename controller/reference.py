"""Controller-facing value types (state, reference) and small rotation helpers in plain floats.

The per-tick path (controller, mission, simulator) works on tuples of Python floats: for
3-vectors and 3x3 matrices that is several times faster than numpy, whose per-call overhead
(~1 us) dominates at this size.

Conventions (those of ``sim_backend.vehicle``): world frame z up, body frame x towards
propeller 1; ``q_wb`` is the body -> world Hamilton quaternion ``(w, x, y, z)``; a rotation
matrix is stored row-major as a 9-tuple ``(r11, r12, r13, r21, ..., r33)`` whose columns are the
body axes b1, b2, b3 expressed in the world frame.
"""

from __future__ import annotations

import math

from controller.compiled import jitable
from controller.values import tick_value

Vec3 = tuple[float, float, float]
Quat = tuple[float, float, float, float]
Mat3 = tuple[float, float, float, float, float, float, float, float, float]

IDENTITY_Q: Quat = (1.0, 0.0, 0.0, 0.0)
IDENTITY_R: Mat3 = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
ZERO3: Vec3 = (0.0, 0.0, 0.0)


@tick_value
class VehicleState:
    """The (estimated or true) state the controller acts on."""

    pos_w_m: Vec3
    vel_w_m_s: Vec3
    q_wb: Quat
    omega_b_rad_s: Vec3


@tick_value
class Reference:
    """The full-pose reference at one instant, from a mission.

    ``alpha_rad`` is the tilt reference, or ``None`` when the mission leaves it to the tilt
    planner's ``auto`` mode. ``segment`` indexes the mission segment; ``measured`` tells whether
    the tick belongs to the experiment proper (takeoff and landing are not measured).
    """

    t_s: float
    pos_w_m: Vec3
    vel_w_m_s: Vec3
    acc_w_m_s2: Vec3
    q_wr: Quat
    omega_r_rad_s: Vec3
    alpha_rad: float | None
    segment: int = 0
    measured: bool = True


@jitable
def quat_to_rot(q: Quat) -> Mat3:
    """Rotation matrix (row-major 9-tuple) of a unit quaternion ``(w, x, y, z)``."""
    w, x, y, z = q
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz = x * y, x * z, y * z
    wx, wy, wz = w * x, w * y, w * z
    return (1.0 - 2.0 * (yy + zz), 2.0 * (xy - wz), 2.0 * (xz + wy),
            2.0 * (xy + wz), 1.0 - 2.0 * (xx + zz), 2.0 * (yz - wx),
            2.0 * (xz - wy), 2.0 * (yz + wx), 1.0 - 2.0 * (xx + yy))


def rot_to_quat(r: Mat3) -> Quat:
    """Unit quaternion (w >= 0) of a rotation matrix (Shepperd's method, stable everywhere)."""
    r11, r12, r13, r21, r22, r23, r31, r32, r33 = r
    tr = r11 + r22 + r33
    if tr > 0.0:
        s = 2.0 * math.sqrt(tr + 1.0)
        q = (0.25 * s, (r32 - r23) / s, (r13 - r31) / s, (r21 - r12) / s)
    elif r11 > r22 and r11 > r33:
        s = 2.0 * math.sqrt(max(1.0 + r11 - r22 - r33, 1e-300))
        q = ((r32 - r23) / s, 0.25 * s, (r12 + r21) / s, (r13 + r31) / s)
    elif r22 > r33:
        s = 2.0 * math.sqrt(max(1.0 + r22 - r11 - r33, 1e-300))
        q = ((r13 - r31) / s, (r12 + r21) / s, 0.25 * s, (r23 + r32) / s)
    else:
        s = 2.0 * math.sqrt(max(1.0 + r33 - r11 - r22, 1e-300))
        q = ((r21 - r12) / s, (r13 + r31) / s, (r23 + r32) / s, 0.25 * s)
    n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    sign = 1.0 if q[0] >= 0.0 else -1.0
    return (sign * q[0] / n, sign * q[1] / n, sign * q[2] / n, sign * q[3] / n)


def quat_mul(a: Quat, b: Quat) -> Quat:
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return (aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw)


def quat_from_axis_angle(axis: Vec3, angle_rad: float) -> Quat:
    """Rotation by ``angle_rad`` about the unit vector ``axis``."""
    h = 0.5 * angle_rad
    s = math.sin(h)
    return (math.cos(h), axis[0] * s, axis[1] * s, axis[2] * s)


def quat_from_euler_zyx(roll_rad: float, pitch_rad: float, yaw_rad: float) -> Quat:
    """``Rz(yaw) Ry(pitch) Rx(roll)`` as a quaternion."""
    cr, sr = math.cos(0.5 * roll_rad), math.sin(0.5 * roll_rad)
    cp, sp = math.cos(0.5 * pitch_rad), math.sin(0.5 * pitch_rad)
    cy, sy = math.cos(0.5 * yaw_rad), math.sin(0.5 * yaw_rad)
    return (cr * cp * cy + sr * sp * sy,
            sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy)


def euler_zyx_from_rot(r: Mat3) -> Vec3:
    """(roll, pitch, yaw) in rad with ``R = Rz(yaw) Ry(pitch) Rx(roll)``."""
    pitch = -math.asin(max(-1.0, min(1.0, r[6])))
    return (math.atan2(r[7], r[8]), pitch, math.atan2(r[3], r[0]))


def rot_angle_between(a: Mat3, b: Mat3) -> float:
    """Geodesic angle of ``a^T b`` (rad)."""
    tr = sum(a[i] * b[i] for i in range(9))  # trace(a^T b) = sum of elementwise products
    return math.acos(max(-1.0, min(1.0, 0.5 * (tr - 1.0))))

"""Frame conversions between the ground station and MAVLink. Pure functions.

Ground station: world W z up, x forward, y left (FLU-style world); body B x towards propeller
1, y left, z up along the rotor axes at zero tilt (FLU); ``q_wb`` body -> world ``(w, x, y, z)``.

MAVLink: world LOCAL_NED (x north, y east, z down) and body FRD (x forward, y right, z down).
We take north = the world x axis, so both frames turn by 180 deg about x:

* vectors:       ``v_ned = (x, -y, -z)``, and the same for body vectors (``omega_frd``);
* attitude:      ``q_ned_frd = C q_wb C^-1`` with ``C`` = 180 deg about x, which is
  ``(w, x, -y, -z)``;
* Euler angles:  roll/pitch/yaw (ZYX) of ``q_ned_frd``, as MAVLink's ATTITUDE expects.

Each map is its own inverse, so the same functions convert MAVLink poses (MoCap input,
setpoints) back into the world frame.
"""

from __future__ import annotations

import math

Vec3 = tuple[float, float, float]
Quat = tuple[float, float, float, float]


def flu_to_frd(v: Vec3) -> Vec3:
    """A world (z-up) or body (FLU) vector in NED / FRD. Its own inverse."""
    return (v[0], -v[1], -v[2])


frd_to_flu = flu_to_frd
world_to_ned = flu_to_frd
ned_to_world = flu_to_frd


def q_world_to_ned(q_wb: Quat) -> Quat:
    """Attitude body(FLU)->world(z up) to body(FRD)->NED, ``(w, x, y, z)``. Its own inverse."""
    return (q_wb[0], q_wb[1], -q_wb[2], -q_wb[3])


q_ned_to_world = q_world_to_ned


def q_normalized(q: Quat) -> Quat:
    n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    if not n > 0.0 or not math.isfinite(n):
        raise ValueError(f"quaternion {q} cannot be normalised")
    return (q[0] / n, q[1] / n, q[2] / n, q[3] / n)


def q_to_euler(q: Quat) -> Vec3:
    """Roll, pitch, yaw (rad) of ``q`` with the aerospace ZYX convention."""
    w, x, y, z = q
    roll = math.atan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y))
    s = max(-1.0, min(1.0, 2.0 * (w * y - z * x)))
    pitch = math.asin(s)
    yaw = math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    return (roll, pitch, yaw)


def q_from_euler(roll: float, pitch: float, yaw: float) -> Quat:
    """The quaternion of ZYX Euler angles (rad), ``(w, x, y, z)``."""
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return (cr * cp * cy + sr * sp * sy, sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy)


def rotate_inverse(q: Quat, v: Vec3) -> Vec3:
    """``R(q)^T v``: a vector of the parent frame expressed in the child frame of ``q``."""
    w, x, y, z = q
    r00 = 1 - 2 * (y * y + z * z)
    r01 = 2 * (x * y - w * z)
    r02 = 2 * (x * z + w * y)
    r10 = 2 * (x * y + w * z)
    r11 = 1 - 2 * (x * x + z * z)
    r12 = 2 * (y * z - w * x)
    r20 = 2 * (x * z - w * y)
    r21 = 2 * (y * z + w * x)
    r22 = 1 - 2 * (x * x + y * y)
    return (r00 * v[0] + r10 * v[1] + r20 * v[2],
            r01 * v[0] + r11 * v[1] + r21 * v[2],
            r02 * v[0] + r12 * v[1] + r22 * v[2])

"""Unit quaternions and rotation vectors, vectorised over leading axes.

Conventions: Hamilton product, components ``(w, x, y, z)``; ``q_wb`` rotates body vectors into the
world frame (``v_w = R(q_wb) v_b``). Rotation vectors are axis * angle in radians. Every function
accepts arrays of shape ``(..., 4)`` or ``(..., 3)`` so that one call handles a single quaternion
or all sigma points of the UKF at once; the products are written as small matrix products
(``L(q) p``) because one ``matmul`` over a stack is far cheaper than sixteen element-wise ops.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]
Vec3Tuple = tuple[float, float, float]
QuatTuple = tuple[float, float, float, float]

IDENTITY: FloatArray = np.array([1.0, 0.0, 0.0, 0.0])


def _left_basis() -> FloatArray:
    """E with L(q) = sum_k q_k E[k]; L(q) p = q (x) p."""
    basis = np.zeros((4, 4, 4))
    for k in range(4):
        w, x, y, z = np.eye(4)[k]
        basis[k] = [[w, -x, -y, -z],
                    [x, w, -z, y],
                    [y, z, w, -x],
                    [z, -y, x, w]]
    return basis


def _rotation_quadratic_form() -> FloatArray:
    """C with R(q)_ij = sum_kl q_k q_l C[k, l, i, j] (homogeneous form, exact for unit q)."""

    def homogeneous(q: FloatArray) -> FloatArray:
        w, x, y, z = q
        return np.array([
            [w * w + x * x - y * y - z * z, 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), w * w - x * x + y * y - z * z, 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), w * w - x * x - y * y + z * z]])

    eye = np.eye(4)
    form = np.zeros((4, 4, 3, 3))
    for k in range(4):
        for m in range(4):
            if k == m:
                form[k, m] = homogeneous(eye[k])
            else:  # polarisation of the quadratic form, split evenly between (k, m) and (m, k)
                both = homogeneous(eye[k] + eye[m]) - homogeneous(eye[k]) - homogeneous(eye[m])
                form[k, m] = 0.5 * both
    return form


_LEFT_BASIS = _left_basis().reshape(4, 16)
_ROT_FORM = _rotation_quadratic_form().reshape(16, 9)
_CONJ = np.array([1.0, -1.0, -1.0, -1.0])


def left_matrix(q: FloatArray) -> FloatArray:
    """L(q), shape (..., 4, 4), such that ``L(q) @ p == q (x) p``."""
    return (q @ _LEFT_BASIS).reshape(*q.shape[:-1], 4, 4)


def quat_mul(a: FloatArray, b: FloatArray) -> FloatArray:
    """Hamilton product a (x) b, broadcast over leading axes."""
    return (left_matrix(a) @ b[..., None])[..., 0]


def quat_conj(q: FloatArray) -> FloatArray:
    """Conjugate (the inverse of a unit quaternion)."""
    return q * _CONJ


def quat_normalize(q: FloatArray) -> FloatArray:
    """q / |q|, with the scalar part made non-negative (q and -q are the same rotation)."""
    q = np.asarray(q, dtype=np.float64)
    sign = np.copysign(1.0, q[..., :1])
    return q * (sign / np.linalg.norm(q, axis=-1, keepdims=True))


def quat_exp(rotvec: FloatArray) -> FloatArray:
    """Exp: rotation vector (..., 3) -> unit quaternion (..., 4); exact at zero angle."""
    angle = np.sqrt(np.einsum("...i,...i->...", rotvec, rotvec))
    half = 0.5 * angle
    out = np.empty((*rotvec.shape[:-1], 4))
    out[..., 0] = np.cos(half)
    # sin(angle/2)/angle, and 0 * anything at angle 0 (where the vector part is 0 anyway)
    out[..., 1:] = rotvec * (np.sin(half) / np.where(angle > 0.0, angle, 1.0))[..., None]
    return out


def quat_log(q: FloatArray) -> FloatArray:
    """Log: unit quaternion (..., 4) -> rotation vector (..., 3) of angle <= pi."""
    w = q[..., 0]
    v = q[..., 1:]
    s = np.sqrt(np.einsum("...i,...i->...", v, v))
    factor = 2.0 * np.arctan2(s, np.abs(w)) / np.where(s > 0.0, s, 1.0) * np.copysign(1.0, w)
    return v * factor[..., None]


def quat_to_rot(q: FloatArray) -> FloatArray:
    """Rotation matrix (..., 3, 3) of a unit quaternion (..., 4)."""
    outer = q[..., :, None] * q[..., None, :]
    return (outer.reshape(*q.shape[:-1], 16) @ _ROT_FORM).reshape(*q.shape[:-1], 3, 3)


def quat_rotate(q: FloatArray, v: FloatArray) -> FloatArray:
    """R(q) v, broadcast over leading axes."""
    return (quat_to_rot(q) @ v[..., None])[..., 0]


def rot_to_quat(rot: FloatArray) -> FloatArray:
    """Unit quaternion (w >= 0) of a single rotation matrix (Shepperd's method)."""
    m = np.asarray(rot, dtype=np.float64)
    trace = m[0, 0] + m[1, 1] + m[2, 2]
    diag = (trace, m[0, 0], m[1, 1], m[2, 2])
    k = int(np.argmax(diag))
    if k == 0:
        s = 2.0 * np.sqrt(1.0 + trace)
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    elif k == 1:
        s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
    elif k == 2:
        s = 2.0 * np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
    return quat_normalize(np.array(q))


def quat_from_euler_zyx(roll_rad: FloatArray | float, pitch_rad: FloatArray | float,
                        yaw_rad: FloatArray | float) -> FloatArray:
    """q_wb of ZYX Euler angles (R = Rz(yaw) Ry(pitch) Rx(roll)), broadcast over inputs."""
    r, p, y = (0.5 * np.asarray(a, dtype=np.float64) for a in (roll_rad, pitch_rad, yaw_rad))
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    return np.stack([cr * cp * cy + sr * sp * sy,
                     sr * cp * cy - cr * sp * sy,
                     cr * sp * cy + sr * cp * sy,
                     cr * cp * sy - sr * sp * cy], axis=-1)


def angle_between(q_a: FloatArray, q_b: FloatArray) -> FloatArray:
    """Geodesic angle (rad) between two rotations, broadcast over leading axes."""
    rel = quat_mul(quat_conj(q_a), q_b)
    return np.sqrt(np.sum(quat_log(rel) ** 2, axis=-1))


# -- single quaternions in plain floats: a few numpy calls on 4 numbers cost more than the math --
def mul_tuple(a: Sequence[float], b: Sequence[float]) -> QuatTuple:
    """Hamilton product a (x) b of two quaternions given as plain floats."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return (aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw)


def conj_tuple(q: Sequence[float]) -> QuatTuple:
    return (q[0], -q[1], -q[2], -q[3])


def normalized_tuple(q: Sequence[float]) -> QuatTuple:
    w, x, y, z = q
    n = math.sqrt(w * w + x * x + y * y + z * z)
    return (w / n, x / n, y / n, z / n)


def mul_exp_tuple(q: Sequence[float], a: float, b: float, c: float) -> QuatTuple:
    """q (x) Exp((a, b, c)), normalised."""
    angle = math.sqrt(a * a + b * b + c * c)
    cw = math.cos(0.5 * angle)
    k = math.sin(0.5 * angle) / angle if angle > 1e-12 else 0.5
    return normalized_tuple(mul_tuple(q, (cw, a * k, b * k, c * k)))


def rotate_tuple(q: Sequence[float], v: Sequence[float]) -> Vec3Tuple:
    """R(q) v for one unit quaternion and one vector."""
    w, x, y, z = q
    a, b, c = v
    # t = 2 q_v x v;  v' = v + w t + q_v x t
    tx, ty, tz = 2.0 * (y * c - z * b), 2.0 * (z * a - x * c), 2.0 * (x * b - y * a)
    return (a + w * tx + (y * tz - z * ty), b + w * ty + (z * tx - x * tz),
            c + w * tz + (x * ty - y * tx))


def mul_exp_single(q: FloatArray, rotvec: FloatArray) -> FloatArray:
    """q (x) Exp(rotvec), normalised, for one quaternion."""
    return np.array(mul_exp_tuple(q.tolist(), *rotvec.tolist()))


def log_relative_single(q_a: FloatArray, q_b: FloatArray) -> FloatArray:
    """Log(q_a^-1 (x) q_b) for one pair: the rotation vector from a to b in a's frame."""
    w, x, y, z = q_a.tolist()
    bw, bx, by, bz = q_b.tolist()
    rw = w * bw + x * bx + y * by + z * bz
    rx = w * bx - x * bw - y * bz + z * by
    ry = w * by + x * bz - y * bw - z * bx
    rz = w * bz - x * by + y * bx - z * bw
    s = math.sqrt(rx * rx + ry * ry + rz * rz)
    if s == 0.0:
        return np.zeros(3)
    f = 2.0 * math.atan2(s, abs(rw)) / s * (1.0 if rw >= 0.0 else -1.0)
    return np.array([rx * f, ry * f, rz * f])


def rotate_single(q: FloatArray, v: FloatArray) -> FloatArray:
    """R(q) v for one unit quaternion and one vector."""
    return np.array(rotate_tuple(q.tolist(), v.tolist()))

"""MoCap frame -> ground-station world frame, and back (for emulated servers).

Conventions of the ground station (see ``sim_backend/vehicle.py``): world frame W is z-up and
right-handed; ``q_wb`` is the Hamilton quaternion ``(w, x, y, z)`` rotating body -> world.

What a MoCap system streams (``protocol-mocap-mavlink.md`` §1, §4):

- OptiTrack Motive, default "Up Axis: Y": right-handed, y up. We map MoCap axes to a z-up
  frame M' with the rotation C = +90 deg about x: ``(x, y, z)_M -> (x, -z, y)_M'``. A body
  1.5 m above the floor (Motive y = 1.5) is at z = 1.5 in M'.
- Vicon, Qualisys, Motive with "Up Axis: Z": already z-up, C = identity.
- Positions in metres (NatNet) or millimetres (Vicon/QTM through some exports): ``units``.
- Quaternions on the wire are ``(x, y, z, w)`` (NatNet and VRPN); here everything is
  ``(w, x, y, z)``.

The axis change is applied to both the world and the rigid-body frame
(``q' = q_C ⊗ q ⊗ q_C⁻¹``), which is right when the rigid body was created aligned with the
MoCap axes. Two configurable transforms follow:

- ``world_from_mocap_q`` / ``mocap_origin_w_m``: the rotation M' -> W and the position of the
  MoCap origin in W (which horizontal MoCap axis points where depends on the calibration square);
- ``rb_to_body_q`` / ``body_origin_rb_m``: the rotation body -> rigid body (q_rb_b) and the
  position of the body origin in the rigid-body frame, for a rigid body not defined at the
  vehicle's centre with the vehicle's axes.

Everything is plain-float arithmetic: one conversion costs a few microseconds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

from config.schema import ConfigValueError

Vec3 = tuple[float, float, float]
Quat = tuple[float, float, float, float]  # (w, x, y, z)

IDENTITY_Q: Quat = (1.0, 0.0, 0.0, 0.0)
_H = math.sqrt(0.5)
# +90 deg about x: MoCap y (up) -> z.
Y_UP_TO_Z_UP_Q: Quat = (_H, _H, 0.0, 0.0)


def quat_mul(a: Quat, b: Quat) -> Quat:
    """Hamilton product a ⊗ b, both (w, x, y, z)."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return (
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    )


def quat_conj(q: Quat) -> Quat:
    return (q[0], -q[1], -q[2], -q[3])


def quat_normalize(q: Quat) -> Quat:
    """Unit quaternion with w >= 0; raises ValueError for a zero or non-finite quaternion."""
    n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    if not math.isfinite(n) or n < 1e-9:
        raise ValueError(f"cannot normalise quaternion {q}")
    s = 1.0 / n if q[0] >= 0.0 else -1.0 / n
    return (q[0] * s, q[1] * s, q[2] * s, q[3] * s)


def quat_rotate(q: Quat, v: Vec3) -> Vec3:
    """R(q) v for a unit quaternion q (w, x, y, z)."""
    w, x, y, z = q
    vx, vy, vz = v
    # t = 2 (q_vec × v); v' = v + w t + q_vec × t
    tx = 2.0 * (y * vz - z * vy)
    ty = 2.0 * (z * vx - x * vz)
    tz = 2.0 * (x * vy - y * vx)
    return (
        vx + w * tx + (y * tz - z * ty),
        vy + w * ty + (z * tx - x * tz),
        vz + w * tz + (x * ty - y * tx),
    )


def quat_angle_rad(a: Quat, b: Quat) -> float:
    """Rotation angle between two quaternions (sign- and scale-insensitive), in [0, pi].

    Computed as 2 atan2(|vec(a* ⊗ b)|, |w(a* ⊗ b)|): accurate for tiny angles, where the
    usual acos of the dot product loses half the digits.
    """
    d = quat_mul(quat_conj(a), b)
    return 2.0 * math.atan2(math.sqrt(d[1] * d[1] + d[2] * d[2] + d[3] * d[3]), abs(d[0]))


def quat_from_axis_angle(axis: Vec3, angle_rad: float) -> Quat:
    n = math.sqrt(axis[0] ** 2 + axis[1] ** 2 + axis[2] ** 2)
    if n < 1e-12:
        return IDENTITY_Q
    s = math.sin(angle_rad / 2.0) / n
    return (math.cos(angle_rad / 2.0), axis[0] * s, axis[1] * s, axis[2] * s)


def xyzw_to_wxyz(q: tuple[float, float, float, float]) -> Quat:
    return (q[3], q[0], q[1], q[2])


def wxyz_to_xyzw(q: Quat) -> tuple[float, float, float, float]:
    return (q[1], q[2], q[3], q[0])


def _is_unit(q: Quat) -> bool:
    return abs(math.sqrt(sum(c * c for c in q)) - 1.0) < 1e-6


@dataclass(frozen=True)
class FrameConfig:
    """How MoCap poses become world-frame body poses. Loadable from YAML (``config.schema``)."""

    up_axis: Literal["y", "z"] = "y"
    units: Literal["m", "mm"] = "m"
    world_from_mocap_q: Quat = IDENTITY_Q
    mocap_origin_w_m: Vec3 = (0.0, 0.0, 0.0)
    rb_to_body_q: Quat = IDENTITY_Q
    body_origin_rb_m: Vec3 = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        if self.up_axis not in ("y", "z"):
            raise ConfigValueError("up_axis", f"must be 'y' or 'z', got {self.up_axis!r}")
        if self.units not in ("m", "mm"):
            raise ConfigValueError("units", f"must be 'm' or 'mm', got {self.units!r}")
        for key in ("world_from_mocap_q", "rb_to_body_q"):
            if not _is_unit(getattr(self, key)):
                raise ConfigValueError(key, "must be a unit quaternion (w, x, y, z)")

    @property
    def scale_to_m(self) -> float:
        return 0.001 if self.units == "mm" else 1.0


class FrameTransform:
    """Precomputed :class:`FrameConfig`: ``to_world`` for clients, ``to_mocap`` for emulators."""

    __slots__ = ("_c", "_c_inv", "_cfg", "_o", "_q_mw", "_q_rb_b", "_q_wm", "_scale", "_t")

    def __init__(self, cfg: FrameConfig | None = None) -> None:
        cfg = cfg or FrameConfig()
        self._cfg = cfg
        self._c = Y_UP_TO_Z_UP_Q if cfg.up_axis == "y" else IDENTITY_Q
        self._c_inv = quat_conj(self._c)
        self._scale = cfg.scale_to_m
        self._q_wm = quat_normalize(cfg.world_from_mocap_q)
        self._q_mw = quat_conj(self._q_wm)
        self._t = cfg.mocap_origin_w_m
        self._q_rb_b = quat_normalize(cfg.rb_to_body_q)
        self._o = cfg.body_origin_rb_m

    @property
    def config(self) -> FrameConfig:
        return self._cfg

    def to_world(self, pos_mocap: Vec3, q_mocap_xyzw: tuple[float, float, float, float]
                 ) -> tuple[Vec3, Quat]:
        """MoCap position (MoCap units) and wire quaternion (x, y, z, w) -> (pos_w_m, q_wb).

        Raises ValueError for a zero or non-finite quaternion.
        """
        s = self._scale
        p_c = quat_rotate(self._c, (pos_mocap[0] * s, pos_mocap[1] * s, pos_mocap[2] * s))
        q_raw = quat_normalize(xyzw_to_wxyz(q_mocap_xyzw))
        q_c = quat_mul(quat_mul(self._c, q_raw), self._c_inv)
        pw = quat_rotate(self._q_wm, p_c)
        p_w = (pw[0] + self._t[0], pw[1] + self._t[1], pw[2] + self._t[2])
        q_w_rb = quat_mul(self._q_wm, q_c)
        off = quat_rotate(q_w_rb, self._o)
        p_wb = (p_w[0] + off[0], p_w[1] + off[1], p_w[2] + off[2])
        return p_wb, quat_normalize(quat_mul(q_w_rb, self._q_rb_b))

    def point_to_mocap(self, p_w_m: Vec3) -> Vec3:
        """A world point (a marker, not a body origin) -> MoCap position (MoCap units): the
        position part of :meth:`to_mocap` without the rigid body's origin offset."""
        p_w = (p_w_m[0] - self._t[0], p_w_m[1] - self._t[1], p_w_m[2] - self._t[2])
        p_raw = quat_rotate(self._c_inv, quat_rotate(self._q_mw, p_w))
        s = 1.0 / self._scale
        return (p_raw[0] * s, p_raw[1] * s, p_raw[2] * s)

    def to_mocap(self, pos_w_m: Vec3, q_wb: Quat) -> tuple[Vec3, tuple[float, float, float, float]]:
        """Inverse of :meth:`to_world`: world body pose -> (MoCap position, wire quat x,y,z,w)."""
        q_w_rb = quat_mul(quat_normalize(q_wb), quat_conj(self._q_rb_b))
        off = quat_rotate(q_w_rb, self._o)
        # the rigid body's origin is a point: the body origin less its offset
        p_m = self.point_to_mocap((pos_w_m[0] - off[0], pos_w_m[1] - off[1],
                                   pos_w_m[2] - off[2]))
        q_c = quat_mul(self._q_mw, q_w_rb)
        q_raw = quat_normalize(quat_mul(quat_mul(self._c_inv, q_c), self._c))
        return p_m, wxyz_to_xyzw(q_raw)

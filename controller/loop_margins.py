"""Stability margins of the controller's linearised loops (pure numerics, no flight).

Each axis of the position loop, linearised at hover, is the mass under a PID force:
``m s^3 + K_v s^2 + K_p s + K_pi = 0``; each attitude axis is the inertia under a PID moment:
``J s^3 + K_w s^2 + K_R s + K_Ri = 0``. From their roots:

- ``pos_min_damping``, ``att_min_damping``: the smallest damping ratio ``-Re(p) / |p|`` of any
  closed-loop pole of any axis of that loop (1 for a real pole): how oscillatory its least
  damped mode is;
- ``separation``: the roll/pitch loop's natural frequency ``sqrt(K_R / J)`` over the position
  loop's ``sqrt(K_p / m)``, the smallest over the axes. At zero tilt the lateral position is
  steered through the attitude, so the attitude must be the faster loop, by a margin;
- ``routh_ratio``: ``K_v K_p / (m K_pi)``, the smallest over the position axes (> 1 is stable,
  the vehicle file asks for > 2);
- ``slowest_pole_rad_s``: the smallest ``|Re(p)|`` of the position loop (what sets how fast
  an integral finds a steady force).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from controller.params import VehicleParams


@dataclass(frozen=True)
class LoopMargins:
    pos_min_damping: float
    att_min_damping: float
    separation: float
    routh_ratio: float
    slowest_pole_rad_s: float


def _poles(inertia: float, d: float, k: float, ki: float) -> np.ndarray:
    return np.roots([inertia, d, k, ki]) if ki > 0.0 else np.roots([inertia, d, k])


def _damping(poles: np.ndarray) -> float:
    return float(min((-p.real / abs(p)) if abs(p) > 0 else 1.0 for p in poles))


def loop_margins(params: VehicleParams) -> LoopMargins:
    """The margins of ``params``' gains on its mass and inertia (module docstring)."""
    c = params.controller
    m = params.mass_kg
    pos_damping = att_damping = math.inf
    slowest = math.inf
    routh = math.inf
    for axis in range(3):
        pos = _poles(m, c.kv_pos[axis], c.kp_pos[axis], c.ki_pos[axis])
        att = _poles(params.inertia_diag_kg_m2[axis], c.kw_att[axis], c.kr_att[axis],
                     c.ki_att[axis])
        pos_damping = min(pos_damping, _damping(pos))
        att_damping = min(att_damping, _damping(att))
        slowest = min(slowest, float(np.min(np.abs(pos.real))))
        if c.ki_pos[axis] > 0.0:
            routh = min(routh, c.kv_pos[axis] * c.kp_pos[axis] / (m * c.ki_pos[axis]))
    att_w = min(math.sqrt(c.kr_att[a] / params.inertia_diag_kg_m2[a]) for a in (0, 1))
    pos_w = max(math.sqrt(c.kp_pos[a] / m) for a in (0, 1))
    return LoopMargins(pos_min_damping=pos_damping, att_min_damping=att_damping,
                       separation=att_w / pos_w, routh_ratio=routh,
                       slowest_pole_rad_s=slowest)

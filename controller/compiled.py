"""Compiled loops of the controller (numba, cached on disk), with plain-Python fallbacks.

The wrench mapper's per-tilt 6x6 map as a compiled loop (numba, cached on disk): the same
maths as :meth:`controller.model.VehicleModel.allocation` followed by
:func:`controller.wrench.tikhonov_map`, without the dozen small numpy calls (~60 us) that cost
more than the arithmetic. The map is recomputed on every tick while the tilt moves.

The solve is an LU factorisation with partial pivoting (LAPACK's ``gesv``, unblocked), so the
map equals numpy's up to rounding. Without numba :data:`AVAILABLE` is false and the wrench
mapper keeps the numpy path.

:func:`jit` and :func:`jitable` are the decorators the controller's own modules use (the
geometric controller's per-tick law, :mod:`controller.geometric`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any, TypeVar

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]
F = TypeVar("F", bound=Callable[..., Any])

try:
    import numba
    from numba.extending import register_jitable

    AVAILABLE = True

    def jit(fn: F) -> F:
        """Compiled (nopython, cached on disk), no fast-math."""
        return numba.njit(cache=True, fastmath=False, nogil=True)(fn)  # type: ignore[return-value]

    def jitable(fn: F) -> F:
        """A plain Python function that compiled code may call too."""
        return register_jitable(fn)
except ImportError:             # pragma: no cover - exercised where numba is absent
    AVAILABLE = False

    def jit(fn: F) -> F:
        return fn

    def jitable(fn: F) -> F:
        return fn


_jit = jit


@_jit
def allocation(alpha_rad: float, arm_yaw_rad: FloatArray, tilt_signs: FloatArray,
               positions_b_m: FloatArray, drag_m: FloatArray, out: FloatArray) -> None:
    """``F(alpha) = [F1; F2]`` into ``out`` (6 x 6): thrust axes ``Rz(yaw_i) Rx(s_i alpha)
    e3`` and moments ``p_i x axis_i + drag_i axis_i`` per unit thrust, one column each."""
    for i in range(arm_yaw_rad.shape[0]):
        a = tilt_signs[i] * alpha_rad
        s, c = math.sin(a), math.cos(a)
        cy, sy = math.cos(arm_yaw_rad[i]), math.sin(arm_yaw_rad[i])
        ax, ay, az = sy * s, -cy * s, c
        px, py, pz = positions_b_m[i, 0], positions_b_m[i, 1], positions_b_m[i, 2]
        d = drag_m[i]
        out[0, i], out[1, i], out[2, i] = ax, ay, az
        out[3, i] = (py * az - pz * ay) + d * ax
        out[4, i] = (pz * ax - px * az) + d * ay
        out[5, i] = (px * ay - py * ax) + d * az


@_jit
def tikhonov_map(f: FloatArray, gamma: float, out: FloatArray) -> None:
    """``(F^T F + gamma I)^-1 F^T`` into ``out`` for a square ``f``."""
    n = f.shape[0]
    a = np.empty((n, n))
    for i in range(n):
        for j in range(n):
            s = 0.0
            for k in range(n):
                s += f[k, i] * f[k, j]
            a[i, j] = s + gamma if i == j else s
    for i in range(n):
        for j in range(n):
            out[i, j] = f[j, i]
    # LU with partial pivoting, applied to the right-hand sides as it goes
    for k in range(n):
        p = k
        big = abs(a[k, k])
        for i in range(k + 1, n):
            if abs(a[i, k]) > big:
                p, big = i, abs(a[i, k])
        if p != k:
            for j in range(n):
                a[k, j], a[p, j] = a[p, j], a[k, j]
                out[k, j], out[p, j] = out[p, j], out[k, j]
        for i in range(k + 1, n):
            m = a[i, k] / a[k, k]
            for j in range(k + 1, n):
                a[i, j] -= m * a[k, j]
            for j in range(n):
                out[i, j] -= m * out[k, j]
    for k in range(n - 1, -1, -1):
        for j in range(n):
            s = out[k, j]
            for i in range(k + 1, n):
                s -= a[k, i] * out[i, j]
            out[k, j] = s / a[k, k]


@_jit
def wrench_map(alpha_rad: float, gamma: float, arm_yaw_rad: FloatArray, tilt_signs: FloatArray,
               positions_b_m: FloatArray, drag_m: FloatArray, work: FloatArray,
               out: FloatArray) -> None:
    """The Tikhonov map at ``alpha_rad`` into ``out``; ``work`` (6 x 6) is scratch."""
    allocation(alpha_rad, arm_yaw_rad, tilt_signs, positions_b_m, drag_m, work)
    tikhonov_map(work, gamma, out)

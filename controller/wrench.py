"""The wrench mapper (paper Sec. IV-C): body wrench -> six propeller thrusts.

``u = (F^T F + gamma I)^-1 F^T [u_f; u_tau]`` with the Tikhonov parameter
``gamma(alpha) = k1 / (alpha + k2)`` (alpha in rad, thrusts in N; paper-notes item 10: k1 = 4e-6,
k2 = 0.02 keeps ~92 % of a demanded yaw torque at alpha = 0 while regularising the rank loss).

The 6x6 map depends only on alpha, so it is computed once per alpha (estimation-notes §6, as
uavatt does) and reused while the measured tilt stays within ``alpha_tolerance_rad`` of the
cached one; the per-tick product is done on Python floats (faster than numpy at 6x6). While the
tilt moves the map is recomputed every tick, compiled (:mod:`controller.compiled`) when numba is
installed.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from controller import compiled
from controller.model import VehicleModel

FloatArray = npt.NDArray[np.float64]


def tikhonov_gamma(alpha_rad: float, k1: float, k2_rad: float) -> float:
    """gamma(alpha) = k1 / (|alpha| + k2)."""
    return k1 / (abs(alpha_rad) + k2_rad)


def tikhonov_map(allocation: FloatArray, gamma: float) -> FloatArray:
    """``(F^T F + gamma I)^-1 F^T`` for a 6x6 allocation matrix."""
    f = np.asarray(allocation, dtype=float)
    return np.asarray(np.linalg.solve(f.T @ f + gamma * np.eye(f.shape[1]), f.T), dtype=float)


class WrenchMapper:
    """Tikhonov-regularised allocation inverse with a per-alpha cache.

    ``alpha_tolerance_rad`` (default 1e-4 rad = 0.006 deg, about the resolution of the tilt
    servo seen through the 20:1 worm) bounds how far the measured tilt may move before the map
    is recomputed; 0 recomputes on every change.
    """

    def __init__(self, model: VehicleModel, *, alpha_tolerance_rad: float = 1e-4) -> None:
        self.model = model
        c = model.params.controller
        self.k1 = c.tikhonov_k1
        self.k2_rad = c.tikhonov_k2_rad
        self.alpha_tolerance_rad = alpha_tolerance_rad
        self._alpha = math.nan
        self._rows: tuple[tuple[float, ...], ...] | None = None  # of _array, on demand
        #: number of times the 6x6 map was (re)computed (the cache's effect, for tests)
        self.recomputations = 0
        # the compiled map computes VehicleModel.allocation's geometry itself
        self._compiled = compiled.AVAILABLE and \
            type(model).allocation is VehicleModel.allocation
        self._geometry = (np.ascontiguousarray(model.arm_yaw_rad, dtype=np.float64),
                          np.ascontiguousarray(model.tilt_signs, dtype=np.float64),
                          np.ascontiguousarray(model.rotor_positions_b_m, dtype=np.float64),
                          np.ascontiguousarray(model.drag_signs * model.c_tau_m,
                                               dtype=np.float64))
        self._work = np.empty((6, 6))
        self._out = np.empty((6, 6))
        self._array = self._out

    def warm_up(self, alpha_rad: float = 0.0) -> None:
        """Compute the map at ``alpha_rad`` now (and compile the kernel, or load it from
        numba's on-disk cache), so that the first tick does not."""
        self._ensure(alpha_rad)

    def matrix(self, alpha_rad: float) -> FloatArray:
        """The 6x6 map at ``alpha_rad`` (from the cache when close enough)."""
        return np.array(self.rows(alpha_rad))

    def _ensure(self, alpha_rad: float) -> None:
        if not abs(alpha_rad - self._alpha) <= self.alpha_tolerance_rad:
            gamma = tikhonov_gamma(alpha_rad, self.k1, self.k2_rad)
            if self._compiled:
                compiled.wrench_map(float(alpha_rad), gamma, *self._geometry, self._work,
                                    self._out)
                m = self._out
            else:
                m = tikhonov_map(self.model.allocation(alpha_rad), gamma)
            self._array = m
            self._rows = None  # the compiled controller reads the array only
            self._alpha = alpha_rad
            self.recomputations += 1

    def rows(self, alpha_rad: float) -> tuple[tuple[float, ...], ...]:
        """The map at ``alpha_rad`` as six rows of Python floats (from the cache when close
        enough)."""
        self._ensure(alpha_rad)
        if self._rows is None:
            self._rows = tuple(tuple(row) for row in self._array.tolist())
        return self._rows

    def rows_array(self, alpha_rad: float) -> FloatArray:
        """The map at ``alpha_rad`` (6 x 6, read-only: the cache itself, overwritten when the
        map is recomputed)."""
        self._ensure(alpha_rad)
        return self._array

    def thrusts_n(self, alpha_rad: float, u_f_b_n: tuple[float, float, float],
                  u_tau_b_n_m: tuple[float, float, float]) -> list[float]:
        """Six thrusts (N, possibly outside the rotor limits) for the body wrench."""
        fx, fy, fz = u_f_b_n
        tx, ty, tz = u_tau_b_n_m
        return [r[0] * fx + r[1] * fy + r[2] * fz + r[3] * tx + r[4] * ty + r[5] * tz
                for r in self.rows(alpha_rad)]

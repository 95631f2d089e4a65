"""The UKF's numerics: process and measurement models, and two interchangeable kernels.

Error state (15): ``x = [p_w, v_w, dtheta_b, b_g, b_a]``; the attitude is
``q_wb = q_ref (x) Exp(dtheta)`` with the nominal ``q_ref`` kept outside the filter, so the
filter never averages quaternions (USQUE / error-state pattern). The IMU is the process input:

    q'  = q_ref (x) Exp(dtheta) (x) Exp((gyro - b_g) dt)
    a_w = R(q_ref (x) Exp(dtheta)) (accel - b_a) + g_w        (g_w = (0, 0, -g))
    p'  = p + v dt + a_w dt^2 / 2,   v' = v + a_w dt
    dtheta' = Log(q_ref'^-1 (x) q'),  q_ref' = q_ref (x) Exp((gyro - mean b_g) dt)

:func:`process_model` is written once over leading axes. :class:`FastKernel` pushes all 2n+1
sigma points through it in one call; :class:`FilterpyKernel` hands the same function to stock
``filterpy.kalman.UnscentedKalmanFilter``, which calls it once per sigma point. Both use
filterpy's ``MerweScaledSigmaPoints`` weights; the tests prove they give the same estimates.

The MoCap measurement is ``z = [p_m, Log(q_ref^-1 (x) q_m)]`` with ``h(x) = [p, dtheta]``.
"""

from __future__ import annotations

import functools
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt
from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter

from . import compiled
from .quaternion import left_matrix, quat_exp, quat_log, quat_to_rot

FloatArray = npt.NDArray[np.float64]

MEAS_IDX = np.array([0, 1, 2, 6, 7, 8])


def process_model(x: FloatArray, dt: float, *, gyro_rad_s: FloatArray, accel_m_s2: FloatArray,
                  left_ref: FloatArray, left_next_ref_inv: FloatArray,
                  gravity_w: FloatArray) -> FloatArray:
    """Propagate error states ``x`` (..., 15) over ``dt`` with one IMU sample.

    ``left_ref`` = L(q_ref) and ``left_next_ref_inv`` = L(q_ref'^-1) (4x4, see
    :func:`~estimator.quaternion.left_matrix`) are shared by every sigma point.
    """
    rotvecs = np.empty((*x.shape[:-1], 2, 3))          # one Exp call for both rotations
    rotvecs[..., 0, :] = x[..., 6:9]
    rotvecs[..., 1, :] = (gyro_rad_s - x[..., 9:12]) * dt
    exps = quat_exp(rotvecs)
    q = exps[..., 0, :] @ left_ref.T                     # q_ref (x) Exp(dtheta)
    a_w = (quat_to_rot(q) @ (accel_m_s2 - x[..., 12:15])[..., None])[..., 0] + gravity_w
    q_next = (left_matrix(q) @ exps[..., 1, :, None])[..., 0]
    F, G = _linear_step(dt)
    out = x @ F.T + a_w @ G.T          # p + v dt + a dt^2/2, v + a dt, biases unchanged
    out[..., 6:9] = quat_log(q_next @ left_next_ref_inv.T)
    return out


@functools.lru_cache(maxsize=8)
def _linear_step(dt: float) -> tuple[FloatArray, FloatArray]:
    """F (15x15, zero on the attitude rows) and G (15x3) of the linear part of the step."""
    i3 = np.eye(3)
    F = np.eye(15)
    F[6:9, 6:9] = 0.0
    F[0:3, 3:6] = dt * i3
    G = np.zeros((15, 3))
    G[0:3] = 0.5 * dt * dt * i3
    G[3:6] = dt * i3
    return F, G


def measurement_model(x: FloatArray) -> FloatArray:
    """h(x) = [p, dtheta] (..., 6)."""
    return x[..., MEAS_IDX]


def make_sigma_points(n: int, alpha: float, beta: float, kappa: float) -> MerweScaledSigmaPoints:
    return MerweScaledSigmaPoints(n, alpha=alpha, beta=beta, kappa=kappa)


class UpdateResult(Protocol):
    x: FloatArray
    P: FloatArray
    y: FloatArray
    S: FloatArray


class Kernel(Protocol):
    """One predict or one (not yet accepted) update of the error-state UKF."""

    def predict(self, x: FloatArray, P: FloatArray, Q: FloatArray, dt: float,
                gyro_rad_s: FloatArray, accel_m_s2: FloatArray, q_ref: FloatArray,
                q_next_ref_inv: FloatArray) -> tuple[FloatArray, FloatArray]:
        """``q_ref`` and ``q_next_ref_inv`` (= q_ref'^-1) are shared by every sigma point."""
        ...

    def update(self, x: FloatArray, P: FloatArray, z: FloatArray, R: FloatArray
               ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """-> (x_post, P_post, innovation y, innovation covariance S)."""
        ...


class FastKernel:
    """All sigma points as one array (numpy); filterpy's sigma-point parameters and weights."""

    def __init__(self, n: int, alpha: float, beta: float, kappa: float,
                 gravity_w: FloatArray) -> None:
        points = make_sigma_points(n, alpha, beta, kappa)
        self.n = n
        self.Wm = np.asarray(points.Wm, dtype=np.float64)
        self.Wc = np.asarray(points.Wc, dtype=np.float64)
        self.scale = alpha ** 2 * (n + kappa)            # = n + lambda
        self.gravity_w = gravity_w
        self._sigmas = np.empty((2 * n + 1, n))

    def sigma_points(self, x: FloatArray, P: FloatArray) -> FloatArray:
        """Same points as ``MerweScaledSigmaPoints.sigma_points`` (rows of the upper factor)."""
        U = np.linalg.cholesky(self.scale * P).T
        s = self._sigmas
        n = self.n
        s[:] = x
        s[1:n + 1] += U
        s[n + 1:] -= U
        return s

    def predict(self, x: FloatArray, P: FloatArray, Q: FloatArray, dt: float,
                gyro_rad_s: FloatArray, accel_m_s2: FloatArray, q_ref: FloatArray,
                q_next_ref_inv: FloatArray) -> tuple[FloatArray, FloatArray]:
        left_ref, left_next_ref_inv = left_matrix(q_ref), left_matrix(q_next_ref_inv)
        sig = process_model(self.sigma_points(x, P), dt, gyro_rad_s=gyro_rad_s,
                            accel_m_s2=accel_m_s2, left_ref=left_ref,
                            left_next_ref_inv=left_next_ref_inv, gravity_w=self.gravity_w)
        x_new = self.Wm @ sig
        dev = sig - x_new
        return x_new, (dev.T * self.Wc) @ dev + Q

    def update(self, x: FloatArray, P: FloatArray, z: FloatArray, R: FloatArray
               ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        sig = self.sigma_points(x, P)
        sig_h = sig[:, MEAS_IDX]
        zp = self.Wm @ sig_h
        dz = sig_h - zp
        wdz = dz * self.Wc[:, None]
        S = dz.T @ wdz + R
        Pxz = (sig - x).T @ wdz
        K = Pxz @ np.linalg.inv(S)
        y = z - zp
        return x + K @ y, P - K @ S @ K.T, y, S


class FilterpyKernel:
    """Stock filterpy ``UnscentedKalmanFilter``: per-sigma-point ``fx``/``hx``. The reference."""

    def __init__(self, n: int, alpha: float, beta: float, kappa: float,
                 gravity_w: FloatArray) -> None:
        self.points = make_sigma_points(n, alpha, beta, kappa)
        self.gravity_w = gravity_w
        self.ukf = UnscentedKalmanFilter(dim_x=n, dim_z=6, dt=0.002, hx=measurement_model,
                                         fx=process_model, points=self.points)

    def predict(self, x: FloatArray, P: FloatArray, Q: FloatArray, dt: float,
                gyro_rad_s: FloatArray, accel_m_s2: FloatArray, q_ref: FloatArray,
                q_next_ref_inv: FloatArray) -> tuple[FloatArray, FloatArray]:
        left_ref, left_next_ref_inv = left_matrix(q_ref), left_matrix(q_next_ref_inv)
        f = self.ukf
        f.x, f.P, f.Q = x.copy(), P.copy(), Q
        f.predict(dt=dt, gyro_rad_s=gyro_rad_s, accel_m_s2=accel_m_s2, left_ref=left_ref,
                  left_next_ref_inv=left_next_ref_inv, gravity_w=self.gravity_w)
        return f.x.copy(), f.P.copy()

    def update(self, x: FloatArray, P: FloatArray, z: FloatArray, R: FloatArray
               ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        f = self.ukf
        f.x, f.P = x.copy(), P.copy()
        # x changed since predict (attitude folded into q_ref): redraw, as filterpy#172 advises.
        f.sigmas_f = self.points.sigma_points(f.x, f.P)
        f.update(z, R=R)
        return f.x.copy(), f.P.copy(), f.y.copy(), f.S.copy()


class CompiledKernel:
    """The same predict and update as compiled loops (:mod:`estimator.compiled`, numba).

    Compiles (or loads from numba's on-disk cache) when constructed, with one predict and one
    update on a dummy state, so that no flight tick waits on the JIT.
    """

    def __init__(self, n: int, alpha: float, beta: float, kappa: float,
                 gravity_w: FloatArray) -> None:
        points = make_sigma_points(n, alpha, beta, kappa)
        self.n = n
        self.Wm = np.ascontiguousarray(points.Wm, dtype=np.float64)
        self.Wc = np.ascontiguousarray(points.Wc, dtype=np.float64)
        self.scale = float(alpha ** 2 * (n + kappa))         # = n + lambda
        self.gravity_w = np.ascontiguousarray(gravity_w, dtype=np.float64)
        m = 2 * n + 1
        self._sig = np.empty((m, n))
        self._dev = np.empty((n, m))      # deviations, transposed (compiled._mean_cov)
        self._work = np.empty((n, n))
        self._U = np.empty((n, n))
        self._meas_idx = MEAS_IDX.astype(np.int64)
        self._q_tmp = np.empty(4)
        self._Q = np.zeros((n, n))
        self._x_out, self._P_out, self._q_out = np.empty(n), np.empty((n, n)), np.empty(4)
        self._y, self._S, self._z = np.empty(6), np.empty((6, 6)), np.empty(6)
        # fuse_in_past: the replayed state, and the history entries it rewrites (sized on use)
        self._xs, self._Ps, self._qs = np.empty(n), np.empty((n, n)), np.empty(4)
        self._bak = (np.empty((0, n)), np.empty((0, n, n)), np.empty((0, 4)))
        self._warm_up()

    def _warm_up(self) -> None:
        x, P, q = np.zeros(self.n), np.eye(self.n) * 1e-4, np.array([1.0, 0.0, 0.0, 0.0])
        Q, R = np.eye(self.n) * 1e-8, np.eye(6) * 1e-6
        x1, P1 = self.predict(x, P, Q, 0.002, np.zeros(3), -self.gravity_w, q, q)
        self.update(x1, P1, np.zeros(6), R)
        out = self.predict_step(x, P, q, Q, 0.002, np.zeros(3), -self.gravity_w, 1e-12, 1.0)
        if out is not None:
            self.update_step(out[0], out[1], out[2], np.zeros(6), R, 1e-12, 1.0)
        # the whole predict, with the argument types of Ukf._compiled_predict
        n_hist, cap = 4, 4
        hist = (np.zeros(n_hist), np.zeros((n_hist, self.n)), np.zeros((n_hist, self.n, self.n)),
                np.zeros((n_hist, 4)), np.zeros((n_hist, 3)), np.zeros((n_hist, 3)))
        buf, ij = np.zeros((cap, compiled.ROW_WIDTH)), np.zeros(2, dtype=np.int64)
        corr = np.zeros(10)
        corr[6] = 1.0
        rates = np.full(4, 1e-6)
        for shift in (True, False):
            self.fuse_now(0.001, np.zeros(3), q.copy(), shift, 0.002, x.copy(), P.copy(),
                          q.copy(), R, 1e9, hist[1], hist[2], hist[3], hist[4],
                          np.zeros(3, dtype=np.int64), buf, ij, corr, 1e-12, 1.0, np.zeros(7),
                          np.zeros(10))
        for direct in (True, False):
            inp = np.zeros(14)
            inp[3:6] = inp[6:9] = -self.gravity_w
            inp[12] = inp[13] = 1.0
            self.horizon_predict(0.002, 0.002, inp, 0.0, direct, 0.0, x.copy(), P.copy(),
                                 q.copy(), buf, ij, corr, float(-self.gravity_w[2]), *hist,
                                 np.zeros(3, dtype=np.int64), rates, 1e-12, 1.0, np.zeros(10),
                                 np.zeros(8), np.array([1e-4, 1.0, 0.03, 1e-4]))
            self.advance(0.004, 0.0, x.copy(), P.copy(), q.copy(), buf, ij, corr, *hist,
                         np.zeros(3, dtype=np.int64), rates, 1e-12, 1.0, np.zeros(10))
        hij = np.array([n_hist - 1, n_hist, 0], dtype=np.int64)
        self.fuse_in_past(0.001, np.zeros(3), q.copy(), 0.004, x.copy(), P.copy(), q.copy(), R,
                          1e9, np.arange(n_hist, dtype=np.float64) * 0.001, np.tile(x, (n_hist, 1)),
                          np.tile(P, (n_hist, 1, 1)), np.tile(q, (n_hist, 1)), hist[4],
                          hist[5], hij, buf, ij, corr, rates, 1e-12, 1.0, np.zeros(7),
                          np.zeros(10))

    def fuse_now(self, t_c: float, pos: FloatArray, q_m: FloatArray, shift: bool,
                 t_filter: float, x: FloatArray, P: FloatArray, q_ref: FloatArray,
                 R: FloatArray, gate_nis: float, hist_x: FloatArray, hist_P: FloatArray,
                 hist_q: FloatArray, hist_gyro: FloatArray, hij: npt.NDArray[Any],
                 buf: FloatArray, ij: npt.NDArray[Any], corr: FloatArray, min_variance: float,
                 max_pos_variance: float, pose_out: FloatArray, newest: FloatArray
                 ) -> tuple[int, float]:
        """``Ukf._fuse_now`` in one call (see :func:`compiled.fuse_now`) -> (status, NIS)."""
        status, nis = compiled.fuse_now(
            t_c, pos, q_m, shift, t_filter, x, P, q_ref, R, self._meas_idx, gate_nis, hist_x,
            hist_P, hist_q, hist_gyro, hij, buf, ij, corr, self.Wm, self.Wc, self.scale,
            min_variance, max_pos_variance, self._sig, self._work, self._U, self._x_out,
            self._P_out, self._q_out, self._y, self._S, self._z, pose_out, newest)
        return int(status), float(nis)

    def horizon_predict(self, t: float, dt: float, inp: FloatArray, target_t: float,
                        direct: bool, t_filter: float, x: FloatArray,
                        P: FloatArray, q_ref: FloatArray, buf: FloatArray, ij: npt.NDArray[Any],
                        corr: FloatArray, gravity_m_s2: float, hist_t: FloatArray,
                        hist_x: FloatArray, hist_P: FloatArray, hist_q: FloatArray,
                        hist_gyro: FloatArray, hist_accel: FloatArray, hij: npt.NDArray[Any],
                        rates: FloatArray, min_variance: float, max_pos_variance: float,
                        newest: FloatArray, fobs: FloatArray, fconst: FloatArray
                        ) -> tuple[int, float]:
        """``Ukf.predict``'s filter step or queue-and-advance in one call (see
        :func:`compiled.horizon_predict`) -> (status, filter time)."""
        status, t_f = compiled.horizon_predict(
            t, dt, inp, target_t, direct, t_filter, x, P, q_ref, buf, ij, corr,
            gravity_m_s2, hist_t, hist_x, hist_P, hist_q, hist_gyro, hist_accel, hij, rates,
            self._Q, self.gravity_w, self.Wm, self.Wc, self.scale, min_variance,
            max_pos_variance, self._sig, self._work, self._U, self._dev, self._q_tmp,
            self._x_out, self._P_out, self._q_out, newest, fobs, fconst)
        return int(status), float(t_f)

    def advance(self, target_t: float, t_filter: float, x: FloatArray, P: FloatArray,
                q_ref: FloatArray, buf: FloatArray, ij: npt.NDArray[Any], corr: FloatArray,
                hist_t: FloatArray, hist_x: FloatArray, hist_P: FloatArray, hist_q: FloatArray,
                hist_gyro: FloatArray, hist_accel: FloatArray, hij: npt.NDArray[Any],
                rates: FloatArray, min_variance: float, max_pos_variance: float,
                newest: FloatArray) -> tuple[int, float]:
        """``Ukf._advance_filter`` in one call (see :func:`compiled.advance`) -> (status,
        filter time)."""
        status, t_f = compiled.advance(
            target_t, t_filter, x, P, q_ref, buf, ij, corr, hist_t, hist_x, hist_P, hist_q,
            hist_gyro, hist_accel, hij, rates, self._Q, self.gravity_w, self.Wm, self.Wc,
            self.scale, min_variance, max_pos_variance, self._sig, self._work, self._U,
            self._dev, self._q_tmp, self._x_out, self._P_out, self._q_out, newest)
        return int(status), float(t_f)

    def fuse_in_past(self, t_c: float, pos: FloatArray, q_m: FloatArray, t_filter: float,
                     x: FloatArray, P: FloatArray, q_ref: FloatArray, R: FloatArray,
                     gate_nis: float, hist_t: FloatArray, hist_x: FloatArray,
                     hist_P: FloatArray, hist_q: FloatArray, hist_gyro: FloatArray,
                     hist_accel: FloatArray, hij: npt.NDArray[Any], buf: FloatArray,
                     ij: npt.NDArray[Any], corr: FloatArray, rates: FloatArray,
                     min_variance: float, max_pos_variance: float, pose_out: FloatArray,
                     newest: FloatArray) -> tuple[int, float]:
        """``Ukf._fuse_in_past`` in one call (see :func:`compiled.fuse_in_past`) -> (status,
        NIS)."""
        n_hist = hist_t.shape[0]
        if self._bak[0].shape[0] != n_hist:  # once per filter: the history's size
            n = self.n
            self._bak = (np.empty((n_hist, n)), np.empty((n_hist, n, n)),
                         np.empty((n_hist, 4)))
        status, nis = compiled.fuse_in_past(
            t_c, pos, q_m, t_filter, x, P, q_ref, R, self._meas_idx, gate_nis, hist_t, hist_x,
            hist_P, hist_q, hist_gyro, hist_accel, hij, buf, ij, corr, rates, self._Q,
            self.gravity_w, self.Wm, self.Wc, self.scale, min_variance, max_pos_variance,
            self._sig, self._work, self._U, self._dev, self._q_tmp, self._x_out, self._P_out,
            self._q_out, self._y, self._S, self._z, pose_out, newest, self._xs, self._Ps,
            self._qs, *self._bak)
        return int(status), float(nis)

    def predict_step(self, x: FloatArray, P: FloatArray, q_ref: FloatArray, Q: FloatArray,
                     dt: float, gyro_rad_s: FloatArray, accel_m_s2: FloatArray,
                     min_variance: float, max_pos_variance: float
                     ) -> tuple[FloatArray, FloatArray, FloatArray, bool] | None:
        """``Ukf._propagate`` in one call -> (x, P, q_ref, finite); None if P is not SPD."""
        n = self.n
        x_out, P_out, q_out = np.empty(n), np.empty((n, n)), np.empty(4)
        status = compiled.predict_step(
            x, P, Q, dt, gyro_rad_s, accel_m_s2, q_ref, self.gravity_w, self.Wm, self.Wc,
            self.scale, min_variance, max_pos_variance, self._sig, self._work, self._U,
            self._dev, self._q_tmp, x_out, P_out, q_out)
        return None if status == 1 else (x_out, P_out, q_out, status == 0)

    def update_step(self, x: FloatArray, P: FloatArray, q_ref: FloatArray, z: FloatArray,
                    R: FloatArray, min_variance: float, max_pos_variance: float
                    ) -> tuple[FloatArray, FloatArray, FloatArray, float, bool] | None:
        """``Ukf._fuse`` before its gate -> (x, P, q_ref, nis, finite); None if P is not SPD."""
        n = self.n
        x_out, P_out, q_out = np.empty(n), np.empty((n, n)), np.empty(4)
        status, nis = compiled.update_step(
            x, P, q_ref, z, R, self._meas_idx, self.Wm, self.Wc, self.scale, min_variance,
            max_pos_variance, self._sig, self._work, self._U, x_out, P_out, q_out,
            np.empty(6), np.empty((6, 6)))
        return None if status == 1 else (x_out, P_out, q_out, nis, status == 0)

    def predict(self, x: FloatArray, P: FloatArray, Q: FloatArray, dt: float,
                gyro_rad_s: FloatArray, accel_m_s2: FloatArray, q_ref: FloatArray,
                q_next_ref_inv: FloatArray) -> tuple[FloatArray, FloatArray]:
        x_out, P_out = np.empty(self.n), np.empty((self.n, self.n))
        if not compiled.predict(x, P, Q, dt, gyro_rad_s, accel_m_s2, q_ref, q_next_ref_inv,
                                self.gravity_w, self.Wm, self.Wc, self.scale, self._sig,
                                self._work, self._U, self._dev, x_out, P_out):
            raise np.linalg.LinAlgError("covariance not positive definite")
        return x_out, P_out

    def update(self, x: FloatArray, P: FloatArray, z: FloatArray, R: FloatArray
               ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        n = self.n
        x_out, P_out, y, S = np.empty(n), np.empty((n, n)), np.empty(6), np.empty((6, 6))
        if compiled.update(x, P, z, R, self._meas_idx, self.Wm, self.Wc, self.scale,
                           self._sig, self._work, self._U, x_out, P_out, y, S) < 0.0:
            raise np.linalg.LinAlgError("covariance not positive definite")
        return x_out, P_out, y, S

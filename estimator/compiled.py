"""The UKF's predict and update as compiled loops (numba, cached on disk), same maths as
:class:`~estimator.kernels.FastKernel`.

Each sigma point is propagated with scalar closed forms (two Exp, one product, one rotation,
one Log) instead of stacks of small matrix products: at 31 points x 15 states the numpy path
spends its time dispatching calls, not computing. The weights are filterpy's
``MerweScaledSigmaPoints`` ones, passed in; the sigma points are the rows of the upper Cholesky
factor of ``(n + lambda) P`` as filterpy draws them. A Cholesky failure is returned as a flag
(the caller raises ``LinAlgError`` and repairs P, as with the numpy path).

Without numba installed :data:`AVAILABLE` is false and the plain-Python functions below are
still importable (far too slow to fly, used only to test the code path).
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

    AVAILABLE = True

    def _jit(fn: F) -> F:
        return numba.njit(cache=True, fastmath=False, nogil=True)(fn)  # type: ignore[return-value]

    def _jit_reassoc(fn: F) -> F:
        # reassociation only: no "no NaN / no inf" assumption, the finiteness checks hold
        return numba.njit(cache=True, fastmath={"reassoc"}, nogil=True)(fn)  # type: ignore[return-value]
except ImportError:             # pragma: no cover - exercised by the fallback test
    AVAILABLE = False

    def _jit(fn: F) -> F:
        return fn

    _jit_reassoc = _jit


@_jit
def _cholesky_upper(A: FloatArray, U: FloatArray) -> bool:
    """U (upper, U^T U = A) in place; False if A is not positive definite."""
    n = A.shape[0]
    for i in range(n):
        for j in range(n):
            U[i, j] = 0.0
    for j in range(n):
        s = A[j, j]
        for k in range(j):
            s -= U[k, j] * U[k, j]
        if not s > 0.0:
            return False
        d = math.sqrt(s)
        U[j, j] = d
        for i in range(j + 1, n):
            t = A[j, i]
            for k in range(j):
                t -= U[k, j] * U[k, i]
            U[j, i] = t / d
    return True


@_jit
def _draw_sigmas(x: FloatArray, P: FloatArray, scale: float, sig: FloatArray,
                 work: FloatArray, U: FloatArray) -> bool:
    n = x.shape[0]
    for i in range(n):
        for j in range(n):
            work[i, j] = scale * P[i, j]
    if not _cholesky_upper(work, U):
        return False
    for j in range(n):
        sig[0, j] = x[j]
    for i in range(n):
        for j in range(n):
            sig[1 + i, j] = x[j] + U[i, j]
            sig[1 + n + i, j] = x[j] - U[i, j]
    return True


@_jit
def _exp(a: float, b: float, c: float) -> tuple[float, float, float, float]:
    angle = math.sqrt(a * a + b * b + c * c)
    half = 0.5 * angle
    k = math.sin(half) / angle if angle > 0.0 else 0.0
    return math.cos(half), a * k, b * k, c * k


@_jit
def _mul(aw: float, ax: float, ay: float, az: float,
         bw: float, bx: float, by: float, bz: float) -> tuple[float, float, float, float]:
    return (aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw)


@_jit_reassoc
def _weighted_outer(devT: FloatArray, Wc: FloatArray, add: FloatArray, cov: FloatArray,
                    wd: FloatArray) -> None:
    """cov = sum_i Wc[i] d_i d_i^T + add over the columns d_i of ``devT`` (n x m, each row
    contiguous so the sums over i vectorise; they are reassociated, hence this helper alone
    is compiled with ``reassoc``)."""
    n, m = devT.shape
    for a in range(n):
        for i in range(m):
            wd[i] = Wc[i] * devT[a, i]
        for b in range(a, n):
            s = 0.0
            for i in range(m):
                s += wd[i] * devT[b, i]
            cov[a, b] = s + add[a, b]
            cov[b, a] = s + add[b, a]


@_jit
def _mean_cov(sig: FloatArray, Wm: FloatArray, Wc: FloatArray, add: FloatArray,
              mean: FloatArray, cov: FloatArray, devT: FloatArray) -> None:
    """Weighted mean and covariance (plus ``add``) of the rows of ``sig``; ``devT`` (n x m)
    is scratch."""
    m, n = sig.shape
    for j in range(n):
        s = 0.0
        for i in range(m):
            s += Wm[i] * sig[i, j]
        mean[j] = s
    for i in range(m):
        for j in range(n):
            devT[j, i] = sig[i, j] - mean[j]
    _weighted_outer(devT, Wc, add, cov, np.empty(m))


@_jit
def predict(x: FloatArray, P: FloatArray, Q: FloatArray, dt: float, gyro: FloatArray,
            accel: FloatArray, q_ref: FloatArray, q_next_inv: FloatArray,
            gravity_w: FloatArray, Wm: FloatArray, Wc: FloatArray, scale: float,
            sig: FloatArray, work: FloatArray, U: FloatArray, devT: FloatArray,
            x_out: FloatArray, P_out: FloatArray) -> bool:
    """One predict into ``x_out``/``P_out``; False if P is not positive definite."""
    if not _draw_sigmas(x, P, scale, sig, work, U):
        return False
    rw, rx, ry, rz = q_ref[0], q_ref[1], q_ref[2], q_ref[3]
    nw, nx, ny, nz = q_next_inv[0], q_next_inv[1], q_next_inv[2], q_next_inv[3]
    h = 0.5 * dt * dt
    for i in range(sig.shape[0]):
        s = sig[i]
        # q = q_ref (x) Exp(dtheta); a_w = R(q) (accel - b_a) + g
        ew, ex, ey, ez = _exp(s[6], s[7], s[8])
        qw, qx, qy, qz = _mul(rw, rx, ry, rz, ew, ex, ey, ez)
        fx, fy, fz = accel[0] - s[12], accel[1] - s[13], accel[2] - s[14]
        tx, ty, tz = 2.0 * (qy * fz - qz * fy), 2.0 * (qz * fx - qx * fz), 2.0 * (qx * fy - qy * fx)
        ax = fx + qw * tx + (qy * tz - qz * ty) + gravity_w[0]
        ay = fy + qw * ty + (qz * tx - qx * tz) + gravity_w[1]
        az = fz + qw * tz + (qx * ty - qy * tx) + gravity_w[2]
        # q' = q (x) Exp((gyro - b_g) dt); dtheta' = Log(q_ref'^-1 (x) q')
        gw, gx, gy, gz = _exp((gyro[0] - s[9]) * dt, (gyro[1] - s[10]) * dt,
                              (gyro[2] - s[11]) * dt)
        pw, px, py, pz = _mul(qw, qx, qy, qz, gw, gx, gy, gz)
        lw, lx, ly, lz = _mul(nw, nx, ny, nz, pw, px, py, pz)
        sn = math.sqrt(lx * lx + ly * ly + lz * lz)
        f = 2.0 * math.atan2(sn, abs(lw)) / sn * (1.0 if lw >= 0.0 else -1.0) if sn > 0.0 else 0.0
        s[0] += s[3] * dt + h * ax
        s[1] += s[4] * dt + h * ay
        s[2] += s[5] * dt + h * az
        s[3] += dt * ax
        s[4] += dt * ay
        s[5] += dt * az
        s[6], s[7], s[8] = lx * f, ly * f, lz * f
    _mean_cov(sig, Wm, Wc, Q, x_out, P_out, devT)
    return True


@_jit
def update(x: FloatArray, P: FloatArray, z: FloatArray, R: FloatArray, meas_idx: Any,
           Wm: FloatArray, Wc: FloatArray, scale: float, sig: FloatArray, work: FloatArray,
           U: FloatArray, x_out: FloatArray, P_out: FloatArray, y_out: FloatArray,
           S_out: FloatArray) -> float:
    """One (not yet gated) update -> the NIS ``y^T S^-1 y``; -1 if P or S is not positive
    definite (nothing meaningful written).

    S is factored once (Cholesky, ``S = L L^T``): the gain ``K = Pxz S^-1`` is solved row by
    row, ``P - K S K^T`` is ``P - Pxz K^T``, and the NIS is ``|L^-1 y|^2``; no inverse."""
    if not _draw_sigmas(x, P, scale, sig, work, U):
        return -1.0
    m, n = sig.shape
    nz = meas_idx.shape[0]
    zp = np.zeros(nz)
    for k in range(nz):
        s = 0.0
        for i in range(m):
            s += Wm[i] * sig[i, meas_idx[k]]
        zp[k] = s
    dz = np.empty((m, nz))
    for i in range(m):
        for k in range(nz):
            dz[i, k] = sig[i, meas_idx[k]] - zp[k]
    for a in range(nz):
        for b in range(a, nz):
            s = 0.0
            for i in range(m):
                s += Wc[i] * dz[i, a] * dz[i, b]
            S_out[a, b] = s + R[a, b]
            S_out[b, a] = s + R[b, a]
    Pxz = np.zeros((n, nz))
    for i in range(m):
        w = Wc[i]
        for a in range(n):
            d = w * (sig[i, a] - x[a])
            for b in range(nz):
                Pxz[a, b] += d * dz[i, b]
    L = np.zeros((nz, nz))          # S = L L^T, lower
    for j in range(nz):
        s = S_out[j, j]
        for k in range(j):
            s -= L[j, k] * L[j, k]
        if not s > 0.0:
            return -1.0
        d = math.sqrt(s)
        L[j, j] = d
        for i in range(j + 1, nz):
            t = S_out[i, j]
            for k in range(j):
                t -= L[i, k] * L[j, k]
            L[i, j] = t / d
    K = np.empty((n, nz))
    u = np.empty(nz)
    for a in range(n):              # S K[a]^T = Pxz[a]^T: forward, then back substitution
        for i in range(nz):
            t = Pxz[a, i]
            for k in range(i):
                t -= L[i, k] * u[k]
            u[i] = t / L[i, i]
        for i in range(nz - 1, -1, -1):
            t = u[i]
            for k in range(i + 1, nz):
                t -= L[k, i] * K[a, k]
            K[a, i] = t / L[i, i]
    nis = 0.0
    for i in range(nz):
        y_out[i] = z[i] - zp[i]
        t = y_out[i]
        for k in range(i):
            t -= L[i, k] * u[k]
        u[i] = t / L[i, i]
        nis += u[i] * u[i]
    for a in range(n):
        s = x[a]
        for k in range(nz):
            s += K[a, k] * y_out[k]
        x_out[a] = s
        for b in range(n):
            t = 0.0
            for k in range(nz):
                t += Pxz[a, k] * K[b, k]
            P_out[a, b] = P[a, b] - t
    return nis


@_jit
def _mul_exp_normalized(q: FloatArray, a: float, b: float, c: float,
                        out: FloatArray) -> None:
    """out = q (x) Exp((a, b, c)), normalised; as ``quaternion.mul_exp_tuple``."""
    angle = math.sqrt(a * a + b * b + c * c)
    cw = math.cos(0.5 * angle)
    k = math.sin(0.5 * angle) / angle if angle > 1e-12 else 0.5
    w, x, y, z = _mul(q[0], q[1], q[2], q[3], cw, a * k, b * k, c * k)
    n = math.sqrt(w * w + x * x + y * y + z * z)
    out[0], out[1], out[2], out[3] = w / n, x / n, y / n, z / n


@_jit
def _condition(P: FloatArray, min_variance: float, max_pos_variance: float) -> None:
    """As ``Ukf._condition``, in place: symmetrise, floor the variances, cap the position."""
    n = P.shape[0]
    for a in range(n):
        for b in range(a + 1, n):
            s = 0.5 * (P[a, b] + P[b, a])
            P[a, b] = s
            P[b, a] = s
    d_min = P[0, 0]
    for a in range(n):
        d_min = min(d_min, P[a, a])
    if d_min < min_variance:
        for a in range(n):
            P[a, a] = max(P[a, a], min_variance)
    if max(P[0, 0], P[1, 1], P[2, 2]) > max_pos_variance:
        scale = np.ones(n)
        for a in range(3):
            scale[a] = math.sqrt(min(1.0, max_pos_variance / P[a, a]))
        for a in range(n):
            for b in range(n):
                P[a, b] = P[a, b] * scale[a] * scale[b]


@_jit
def _finite(x: FloatArray, P: FloatArray) -> bool:
    return math.isfinite(x.sum() + P.sum())


@_jit
def predict_step(x: FloatArray, P: FloatArray, Q: FloatArray, dt: float, gyro: FloatArray,
                 accel: FloatArray, q_ref: FloatArray, gravity_w: FloatArray, Wm: FloatArray,
                 Wc: FloatArray, scale: float, min_variance: float, max_pos_variance: float,
                 sig: FloatArray, work: FloatArray, U: FloatArray, devT: FloatArray,
                 q_tmp: FloatArray, x_out: FloatArray, P_out: FloatArray,
                 q_out: FloatArray) -> int:
    """``Ukf._propagate`` whole: the nominal attitude's step, the predict, the attitude folded
    into ``q_out`` and P conditioned. 0: done; 1: P not positive definite (nothing written);
    2: the result is not finite (before folding and conditioning, like the Python path)."""
    dt_bx, dt_by, dt_bz = (gyro[0] - x[9]) * dt, (gyro[1] - x[10]) * dt, (gyro[2] - x[11]) * dt
    _mul_exp_normalized(q_ref, dt_bx, dt_by, dt_bz, q_tmp)      # q_ref'
    q_next_inv = np.empty(4)
    q_next_inv[0] = q_tmp[0]
    q_next_inv[1], q_next_inv[2], q_next_inv[3] = -q_tmp[1], -q_tmp[2], -q_tmp[3]
    if not predict(x, P, Q, dt, gyro, accel, q_ref, q_next_inv, gravity_w, Wm, Wc, scale, sig,
                   work, U, devT, x_out, P_out):
        return 1
    _mul_exp_normalized(q_tmp, x_out[6], x_out[7], x_out[8], q_out)
    x_out[6] = x_out[7] = x_out[8] = 0.0
    if not _finite(x_out, P_out):
        return 2
    _condition(P_out, min_variance, max_pos_variance)
    return 0


@_jit
def update_step(x: FloatArray, P: FloatArray, q_ref: FloatArray, z: FloatArray, R: FloatArray,
                meas_idx: Any, Wm: FloatArray, Wc: FloatArray, scale: float,
                min_variance: float, max_pos_variance: float, sig: FloatArray,
                work: FloatArray, U: FloatArray, x_out: FloatArray, P_out: FloatArray,
                q_out: FloatArray, y_out: FloatArray, S_out: FloatArray
                ) -> tuple[int, float]:
    """``Ukf._fuse`` before its gate: the update and -> (status, NIS). Status 0: finite, the
    attitude folded into ``q_out`` and P conditioned; 1: P not positive definite (nothing
    written); 2: not finite (returned as it is, for the caller's gate to refuse)."""
    nis = update(x, P, z, R, meas_idx, Wm, Wc, scale, sig, work, U, x_out, P_out, y_out, S_out)
    if nis < 0.0:
        return 1, math.nan
    if not _finite(x_out, P_out):
        return 2, nis
    _mul_exp_normalized(q_ref, x_out[6], x_out[7], x_out[8], q_out)
    x_out[6] = x_out[7] = x_out[8] = 0.0
    _condition(P_out, min_variance, max_pos_variance)
    return 0, nis

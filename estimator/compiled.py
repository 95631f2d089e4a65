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


# -- the whole predict with the fusion horizon (``Ukf.predict``'s common path, one call) ---------
# Output-predictor rows (``ukf._OutputPredictor``): time, gyro and accelerometer inputs, and the
# output position, velocity and attitude at that time, stored without the lazy correction
# ``corr`` = (a (3), b (3), dq (4)): the output at time t is p + a + b t, v + b, dq (x) q.
ROW_T, ROW_GYRO, ROW_ACCEL, ROW_POS, ROW_VEL, ROW_Q, ROW_WIDTH = 0, 1, 4, 7, 10, 13, 17


@_jit
def process_noise(dt: float, rates: FloatArray, Q: FloatArray) -> None:
    """``Ukf._process_noise`` into Q; ``rates``: accelerometer, gyro, gyro-bias walk and
    accelerometer-bias walk variances per second (two-sided densities squared)."""
    Q[:, :] = 0.0
    qa = rates[0]
    pp, pv, vv = qa * dt ** 3 / 3.0, qa * dt ** 2 / 2.0, qa * dt
    aa, gg, bb = rates[1] * dt, rates[2] * dt, rates[3] * dt
    for i in range(3):
        Q[i, i] = pp
        Q[i, 3 + i] = Q[3 + i, i] = pv
        Q[3 + i, 3 + i] = vv
        Q[6 + i, 6 + i] = aa
        Q[9 + i, 9 + i] = gg
        Q[12 + i, 12 + i] = bb


@_jit
def _corrected_row(buf: FloatArray, r: int, corr: FloatArray, out: FloatArray) -> None:
    """out = (p, v, q) of row r with the correction applied."""
    t = buf[r, ROW_T]
    for i in range(3):
        out[i] = buf[r, ROW_POS + i] + corr[i] + corr[3 + i] * t
        out[3 + i] = buf[r, ROW_VEL + i] + corr[3 + i]
    q = ROW_Q
    out[6], out[7], out[8], out[9] = _mul(corr[6], corr[7], corr[8], corr[9], buf[r, q],
                                          buf[r, q + 1], buf[r, q + 2], buf[r, q + 3])


@_jit
def _rebase(corr: FloatArray, pv_new: FloatArray, q_new: FloatArray, pv_ref: FloatArray,
            q_ref: FloatArray, t_ref: float) -> None:
    """``Ukf._correct_outputs``: the outputs were built on (p, v, q)_ref at t_ref, the filter
    now says (p, v, q)_new there: add the difference to the lazy correction."""
    for i in range(3):
        dv = pv_new[3 + i] - pv_ref[3 + i]
        corr[i] = corr[i] + (pv_new[i] - pv_ref[i]) - dv * t_ref
        corr[3 + i] = corr[3 + i] + dv
    dw, dx, dy, dz = _mul(q_new[0], q_new[1], q_new[2], q_new[3],
                          q_ref[0], -q_ref[1], -q_ref[2], -q_ref[3])
    w, a, b, c = _mul(dw, dx, dy, dz, corr[6], corr[7], corr[8], corr[9])
    n = math.sqrt(w * w + a * a + b * b + c * c)
    corr[6], corr[7], corr[8], corr[9] = w / n, a / n, b / n, c / n


@_jit
def _reset_correction(corr: FloatArray) -> None:
    corr[:] = 0.0
    corr[6] = 1.0


@_jit
def _push_history(t: float, g: FloatArray, a: FloatArray, x: FloatArray, P: FloatArray,
                  q: FloatArray, hist_t: FloatArray, hist_x: FloatArray, hist_P: FloatArray,
                  hist_q: FloatArray, hist_gyro: FloatArray, hist_accel: FloatArray,
                  hij: Any) -> None:
    n = hist_t.shape[0]
    i = (hij[0] + 1) % n
    hij[0] = i
    hij[1] = min(hij[1] + 1, n)
    hist_t[i] = t
    hist_gyro[i, :] = g
    hist_accel[i, :] = a
    hist_x[i, :] = x
    hist_P[i, :, :] = P
    hist_q[i, :] = q
    hij[2] += 1             # filter steps taken in compiled code (Ukf.filter_steps)


@_jit
def _step(x: FloatArray, P: FloatArray, q_ref: FloatArray, dt: float, g: FloatArray,
          a: FloatArray, rates: FloatArray, Q: FloatArray, gravity_w: FloatArray,
          Wm: FloatArray, Wc: FloatArray, scale: float, min_variance: float,
          max_pos_variance: float, sig: FloatArray, work: FloatArray, U: FloatArray,
          devT: FloatArray, q_tmp: FloatArray, x_out: FloatArray, P_out: FloatArray,
          q_out: FloatArray) -> int:
    """One filter predict (``Ukf._filter_step``), written into x, P, q_ref when it succeeds."""
    dt = round(dt, 9)       # as Ukf._propagate: the repeated IMU period, to the nanosecond
    process_noise(dt, rates, Q)
    st = predict_step(x, P, Q, dt, g, a, q_ref, gravity_w, Wm, Wc, scale, min_variance,
                      max_pos_variance, sig, work, U, devT, q_tmp, x_out, P_out, q_out)
    if st != 0:
        return st
    x[:] = x_out
    P[:, :] = P_out
    q_ref[:] = q_out
    return 0


@_jit
def horizon_predict(t: float, dt: float, inp: FloatArray, target_t: float,
                    direct: bool, t_filter: float, x: FloatArray, P: FloatArray,
                    q_ref: FloatArray, buf: FloatArray, ij: Any, corr: FloatArray,
                    gravity_m_s2: float, hist_t: FloatArray, hist_x: FloatArray,
                    hist_P: FloatArray, hist_q: FloatArray, hist_gyro: FloatArray,
                    hist_accel: FloatArray, hij: Any, rates: FloatArray, Q: FloatArray,
                    gravity_w: FloatArray, Wm: FloatArray, Wc: FloatArray, scale: float,
                    min_variance: float, max_pos_variance: float, sig: FloatArray,
                    work: FloatArray, U: FloatArray, devT: FloatArray, q_tmp: FloatArray,
                    x_out: FloatArray, P_out: FloatArray, q_out: FloatArray,
                    newest: FloatArray, fobs: FloatArray, fconst: FloatArray
                    ) -> tuple[int, float]:
    """``Ukf.predict`` after its input checks, for a finite filter and a queue with room:
    ``direct`` (no horizon, empty queue) one filter step to t; else queue the input with its
    output state and feed the filter every queued input up to ``target_t``, then re-base the
    outputs on it. x, P, q_ref, the queue and the history ring are updated in place.

    -> (status, filter time). Status 0: done. 1 (P not positive definite) or 2 (a non-finite
    result): the step of the queue's oldest input (of t when ``direct``) was not taken and
    nothing of it is written; the outputs are re-based on the steps taken; the caller takes
    it from there (its repair and non-finite paths). ``newest`` = the output (p, v, q) at the
    newest input, valid with status 0.

    ``inp``: the filter's gyro and accelerometer inputs (3 + 3), the raw accelerometer sample
    (3), the commanded body force (3), whether one was given (1.0) and whether the force
    observer runs (1.0); with status 0 the observer is updated (``observe_force``)."""
    g_in, a_in = inp[0:3], inp[3:6]
    st, t_filter = _horizon(t, dt, g_in, a_in, target_t, direct, t_filter, x, P, q_ref, buf, ij,
                            corr, gravity_m_s2, hist_t, hist_x, hist_P, hist_q, hist_gyro,
                            hist_accel, hij, rates, Q, gravity_w, Wm, Wc, scale, min_variance,
                            max_pos_variance, sig, work, U, devT, q_tmp, x_out, P_out, q_out,
                            newest)
    if st == 0 and inp[13] != 0.0:
        observe_force(dt, inp, x, P, newest, fobs, fconst)
    return st, t_filter


@_jit
def observe_force(dt: float, inp: FloatArray, x: FloatArray, P: FloatArray,
                  newest: FloatArray, fobs: FloatArray, fconst: FloatArray) -> None:
    """``Ukf._observe_force``: ``fobs`` = estimate (3), variance, lagged command (3), lagged
    command set; ``fconst`` = force walk variance rate, mass, command lag, accelerometer
    variance rate; the attitude is the newest output's (``newest[6:10]``)."""
    fobs[3] += fconst[0] * dt
    if inp[12] == 0.0:
        return
    fx, fy, fz = inp[9], inp[10], inp[11]
    if not math.isfinite(fx + fy + fz):
        return
    lag = fconst[2]
    if lag > 0.0:
        if fobs[7] == 0.0:
            fobs[4], fobs[5], fobs[6], fobs[7] = fx, fy, fz, 1.0
        else:   # exact discretisation of the first-order lag over dt
            blend = 1.0 - math.exp(-dt / lag)
            px, py, pz = fobs[4], fobs[5], fobs[6]
            fobs[4], fobs[5], fobs[6] = (px + blend * (fx - px), py + blend * (fy - py),
                                         pz + blend * (fz - pz))
        fx, fy, fz = fobs[4], fobs[5], fobs[6]
    m = fconst[1]
    a, b, c = (m * (inp[6] - x[12]) - fx, m * (inp[7] - x[13]) - fy,
               m * (inp[8] - x[14]) - fz)
    w, qx, qy, qz = newest[6], newest[7], newest[8], newest[9]
    tx, ty, tz = 2.0 * (qy * c - qz * b), 2.0 * (qz * a - qx * c), 2.0 * (qx * b - qy * a)
    zx = a + w * tx + (qy * tz - qz * ty)
    zy = b + w * ty + (qz * tx - qx * tz)
    zz = c + w * tz + (qx * ty - qy * tx)
    r = m * m * (fconst[3] / dt + (P[12, 12] + P[13, 13] + P[14, 14]) / 3.0)
    var = fobs[3]
    gain = var / (var + r)
    wx, wy, wz = fobs[0], fobs[1], fobs[2]
    fobs[0], fobs[1], fobs[2] = wx + gain * (zx - wx), wy + gain * (zy - wy), wz + gain * (zz - wz)
    fobs[3] = var * (1.0 - gain)


@_jit
def _horizon(t: float, dt: float, g_in: FloatArray, a_in: FloatArray, target_t: float,
             direct: bool, t_filter: float, x: FloatArray, P: FloatArray, q_ref: FloatArray,
             buf: FloatArray, ij: Any, corr: FloatArray, gravity_m_s2: float,
             hist_t: FloatArray, hist_x: FloatArray, hist_P: FloatArray, hist_q: FloatArray,
             hist_gyro: FloatArray, hist_accel: FloatArray, hij: Any, rates: FloatArray,
             Q: FloatArray, gravity_w: FloatArray, Wm: FloatArray, Wc: FloatArray,
             scale: float, min_variance: float, max_pos_variance: float, sig: FloatArray,
             work: FloatArray, U: FloatArray, devT: FloatArray, q_tmp: FloatArray,
             x_out: FloatArray, P_out: FloatArray, q_out: FloatArray, newest: FloatArray
             ) -> tuple[int, float]:
    if direct:
        st = _step(x, P, q_ref, dt, g_in, a_in, rates, Q, gravity_w, Wm, Wc, scale,
                   min_variance, max_pos_variance, sig, work, U, devT, q_tmp, x_out, P_out,
                   q_out)
        if st != 0:
            return st, t_filter
        _push_history(t, g_in, a_in, x, P, q_ref, hist_t, hist_x, hist_P, hist_q, hist_gyro,
                      hist_accel, hij)
        for i in range(6):
            newest[i] = x[i]
        for i in range(4):
            newest[6 + i] = q_ref[i]
        return 0, t
    cap = buf.shape[0]
    head, count = ij[0], ij[1]
    # queue the input with the output state propagated to t (ukf._OutputPredictor.push)
    if count == 0:
        _reset_correction(corr)
        for i in range(6):
            newest[i] = x[i]
        for i in range(4):
            newest[6 + i] = q_ref[i]
    else:
        _corrected_row(buf, (head + count - 1) % cap, corr, newest)
    qw, qx, qy, qz = newest[6], newest[7], newest[8], newest[9]
    sa, sb, sc = a_in[0] - x[12], a_in[1] - x[13], a_in[2] - x[14]
    tx, ty, tz = 2.0 * (qy * sc - qz * sb), 2.0 * (qz * sa - qx * sc), 2.0 * (qx * sb - qy * sa)
    ax = sa + qw * tx + (qy * tz - qz * ty)
    ay = sb + qw * ty + (qz * tx - qx * tz)
    az = sc + qw * tz + (qx * ty - qy * tx) - gravity_m_s2
    h = 0.5 * dt * dt
    r = (head + count) % cap
    buf[r, ROW_T] = t
    for i in range(3):
        buf[r, ROW_GYRO + i] = g_in[i]
        buf[r, ROW_ACCEL + i] = a_in[i]
    acc = (ax, ay, az)
    for i in range(3):
        buf[r, ROW_POS + i] = newest[i] + dt * newest[3 + i] + h * acc[i] - corr[i] \
            - corr[3 + i] * t
        buf[r, ROW_VEL + i] = newest[3 + i] + dt * acc[i] - corr[3 + i]
    _mul_exp_normalized(newest[6:10], (g_in[0] - x[9]) * dt, (g_in[1] - x[10]) * dt,
                        (g_in[2] - x[11]) * dt, q_tmp)
    q = ROW_Q
    buf[r, q], buf[r, q + 1], buf[r, q + 2], buf[r, q + 3] = _mul(
        corr[6], -corr[7], -corr[8], -corr[9], q_tmp[0], q_tmp[1], q_tmp[2], q_tmp[3])
    ij[1] = count + 1
    return _advance(target_t, t_filter, x, P, q_ref, buf, ij, corr, hist_t, hist_x, hist_P,
                    hist_q, hist_gyro, hist_accel, hij, rates, Q, gravity_w, Wm, Wc, scale,
                    min_variance, max_pos_variance, sig, work, U, devT, q_tmp, x_out, P_out,
                    q_out, newest)


@_jit
def _advance(target_t: float, t_filter: float, x: FloatArray, P: FloatArray,
             q_ref: FloatArray, buf: FloatArray, ij: Any, corr: FloatArray,
             hist_t: FloatArray, hist_x: FloatArray, hist_P: FloatArray, hist_q: FloatArray,
             hist_gyro: FloatArray, hist_accel: FloatArray, hij: Any, rates: FloatArray,
             Q: FloatArray, gravity_w: FloatArray, Wm: FloatArray, Wc: FloatArray,
             scale: float, min_variance: float, max_pos_variance: float, sig: FloatArray,
             work: FloatArray, U: FloatArray, devT: FloatArray, q_tmp: FloatArray,
             x_out: FloatArray, P_out: FloatArray, q_out: FloatArray, newest: FloatArray
             ) -> tuple[int, float]:
    """``Ukf._advance_filter``: feed the filter every queued input up to ``target_t``, then
    re-base the outputs on it; ``newest`` = the output at the newest input (status 0).
    -> (status, filter time), status as :func:`horizon_predict`'s."""
    cap = buf.shape[0]
    head, count = ij[0], ij[1]
    last = -1
    st = 0
    while count > 0 and buf[head, ROW_T] <= target_t + 1e-9:
        te = buf[head, ROW_T]
        st = _step(x, P, q_ref, te - t_filter, buf[head, ROW_GYRO:ROW_GYRO + 3],
                   buf[head, ROW_ACCEL:ROW_ACCEL + 3], rates, Q, gravity_w, Wm, Wc, scale,
                   min_variance, max_pos_variance, sig, work, U, devT, q_tmp, x_out, P_out,
                   q_out)
        if st != 0:
            break
        _push_history(te, buf[head, ROW_GYRO:ROW_GYRO + 3], buf[head, ROW_ACCEL:ROW_ACCEL + 3],
                      x, P, q_ref, hist_t, hist_x, hist_P, hist_q, hist_gyro, hist_accel, hij)
        t_filter = te
        last = head
        head = (head + 1) % cap
        count -= 1
    ij[0], ij[1] = head, count
    if last >= 0:
        # re-base the outputs (Ukf._correct_outputs): the output at the filter's time is the
        # filter's state (the row is still in the buffer, only popped)
        if count == 0:
            _reset_correction(corr)
        else:
            _corrected_row(buf, last, corr, newest)
            _rebase(corr, x, q_ref, newest[0:6], newest[6:10], buf[last, ROW_T])
    if count == 0:
        for i in range(6):
            newest[i] = x[i]
        for i in range(4):
            newest[6 + i] = q_ref[i]
    else:
        _corrected_row(buf, (head + count - 1) % cap, corr, newest)
    return st, t_filter


@_jit
def advance(target_t: float, t_filter: float, x: FloatArray, P: FloatArray,
            q_ref: FloatArray, buf: FloatArray, ij: Any, corr: FloatArray,
            hist_t: FloatArray, hist_x: FloatArray, hist_P: FloatArray, hist_q: FloatArray,
            hist_gyro: FloatArray, hist_accel: FloatArray, hij: Any, rates: FloatArray,
            Q: FloatArray, gravity_w: FloatArray, Wm: FloatArray, Wc: FloatArray,
            scale: float, min_variance: float, max_pos_variance: float, sig: FloatArray,
            work: FloatArray, U: FloatArray, devT: FloatArray, q_tmp: FloatArray,
            x_out: FloatArray, P_out: FloatArray, q_out: FloatArray, newest: FloatArray
            ) -> tuple[int, float]:
    """``Ukf._advance_filter`` in one call (a pose that brings the filter to its capture
    time): see :func:`_advance`."""
    return _advance(target_t, t_filter, x, P, q_ref, buf, ij, corr, hist_t, hist_x, hist_P,
                    hist_q, hist_gyro, hist_accel, hij, rates, Q, gravity_w, Wm, Wc, scale,
                    min_variance, max_pos_variance, sig, work, U, devT, q_tmp, x_out, P_out,
                    q_out, newest)


@_jit
def _gated_pose_update(pos: FloatArray, q_m: FloatArray, dt_s: float, gyro: FloatArray,
                       x: FloatArray, P: FloatArray, q_ref: FloatArray, R: FloatArray,
                       meas_idx: Any, gate_nis: float, Wm: FloatArray, Wc: FloatArray,
                       scale: float, min_variance: float, max_pos_variance: float,
                       sig: FloatArray, work: FloatArray, U: FloatArray, x_out: FloatArray,
                       P_out: FloatArray, q_out: FloatArray, y: FloatArray, S: FloatArray,
                       z: FloatArray, pose_out: FloatArray) -> tuple[int, float]:
    """``Ukf._shift_pose`` by ``dt_s`` (0: none) with the rate ``gyro`` of the state (x, q_ref),
    then ``Ukf._fuse``: the update of the state into x_out, P_out, q_out and its gate.
    -> (status, NIS): 0 accepted, 1 P not positive definite, 2 refused by the gate or not
    finite. ``pose_out`` = the pose as fused or refused (p, q)."""
    for i in range(3):
        pose_out[i] = pos[i]
    for i in range(4):
        pose_out[3 + i] = q_m[i]
    if abs(dt_s) > 1e-9:
        for i in range(3):
            pose_out[i] = pos[i] + dt_s * x[3 + i]
        _mul_exp_normalized(q_m, dt_s * (gyro[0] - x[9]), dt_s * (gyro[1] - x[10]),
                            dt_s * (gyro[2] - x[11]), pose_out[3:7])
    # z = (p, Log(q_ref^-1 (x) q)), as quaternion.log_relative_single
    w, a, b, c = q_ref[0], q_ref[1], q_ref[2], q_ref[3]
    bw, bx, by, bz = pose_out[3], pose_out[4], pose_out[5], pose_out[6]
    rw = w * bw + a * bx + b * by + c * bz
    rx = w * bx - a * bw - b * bz + c * by
    ry = w * by + a * bz - b * bw - c * bx
    rz = w * bz - a * by + b * bx - c * bw
    s = math.sqrt(rx * rx + ry * ry + rz * rz)
    for i in range(3):
        z[i] = pose_out[i]
    if s == 0.0:
        z[3] = z[4] = z[5] = 0.0
    else:
        f = 2.0 * math.atan2(s, abs(rw)) / s * (1.0 if rw >= 0.0 else -1.0)
        z[3], z[4], z[5] = rx * f, ry * f, rz * f
    st, nis = update_step(x, P, q_ref, z, R, meas_idx, Wm, Wc, scale, min_variance,
                          max_pos_variance, sig, work, U, x_out, P_out, q_out, y, S)
    if st == 1:
        return 1, nis
    if st == 2 or not nis <= gate_nis:
        return 2, nis
    return 0, nis


@_jit
def fuse_now(t_c: float, pos: FloatArray, q_m: FloatArray, shift: bool, t_filter: float,
             x: FloatArray, P: FloatArray, q_ref: FloatArray, R: FloatArray, meas_idx: Any,
             gate_nis: float, hist_x: FloatArray, hist_P: FloatArray, hist_q: FloatArray,
             hist_gyro: FloatArray, hij: Any, buf: FloatArray, ij: Any, corr: FloatArray,
             Wm: FloatArray, Wc: FloatArray, scale: float, min_variance: float,
             max_pos_variance: float, sig: FloatArray, work: FloatArray, U: FloatArray,
             x_out: FloatArray, P_out: FloatArray, q_out: FloatArray, y: FloatArray,
             S: FloatArray, z: FloatArray, pose_out: FloatArray, newest: FloatArray
             ) -> tuple[int, float]:
    """``Ukf._fuse_now`` in one call, for a finite filter: the pose moved to the filter's
    time (``shift``), the gated update, the history entry rewritten and the outputs re-based.

    -> (status, NIS). 0: fused (x, P, q_ref, the history head and the correction updated);
    1: P not positive definite, nothing written (the caller repairs); 2: refused by the gate
    or not finite, nothing written. ``pose_out`` = the pose as fused or refused (p, q)."""
    head = hij[0]
    st, nis = _gated_pose_update(pos, q_m, t_filter - t_c if shift else 0.0, hist_gyro[head],
                                 x, P, q_ref, R, meas_idx, gate_nis, Wm, Wc, scale,
                                 min_variance, max_pos_variance, sig, work, U, x_out, P_out,
                                 q_out, y, S, z, pose_out)
    if st != 0:
        return st, nis
    # the outputs were built on the filter's state before the update (Ukf._correct_outputs)
    head_q, count = ij[0], ij[1]
    if count > 0:
        _rebase(corr, x_out, q_out, x, q_ref, t_filter)
        _corrected_row(buf, (head_q + count - 1) % buf.shape[0], corr, newest)
    x[:] = x_out
    P[:, :] = P_out
    q_ref[:] = q_out
    hist_x[head, :] = x
    hist_P[head, :, :] = P
    hist_q[head, :] = q_ref
    return 0, nis


@_jit
def fuse_in_past(t_c: float, pos: FloatArray, q_m: FloatArray, t_filter: float,
                 x: FloatArray, P: FloatArray, q_ref: FloatArray, R: FloatArray,
                 meas_idx: Any, gate_nis: float, hist_t: FloatArray, hist_x: FloatArray,
                 hist_P: FloatArray, hist_q: FloatArray, hist_gyro: FloatArray,
                 hist_accel: FloatArray, hij: Any, buf: FloatArray, ij: Any,
                 corr: FloatArray, rates: FloatArray, Q: FloatArray, gravity_w: FloatArray,
                 Wm: FloatArray, Wc: FloatArray, scale: float, min_variance: float,
                 max_pos_variance: float, sig: FloatArray, work: FloatArray, U: FloatArray,
                 devT: FloatArray, q_tmp: FloatArray, x_out: FloatArray, P_out: FloatArray,
                 q_out: FloatArray, y: FloatArray, S: FloatArray, z: FloatArray,
                 pose_out: FloatArray, newest: FloatArray, xs: FloatArray, Ps: FloatArray,
                 qs: FloatArray, bak_x: FloatArray, bak_P: FloatArray, bak_q: FloatArray
                 ) -> tuple[int, float]:
    """``Ukf._fuse_in_past`` in one call, for a finite filter: rewind the history to the IMU
    sample nearest ``t_c``, fuse the pose moved to that sample (gated), replay the newer
    inputs rewriting the history, make the result the filter's state and re-base the outputs.

    -> (status, NIS). 0: fused; 1: P not positive definite or a non-finite replay step,
    nothing written (the history restored): the Python path takes the pose from the start;
    2: refused by the gate or not finite, nothing written, ``pose_out`` = the pose as
    refused (p, q); 3: older than the history, nothing written. ``xs``, ``Ps``, ``qs`` are
    scratch for the replayed state, ``bak_*`` (history-sized) for the entries it rewrites."""
    n = hist_t.shape[0]
    head, hlen = hij[0], hij[1]
    k = 0
    while k < hlen and hist_t[(head - k) % n] > t_c:
        k += 1
    if k >= hlen:
        return 3, math.nan
    j = (head - k) % n
    if k > 0 and hist_t[(j + 1) % n] - t_c < t_c - hist_t[j]:
        k -= 1                              # the next sample is nearer the capture time
        j = (j + 1) % n
    for i in range(x.shape[0]):
        xs[i] = hist_x[j, i]
    Ps[:, :] = hist_P[j]
    for i in range(4):
        qs[i] = hist_q[j, i]
    st, nis = _gated_pose_update(pos, q_m, hist_t[j] - t_c, hist_gyro[j], xs, Ps, qs, R,
                                 meas_idx, gate_nis, Wm, Wc, scale, min_variance,
                                 max_pos_variance, sig, work, U, x_out, P_out, q_out, y, S, z,
                                 pose_out)
    if st != 0:
        return st, nis
    for m in range(k + 1):                  # the entries the replay rewrites, j .. head
        i = (j + m) % n
        bak_x[m, :] = hist_x[i]
        bak_P[m, :, :] = hist_P[i]
        bak_q[m, :] = hist_q[i]
    xs[:] = x_out
    Ps[:, :] = P_out
    qs[:] = q_out
    hist_x[j, :] = xs
    hist_P[j, :, :] = Ps
    hist_q[j, :] = qs
    replayed = 0
    while k > 0:
        k -= 1
        i = (head - k) % n
        st = _step(xs, Ps, qs, hist_t[i] - hist_t[(i - 1) % n], hist_gyro[i], hist_accel[i],
                   rates, Q, gravity_w, Wm, Wc, scale, min_variance, max_pos_variance, sig,
                   work, U, devT, q_tmp, x_out, P_out, q_out)
        if st != 0:                         # the Python path stores what it gets: hand over
            for m in range(replayed + 1):
                r = (j + m) % n
                hist_x[r, :] = bak_x[m]
                hist_P[r, :, :] = bak_P[m]
                hist_q[r, :] = bak_q[m]
            return 1, nis
        hist_x[i, :] = xs
        hist_P[i, :, :] = Ps
        hist_q[i, :] = qs
        replayed += 1
    hij[2] += replayed                      # replays count as filter steps (Ukf.filter_steps)
    head_q, count = ij[0], ij[1]
    if count > 0:                           # the outputs were built on the old filter state
        _rebase(corr, xs, qs, x, q_ref, t_filter)
        _corrected_row(buf, (head_q + count - 1) % buf.shape[0], corr, newest)
    x[:] = xs
    P[:, :] = Ps
    q_ref[:] = qs
    return 0, nis


#: the columns of one pose of :class:`estimator.consistency.ConsistencyMonitor`: t, the
#: position, c (4) and u (3)
POSE_WIDTH = 11


@_jit
def window_stats(poses: FloatArray, lo: int, hi: int, out: FloatArray) -> None:
    """The statistics of the MoCap/IMU monitor's window over the rows ``lo:hi`` of ``poses``
    (:class:`estimator.consistency.ConsistencyMonitor`: one pose a row, :data:`POSE_WIDTH`
    columns t, p, c, u) into ``out`` (11): the mean of c (normalised, signs aligned to the
    first row's), the mean time, the mean of u, and MoCap's velocity (the least-squares slope
    of p: the velocity at the mean time). No fast-math: compiled and interpreted, the same bits
    (tested)."""
    n = hi - lo
    c0w, c0x, c0y, c0z = poses[lo, 4], poses[lo, 5], poses[lo, 6], poses[lo, 7]
    sw = sx = sy = sz = st = sux = suy = suz = spx = spy = spz = 0.0
    for i in range(lo, hi):
        cw, cx, cy, cz = poses[i, 4], poses[i, 5], poses[i, 6], poses[i, 7]
        if cw * c0w + cx * c0x + cy * c0y + cz * c0z >= 0.0:
            sw += cw
            sx += cx
            sy += cy
            sz += cz
        else:
            sw -= cw
            sx -= cx
            sy -= cy
            sz -= cz
        st += poses[i, 0]
        sux += poses[i, 8]
        suy += poses[i, 9]
        suz += poses[i, 10]
        spx += poses[i, 1]
        spy += poses[i, 2]
        spz += poses[i, 3]
    norm = math.sqrt(sw * sw + sx * sx + sy * sy + sz * sz)
    tm = st / n
    mx, my, mz = spx / n, spy / n, spz / n
    stt = vx = vy = vz = 0.0
    for i in range(lo, hi):
        d = poses[i, 0] - tm
        stt += d * d
        vx += d * (poses[i, 1] - mx)
        vy += d * (poses[i, 2] - my)
        vz += d * (poses[i, 3] - mz)
    out[0], out[1], out[2], out[3] = sw / norm, sx / norm, sy / norm, sz / norm
    out[4] = tm
    out[5], out[6], out[7] = sux / n, suy / n, suz / n
    out[8], out[9], out[10] = vx / stt, vy / stt, vz / stt

"""The 500 Hz error-state UKF fusing the IMU with late MoCap poses.

One instance serves the control loop::

    est = Ukf(EstimatorConfig())
    est.predict(imu_t_s, gyro_rad_s, accel_m_s2, force_cmd_b_n)  # every IMU sample
    est.update_pose(capture_t_s, pos_w_m, q_wb)                  # every new MoCap frame
    state = est.estimate()                                       # every tick

Timeline and delay compensation (PX4 EKF2's delayed fusion horizon, pom's history): the filter
runs ``fusion_delay_s`` behind the newest IMU sample, about the smallest MoCap latency of the
last ``latency_window`` poses (the lowest eighth of them left out, see
:data:`HORIZON_LOW_OUTLIERS`; at most ``max_fusion_delay_s``). IMU inputs newer than the filter
wait in a queue; an output predictor integrates them (mean only, the same model) so that
:meth:`Ukf.estimate` is always at the newest sample. A pose captured at ``t_c`` arrives when
the filter is at or just before ``t_c``: the filter takes the queued inputs up to the IMU
sample nearest ``t_c`` and fuses the pose there, moved to that sample's time with the
velocity and rate (at most half an IMU period). No IMU sample is integrated twice, so a late
pose costs one update instead of replaying its age in predicts. Whenever the filter moves,
the queued outputs are re-based on it exactly (to first order), not smoothed as EKF2 does.
A pose older than the filter (a latency above the horizon) is fused in the filter's own
history: every predict appends its state and input to a ring covering ``history_s``, the
ring is rewound to the sample nearest ``t_c``, the pose is fused and the remaining inputs are
replayed, rewriting the ring (robot_localization style). Older than the ring: dropped, counted.
With ``max_fusion_delay_s = 0`` the filter stays at the newest sample and every late pose is
replayed; the tests check that both give the same estimate to a few micrometres.

Robustness: a chi-square gate on the 6-D innovation skips an update (counted); after
``max_consecutive_rejections`` in a row the position and attitude are re-seeded from MoCap
(a marker swap that stays). P is symmetrised and its diagonal floored after every step; a
failed Cholesky is repaired by clipping the eigenvalues (counted). Without poses the filter dead
reckons on the IMU and P grows; health flags report it (:class:`~estimator.types.HealthFlag`).

Initialisation: the first ``init_rest_s`` of IMU samples with at least ``init_min_poses`` poses,
the vehicle at rest, give the gyro bias (mean gyro), the accelerometer bias (mean specific force
minus gravity seen in the MoCap attitude), the position and the attitude.

External-force observer: with ``force_observer`` on and the controller's commanded body force
given to :meth:`Ukf.predict`, ``m R (accel - b_a) - R F_cmd`` is an instantaneous measurement of
the unmodelled force in the world frame; a random-walk Kalman state filters it. It is kept out of
the 15-state UKF on purpose: the accelerometer already drives the kinematic prediction there, and
fusing the same samples a second time would count their noise twice. "Unmodelled" includes the
rotors' own deviation from the thrust model (spread of c_f, misalignment), which looks exactly
like an external pull; both are what the controller's ``force_feedforward`` should cancel
(``StateEstimate.force_ext_w_n`` -> ``GeometricController.step(..., force_ext_w_n=)``).
"""

from __future__ import annotations

import collections
import copy
import enum
import math
from collections.abc import Iterable, Sequence
from typing import Literal, NamedTuple

import numpy as np
import numpy.typing as npt

from . import compiled
from .config import TWO_SIDED, EstimatorConfig
from .kernels import CompiledKernel, FastKernel, FilterpyKernel, Kernel
from .quaternion import (
    QuatTuple,
    Vec3Tuple,
    conj_tuple,
    log_relative_single,
    mul_exp_single,
    mul_exp_tuple,
    mul_tuple,
    normalized_tuple,
    quat_conj,
    quat_normalize,
    quat_to_rot,
    rotate_tuple,
)
from .types import (
    ACCEL_BIAS,
    ATT,
    GYRO_BIAS,
    POS,
    STATE_DIM,
    VEL,
    EstimatorHealth,
    HealthFlag,
    StateEstimate,
)

FloatArray = npt.NDArray[np.float64]
ArrayLike = npt.ArrayLike

_TIME_EPS_S = 1e-9

HORIZON_LOW_OUTLIERS = 0.125
"""The share of the latency window the fusion horizon leaves out at the low end.

A pose can look less late than it was: one read just after a delayed IMU sample is measured
against that older sample. Were the horizon the smallest latency of the window, that one pose
would pull it down for a whole window (0.32 s at 100 Hz) and send every other pose of it,
about an IMU period later than the horizon, through a replay of its age (at 1 kHz a realtime
flight saw a 9.0 ms outlier among 11.0 ms latencies). Poses below the horizon cost nothing
extra: the filter takes the queued inputs up to their capture time, which it would take on
the next ticks anyway. With a window under 8 poses the horizon is the smallest latency.
"""


#: :meth:`Ukf.dead_reckon_from` takes a bias from now where the checkpoint's variance of it was
#: this many times larger (4: twice the sigma; seen: 5x the sigma at arming, 1.1x later on)
BIAS_UNSETTLED_VAR_RATIO = 4.0
#: a re-seed (poses refused too often in a row) takes the velocity from MoCap too when the IMU
#: was seen failing (:meth:`Ukf.note_imu_anomaly`) since this long before the first refused
#: pose: the refusals then come from motion the IMU missed (an impact beyond the I frame's
#: range: seen, a 1.05 m/s touchdown left 0.53 m/s in the estimate, and a re-seed that kept
#: it refused the next poses at once, three times in 0.6 s)
IMU_ANOMALY_MARGIN_S = 0.3
#: the MoCap velocity at a re-seed: the slope of the refused poses of this last stretch (10
#: poses at 100 Hz: about 1 cm/s of noise at 0.5 mm per pose); at least 3 poses
RESEED_VELOCITY_WINDOW_S = 0.1


class ResetInfo(NamedTuple):
    """What the last re-seed from MoCap saw (:attr:`Ukf.last_reset`)."""

    t_s: float
    """Capture time of the pose it re-seeded on."""
    streak_start_s: float
    """Capture time of the first refused pose of the run that ended in it."""
    vel_est_w_m_s: Vec3Tuple
    """The filter's velocity just before (the IMU's account of the motion)."""
    vel_mocap_w_m_s: Vec3Tuple | None
    """The refused poses' velocity (:data:`RESEED_VELOCITY_WINDOW_S`); None: too few poses."""
    imu_suspect: bool
    """The IMU was seen failing around the refusals: the velocity was taken from MoCap."""
    imu_missed_motion: bool
    """... and in a way that surely missed motion (an impact beyond the link's range), not
    only lost or corrupted samples."""

    @property
    def velocity_gap_m_s(self) -> float:
        """How far the IMU's and the MoCap's velocities differ (NaN without a MoCap one)."""
        if self.vel_mocap_w_m_s is None:
            return math.nan
        return math.dist(self.vel_est_w_m_s, self.vel_mocap_w_m_s)


class UkfCheckpoint(NamedTuple):
    """A copy of a filter's state (:meth:`Ukf.checkpoint`)."""

    t_s: float
    """The newest IMU sample's time then (s)."""
    state: dict[str, object]


#: left out of a checkpoint: configuration and constants, the kernels (stateless), the history
#: ring (no pose is fused into the past of a dead reckoning), the start-up collector and the
#: counters of what happened (they go on counting)
_CHECKPOINT_SKIP = frozenset({
    "cfg", "_gravity_w", "kernel_name", "_step_kernel", "_kernel", "_R", "_diag",
    "_hist_t", "_hist_x", "_hist_P", "_hist_q", "_hist_gyro", "_hist_accel", "_steps_py",
    "_fobs_const", "_noise_rates", "_horizon_rank", "_rest", "_accepted", "_rejected",
    "_too_old", "_resets", "_repairs", "_imu_out_of_order", "_imu_invalid", "_poses_invalid",
    "_last_nis", "_refused", "last_reset", "_imu_anomaly_t_s", "_imu_missed_t_s"})


class PoseVerdict(enum.Enum):
    """What :meth:`Ukf.update_pose` did with a pose."""

    ACCEPTED = "accepted"
    REJECTED = "rejected"            # failed the Mahalanobis gate
    RESET = "reset"                  # rejected once too often: position/attitude re-seeded
    TOO_OLD = "too_old"              # captured before the history window
    INVALID = "invalid"              # non-finite values or a degenerate quaternion
    INITIALIZING = "initializing"    # collected for the rest-period initialisation


class _RestCollector:
    """Running sums over the rest period that starts the filter."""

    def __init__(self) -> None:
        self.clear()

    def clear(self) -> None:
        self.t_first_s = math.nan
        self.n_imu = 0
        self.gyro_sum = np.zeros(3)
        self.gyro_sq = np.zeros(3)
        self.accel_sum = np.zeros(3)
        self.accel_sq = np.zeros(3)
        self.n_pose = 0
        self.pos_sum = np.zeros(3)
        self.pos_min = np.full(3, np.inf)
        self.pos_max = np.full(3, -np.inf)
        self.q_sum = np.zeros(4)

    def add_imu(self, t_s: float, gyro: FloatArray, accel: FloatArray) -> None:
        if self.n_imu == 0:
            self.t_first_s = t_s
        self.n_imu += 1
        self.gyro_sum += gyro
        self.gyro_sq += gyro * gyro
        self.accel_sum += accel
        self.accel_sq += accel * accel

    def add_pose(self, pos: FloatArray, q: FloatArray) -> None:
        self.n_pose += 1
        self.pos_sum += pos
        np.minimum(self.pos_min, pos, out=self.pos_min)
        np.maximum(self.pos_max, pos, out=self.pos_max)
        # q and -q are the same attitude: align signs before averaging (small spread at rest).
        self.q_sum += q if self.n_pose == 1 or float(q @ self.q_sum) >= 0.0 else -q

    @staticmethod
    def std(total: FloatArray, sq: FloatArray, n: int) -> float:
        mean = total / n
        return float(np.sqrt(np.max(np.maximum(sq / n - mean * mean, 0.0))))


# -- the output predictor, in plain floats (a few numpy calls on 3-vectors cost more) ----------
class _Pending(NamedTuple):
    """One IMU input the filter has not taken yet, and the output state at its time (stored
    without the correction of :class:`_OutputPredictor`)."""

    t_s: float
    gyro_in: FloatArray
    accel_in: FloatArray
    pos: Vec3Tuple
    vel: Vec3Tuple
    q: QuatTuple


class _OutputPredictor:
    """The queued inputs newer than the filter's time and the output state at each.

    Corrections (the filter's state minus the output at the filter's time, see
    :meth:`Ukf._correct_outputs`) are accumulated lazily instead of rewriting every entry:
    the true output at time t is ``p + a + b t``, ``v + b``, ``dq (x) q`` of the stored one.
    The queue is a ring of rows (:data:`compiled.ROW_WIDTH` floats: time, inputs, stored
    output) and the correction an array (a, b, dq), so that the compiled predict
    (:func:`compiled.horizon_predict`) works on the same storage as these methods.
    """

    def __init__(self, gravity_m_s2: float, capacity: int) -> None:
        self._g = gravity_m_s2
        self._capacity = capacity
        self.buf = np.zeros((capacity, compiled.ROW_WIDTH))
        self.ij = np.zeros(2, dtype=np.int64)      # head (oldest row), count
        self.corr = np.zeros(10)                    # a (3), b (3), dq (4)
        self.corr[6] = 1.0
        # the corrected newest output, kept until the queue or the correction changes
        self._newest: tuple[Vec3Tuple, Vec3Tuple, QuatTuple] | None = None

    def _reset(self) -> None:
        self.corr[:] = 0.0
        self.corr[6] = 1.0

    def __bool__(self) -> bool:
        return self.ij.item(1) > 0

    def __len__(self) -> int:
        return self.ij.item(1)

    def full(self) -> bool:
        return self.ij.item(1) >= self._capacity

    def clear(self) -> None:
        self.ij[1] = 0
        self._reset()
        self._newest = None

    def oldest_t_s(self) -> float:
        head, count = self.ij.tolist()
        return self.buf.item(head, 0) if count else math.inf

    def popleft(self) -> _Pending:
        head, count = self.ij.tolist()
        if not count:
            raise IndexError("pop from an empty output predictor")
        r = self.buf[head].tolist()
        self.ij[0], self.ij[1] = (head + 1) % self._capacity, count - 1
        self._newest = None
        return _Pending(r[0], np.array(r[1:4]), np.array(r[4:7]), (r[7], r[8], r[9]),
                        (r[10], r[11], r[12]), (r[13], r[14], r[15], r[16]))

    def corrected(self, e: _Pending) -> tuple[Vec3Tuple, Vec3Tuple, QuatTuple]:
        return self._corrected(e.t_s, e.pos, e.vel, e.q)

    def _corrected(self, t: float, p: Sequence[float], v: Sequence[float],
                   q: Sequence[float]) -> tuple[Vec3Tuple, Vec3Tuple, QuatTuple]:
        c = self.corr.tolist()
        return ((p[0] + c[0] + c[3] * t, p[1] + c[1] + c[4] * t, p[2] + c[2] + c[5] * t),
                (v[0] + c[3], v[1] + c[4], v[2] + c[5]), mul_tuple(c[6:10], q))

    def newest(self) -> tuple[Vec3Tuple, Vec3Tuple, QuatTuple]:
        if self._newest is None:
            head, count = self.ij.tolist()
            r = self.buf[(head + count - 1) % self._capacity].tolist()
            self._newest = self._corrected(r[0], r[7:10], r[10:13], r[13:17])
        return self._newest

    def clear_newest(self) -> None:
        self._newest = None

    def set_newest(self, out: FloatArray) -> None:
        """The compiled predict's corrected newest output (p, v, q), while the queue holds
        inputs."""
        o = out.tolist()
        self._newest = ((o[0], o[1], o[2]), (o[3], o[4], o[5]), (o[6], o[7], o[8], o[9]))

    def correct(self, dp: Vec3Tuple, dv: Vec3Tuple, t_ref: float, dq: QuatTuple) -> None:
        """Add dp + dv (t - t_ref) to the positions, dv to the velocities, turn by dq."""
        self._newest = None
        if not self:
            self._reset()
            return
        c = self.corr.tolist()
        self.corr[0:6] = (c[0] + dp[0] - dv[0] * t_ref, c[1] + dp[1] - dv[1] * t_ref,
                          c[2] + dp[2] - dv[2] * t_ref, c[3] + dv[0], c[4] + dv[1], c[5] + dv[2])
        # unit, so that repeated corrections never change the outputs' norm
        self.corr[6:10] = normalized_tuple(mul_tuple(dq, c[6:10]))

    def push(self, t: float, dt: float, gyro_in: FloatArray, accel_in: FloatArray,
             p0: Sequence[float], v0: Sequence[float], q0: Sequence[float],
             omega_b: Sequence[float], specific_b: Sequence[float]) -> None:
        """Propagate the (corrected) output (p0, v0, q0) over dt and queue it at t."""
        head, count = self.ij.tolist()
        if not count:
            self._reset()
        ax, ay, az = rotate_tuple(q0, specific_b)
        az -= self._g
        h = 0.5 * dt * dt
        p = (p0[0] + dt * v0[0] + h * ax, p0[1] + dt * v0[1] + h * ay,
             p0[2] + dt * v0[2] + h * az)
        v = (v0[0] + dt * ax, v0[1] + dt * ay, v0[2] + dt * az)
        q = mul_exp_tuple(q0, omega_b[0] * dt, omega_b[1] * dt, omega_b[2] * dt)
        c = self.corr.tolist()      # store without the correction
        row = self.buf[(head + count) % self._capacity]
        row[0] = t
        row[1:4] = gyro_in
        row[4:7] = accel_in
        row[7:13] = (p[0] - c[0] - c[3] * t, p[1] - c[1] - c[4] * t, p[2] - c[2] - c[5] * t,
                     v[0] - c[3], v[1] - c[4], v[2] - c[5])
        row[13:17] = mul_tuple(conj_tuple(c[6:10]), q)
        self.ij[1] = count + 1
        self._newest = None


class Ukf:
    """Error-state UKF on [p, v, dtheta, b_g, b_a]; see the module docstring.

    ``kernel="fast"`` (default) is ``"compiled"`` (numba loops, :mod:`estimator.compiled`) when
    numba is installed, else ``"numpy"`` (all sigma points as one array); ``kernel="filterpy"``
    runs the same models through stock filterpy, one sigma point at a time (reference/baseline).
    The compiled kernel compiles in the constructor (start-up), never in a tick.
    """

    def __init__(self, cfg: EstimatorConfig | None = None,
                 kernel: Literal["fast", "compiled", "numpy", "filterpy"] = "fast") -> None:
        self.cfg = cfg = cfg if cfg is not None else EstimatorConfig()
        self._gravity_w = np.array([0.0, 0.0, -cfg.gravity_m_s2])
        if kernel == "fast":        # compiled when numba is there, else the numpy one
            kernel = "compiled" if compiled.AVAILABLE else "numpy"
        self.kernel_name = kernel
        self._step_kernel: CompiledKernel | None = None     # whole steps in one call
        args = (STATE_DIM, cfg.sigma_alpha, cfg.sigma_beta, cfg.sigma_kappa, self._gravity_w)
        self._kernel: Kernel = (CompiledKernel(*args) if kernel == "compiled"
                                else FastKernel(*args) if kernel == "numpy"
                                else FilterpyKernel(*args))
        if isinstance(self._kernel, CompiledKernel):
            self._step_kernel = self._kernel
        self._R = np.diag([cfg.mocap_pos_sigma_m ** 2] * 3
                          + [math.radians(cfg.mocap_att_sigma_deg) ** 2] * 3)
        self._diag = np.diag_indices(STATE_DIM)
        self._q_cache_dt = math.nan
        self._q_cache = np.zeros((STATE_DIM, STATE_DIM))
        # current state
        self._initialized = False
        self._t_s = math.nan
        self._x = np.zeros(STATE_DIM)
        self._P = np.eye(STATE_DIM)
        self._q_ref = np.array([1.0, 0.0, 0.0, 0.0])
        self._prev_gyro: FloatArray | None = None
        self._prev_accel: FloatArray | None = None
        self._prev_f = ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0))     # the same, as floats
        self._last_gyro = np.zeros(3)
        self._nonfinite = False
        # history ring: the state after each predict and the input that led to it
        n_hist = cfg.history_len
        self._hist_t = np.full(n_hist, -np.inf)
        self._hist_x = np.zeros((n_hist, STATE_DIM))
        self._hist_P = np.zeros((n_hist, STATE_DIM, STATE_DIM))
        self._hist_q = np.zeros((n_hist, 4))
        self._hist_gyro = np.zeros((n_hist, 3))
        self._hist_accel = np.zeros((n_hist, 3))
        # head (newest), length, and the filter steps the compiled predict took
        self._hij = np.zeros(3, dtype=np.int64)
        self._steps_py = 0      # filter steps (UKF time updates) taken by _propagate
        # force observer (isotropic variance: the accelerometer noise is isotropic)
        # estimate (3), variance, lagged command (3), lagged command set (0/1): an array the
        # compiled predict updates (read through the properties below)
        self._fobs = np.zeros(8)
        self._fobs[3] = cfg.init_force_sigma_n ** 2
        self._fobs_const = np.array([cfg.force_walk_n_sqrt_s ** 2, cfg.mass_kg,
                                     cfg.force_cmd_lag_s,
                                     TWO_SIDED * cfg.accel_noise_m_s2_sqrt_hz ** 2])
        # fusion horizon and output predictor: IMU inputs newer than the filter's time wait
        # here, each with the output state (mean only) propagated to its time
        self._pending = _OutputPredictor(cfg.gravity_m_s2,
                                         2 * math.ceil(cfg.max_fusion_delay_s
                                                       * cfg.max_imu_rate_hz) + 8)
        # the process-noise variance rates (per second of integration) and the newest output
        # of the compiled predict
        self._noise_rates = np.array([
            TWO_SIDED * cfg.accel_noise_m_s2_sqrt_hz ** 2,
            TWO_SIDED * cfg.gyro_noise_rad_s_sqrt_hz ** 2,
            TWO_SIDED * cfg.gyro_bias_walk_rad_s2_sqrt_hz ** 2,
            TWO_SIDED * cfg.accel_bias_walk_m_s3_sqrt_hz ** 2])
        self._newest_out = np.zeros(10)
        self._pose_out = np.zeros(7)
        self._now_s = math.nan
        self._latencies = [math.inf] * cfg.latency_window
        #: the horizon is the latency of this rank among the window's (0: the smallest)
        self._horizon_rank = int(cfg.latency_window * HORIZON_LOW_OUTLIERS)
        self._latency_i = 0
        self._delay_s = 0.0
        # bookkeeping
        self._rest = _RestCollector()
        self._last_pose_t_s = -math.inf
        self._accepted = 0
        self._rejected = 0
        self._consecutive = 0
        #: the refused poses of the current run of refusals: (capture time, x, y, z)
        self._refused: collections.deque[tuple[float, float, float, float]] = \
            collections.deque(maxlen=1024)
        #: newest time the IMU was seen failing, and missing motion (note_imu_anomaly)
        self._imu_anomaly_t_s = self._imu_missed_t_s = -math.inf
        #: the newest re-seed from refused poses, None before the first
        self.last_reset: ResetInfo | None = None
        self._too_old = 0
        self._resets = 0
        self._repairs = 0
        self._imu_out_of_order = 0
        self._imu_invalid = 0
        self._poses_invalid = 0
        self._last_nis = math.nan

    # the force observer's state lives in an array the compiled predict updates
    @property
    def _force_w(self) -> Vec3Tuple:
        f = self._fobs.tolist()
        return (f[0], f[1], f[2])

    @_force_w.setter
    def _force_w(self, f: Vec3Tuple) -> None:
        self._fobs[0:3] = f

    @property
    def _force_var(self) -> float:
        return self._fobs.item(3)

    @_force_var.setter
    def _force_var(self, v: float) -> None:
        self._fobs[3] = v

    @property
    def _force_produced_b(self) -> Vec3Tuple | None:
        f = self._fobs.tolist()
        return (f[4], f[5], f[6]) if f[7] else None

    @_force_produced_b.setter
    def _force_produced_b(self, f: Vec3Tuple | None) -> None:
        if f is None:
            self._fobs[7] = 0.0
        else:
            self._fobs[4:8] = (f[0], f[1], f[2], 1.0)

    # the history ring's head and length live in an array the compiled predict updates
    @property
    def _hist_head(self) -> int:
        return self._hij.item(0)

    @_hist_head.setter
    def _hist_head(self, i: int) -> None:
        self._hij[0] = i

    @property
    def _hist_len(self) -> int:
        return self._hij.item(1)

    @_hist_len.setter
    def _hist_len(self, n: int) -> None:
        self._hij[1] = n

    # -- public API -----------------------------------------------------------------------------
    @property
    def initialized(self) -> bool:
        return self._initialized

    @property
    def t_s(self) -> float:
        """Time of the current state (the newest IMU sample); nan before the first one."""
        return self._now_s

    def initialize(self, t_s: float, pos_w_m: ArrayLike, q_wb: ArrayLike,
                   vel_w_m_s: ArrayLike = (0.0, 0.0, 0.0),
                   gyro_bias_rad_s: ArrayLike = (0.0, 0.0, 0.0),
                   accel_bias_m_s2: ArrayLike = (0.0, 0.0, 0.0),
                   cov: ArrayLike | None = None) -> None:
        """Start the filter from a known state at ``t_s`` (the rest-period path calls this).

        ``cov`` (15x15, symmetric positive semi-definite) replaces the configured initial
        sigmas; ``ValueError`` if it is not one.
        """
        P0 = self._initial_covariance() if cov is None else np.array(cov, dtype=np.float64)
        if cov is not None and (
                P0.shape != (STATE_DIM, STATE_DIM) or not np.all(np.isfinite(P0))
                or not np.allclose(P0, P0.T, rtol=0.0, atol=1e-12 * float(np.abs(P0).max()))
                or float(np.linalg.eigvalsh(P0).min()) < -1e-12 * float(np.abs(P0).max())):
            raise ValueError("initial covariance must be a symmetric positive semi-definite "
                             f"{STATE_DIM}x{STATE_DIM} matrix")
        self._x = np.zeros(STATE_DIM)
        self._x[POS] = np.asarray(pos_w_m, dtype=np.float64)
        self._x[VEL] = np.asarray(vel_w_m_s, dtype=np.float64)
        self._x[GYRO_BIAS] = np.asarray(gyro_bias_rad_s, dtype=np.float64)
        self._x[ACCEL_BIAS] = np.asarray(accel_bias_m_s2, dtype=np.float64)
        self._q_ref = quat_normalize(np.asarray(q_wb, dtype=np.float64))
        self._P = P0
        self._t_s = self._now_s = float(t_s)
        self._pending.clear()
        self._initialized = True
        self._nonfinite = False
        self._last_pose_t_s = float(t_s)
        self._hist_len = 0
        self._push_history(self._prev_gyro if self._prev_gyro is not None else np.zeros(3),
                           self._prev_accel if self._prev_accel is not None else np.zeros(3))

    def _initial_covariance(self) -> FloatArray:
        cfg = self.cfg
        return np.diag([cfg.init_pos_sigma_m ** 2] * 3 + [cfg.init_vel_sigma_m_s ** 2] * 3
                       + [math.radians(cfg.init_att_sigma_deg) ** 2] * 3
                       + [cfg.init_gyro_bias_sigma_rad_s ** 2] * 3
                       + [cfg.init_accel_bias_sigma_m_s2 ** 2] * 3)

    def predict(self, imu_t_s: float, gyro_rad_s: ArrayLike, accel_m_s2: ArrayLike,
                force_cmd_b_n: ArrayLike | None = None) -> None:
        """Propagate to ``imu_t_s`` with one IMU sample (body frame, specific force).

        ``force_cmd_b_n`` is the body-frame force the controller commanded (for the force
        observer); ``None`` leaves the force estimate to its time update.
        """
        gyro = np.asarray(gyro_rad_s, dtype=np.float64)
        accel = np.asarray(accel_m_s2, dtype=np.float64)
        t = float(imu_t_s)
        # plain floats: a numpy sum per check costs more than the six additions
        gx, gy, gz = gyro.tolist()
        ax, ay, az = accel.tolist()
        if not math.isfinite(t + gx + gy + gz + ax + ay + az):
            self._imu_invalid += 1
            return
        if not self._initialized:
            if self._prev_gyro is not None and not t > self._now_s:
                self._imu_out_of_order += 1
                return
            self._t_s = self._now_s = t
            self._prev_gyro, self._prev_accel, self._last_gyro = gyro, accel, gyro
            self._prev_f = ((gx, gy, gz), (ax, ay, az))
            self._rest.add_imu(t, gyro, accel)
            self._try_initialize()
            return
        dt = t - self._now_s
        if not dt > 0.0:
            self._imu_out_of_order += 1
            return
        if self._prev_gyro is not None and self.cfg.imu_integration == "trapezoid":
            (pgx, pgy, pgz), (pax, pay, paz) = self._prev_f   # floats: cheaper than numpy
            gi = (0.5 * (pgx + gx), 0.5 * (pgy + gy), 0.5 * (pgz + gz))
            ai = (0.5 * (pax + ax), 0.5 * (pay + ay), 0.5 * (paz + az))
        else:
            gi, ai = (gx, gy, gz), (ax, ay, az)
        self._prev_gyro, self._prev_accel, self._last_gyro = gyro, accel, gyro
        self._prev_f = ((gx, gy, gz), (ax, ay, az))
        self._now_s = t
        pending = self._pending
        direct = self._delay_s == 0.0 and not pending      # the filter is the output
        if self._step_kernel is not None and not self._nonfinite and not pending.full():
            # one fresh array of every input (the compiled signature never changes)
            fx, fy, fz = (0.0, 0.0, 0.0) if force_cmd_b_n is None else \
                np.asarray(force_cmd_b_n, dtype=np.float64).tolist()
            inp = np.array((*gi, *ai, ax, ay, az, fx, fy, fz,
                            force_cmd_b_n is not None, self.cfg.force_observer), np.float64)
            if self._compiled_predict(t, dt, inp, direct) == 0:
                return          # the force observer ran in the same call
            # a repair or a non-finite step: the Python path from where it stopped
            if direct:
                self._filter_step(t, dt, inp[0:3].copy(), inp[3:6].copy())
            else:
                self._advance_filter(t - self._delay_s)
        elif direct:
            g_in, a_in = np.array(gi), np.array(ai)
            self._filter_step(t, dt, g_in, a_in)
        else:
            self._queue_input(t, dt, np.array(gi), np.array(ai))
            self._advance_filter(t - self._delay_s)
        if self.cfg.force_observer:
            self._observe_force(dt, accel, force_cmd_b_n)

    def _compiled_predict(self, t: float, dt: float, inp: FloatArray, direct: bool) -> int:
        """The same sequence as the Python path (a direct filter step, or queue the input and
        advance the filter to the horizon; then the force observer), in one compiled call;
        its status (0: done)."""
        step = self._step_kernel
        assert step is not None
        cfg = self.cfg
        pending = self._pending
        x, P, q = self._contiguous_state()
        status, self._t_s = step.horizon_predict(
            t, dt, inp, t - self._delay_s, direct, self._t_s, x, P, q, pending.buf,
            pending.ij, pending.corr, cfg.gravity_m_s2, self._hist_t, self._hist_x,
            self._hist_P, self._hist_q, self._hist_gyro, self._hist_accel, self._hij,
            self._noise_rates, cfg.min_variance, cfg.max_pos_sigma_m ** 2, self._newest_out,
            self._fobs, self._fobs_const)
        if status == 0 and pending:
            pending.set_newest(self._newest_out)
        else:
            pending.clear_newest()
        return status

    def update_pose(self, capture_t_s: float, pos_w_m: ArrayLike, q_wb: ArrayLike
                    ) -> PoseVerdict:
        """Fuse a MoCap pose captured at ``capture_t_s`` (IMU clock), compensating its age."""
        pos = np.asarray(pos_w_m, dtype=np.float64)
        q_raw = np.asarray(q_wb, dtype=np.float64)
        if pos.shape != (3,) or q_raw.shape != (4,):
            self._poses_invalid += 1
            return PoseVerdict.INVALID
        # plain floats: validating and normalising 7 numbers costs more in numpy calls
        qw, qx, qy, qz = q_raw.tolist()
        px, py, pz = pos.tolist()
        norm = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
        if not math.isfinite(float(capture_t_s) + px + py + pz + norm) or abs(norm - 1.0) > 0.1:
            self._poses_invalid += 1
            return PoseVerdict.INVALID
        k = math.copysign(1.0, qw) / norm           # w >= 0, as quat_normalize
        q_m = np.array((qw * k, qx * k, qy * k, qz * k))
        pos = np.array((px, py, pz))    # fresh: the compiled update's argument types
        if not self._initialized:
            self._rest.add_pose(pos, q_m)
            self._try_initialize()
            return PoseVerdict.INITIALIZING
        if self._nonfinite:
            self._reseed(pos, q_m, zero_velocity=True)
            return PoseVerdict.RESET
        t_c = float(capture_t_s)
        if not self.cfg.latency_compensation:
            self._advance_filter(math.inf)
            return self._fuse_now(t_c, pos, q_m, shift=False)
        self._note_latency(self._now_s - t_c)
        if t_c < self._t_s - self._half_step_s():
            # older than the filter's time: replay the filter's own history
            return self._fuse_in_past(t_c, pos, q_m)
        # at or after the filter's time: bring the filter to the IMU sample nearest the capture
        # time and fuse there
        self._advance_filter(t_c)
        t_next = self._pending.oldest_t_s()
        if t_next - t_c < t_c - self._t_s:
            self._advance_filter(t_next)
        return self._fuse_now(t_c, pos, q_m)

    def estimate(self) -> StateEstimate:
        """The state at the newest IMU sample, with covariance, force estimate and health.

        Position, velocity and attitude are the output predictor's (the filter's state carried
        to the newest sample); ``cov`` and the biases are the filter's, at the fusion horizon.
        """
        x = self._x
        omega = self._last_gyro - x[GYRO_BIAS]
        if not self._pending:
            pos, vel, q = x[POS].copy(), x[VEL].copy(), self._q_ref.copy()
        else:
            p, v, qq = self._pending.newest()
            pos, vel, q = np.array(p), np.array(v), np.array(qq)
        return StateEstimate(
            t_s=self._now_s, pos_w_m=pos, vel_w_m_s=vel,
            q_wb=q, omega_b_rad_s=omega,
            gyro_bias_rad_s=x[GYRO_BIAS].copy(), accel_bias_m_s2=x[ACCEL_BIAS].copy(),
            cov=self._P.copy(), force_ext_w_n=np.array(self._force_w),
            force_ext_sigma_n=math.sqrt(self._force_var), health=self.health())

    def output_state(self) -> tuple[Vec3Tuple, Vec3Tuple, QuatTuple, Vec3Tuple]:
        """Position, velocity, attitude and body rate of :meth:`estimate` as plain floats,
        without its covariance copy and health report (a controller's per-tick read)."""
        xl = self._x.tolist()
        gx, gy, gz = self._last_gyro.tolist()
        omega = (gx - xl[9], gy - xl[10], gz - xl[11])
        if not self._pending:
            q = self._q_ref.tolist()
            return ((xl[0], xl[1], xl[2]), (xl[3], xl[4], xl[5]), (q[0], q[1], q[2], q[3]),
                    omega)
        p, v, qq = self._pending.newest()
        return p, v, qq, omega

    def biases(self) -> tuple[Vec3Tuple, Vec3Tuple]:
        """The gyro (rad/s) and accelerometer (m/s^2) biases as plain floats."""
        xl = self._x[9:15].tolist()
        return (xl[0], xl[1], xl[2]), (xl[3], xl[4], xl[5])

    def force_ext_w_n(self) -> Vec3Tuple:
        """The force observer's estimate of :meth:`estimate` (world, N), as plain floats."""
        return self._force_w

    def usable(self) -> bool:
        """Initialised and not diverged: what :meth:`health` reports without the flags
        ``NOT_INITIALIZED`` and ``DIVERGED`` (the same tests, without building the report: the
        per-tick question of a flight loop)."""
        if not self._initialized:
            return False
        if self._nonfinite:
            return False
        cfg = self.cfg
        P = self._P
        return (max(P.item(0, 0), P.item(1, 1), P.item(2, 2)) <= cfg.diverged_pos_sigma_m ** 2
                and max(P.item(6, 6), P.item(7, 7), P.item(8, 8))
                <= math.radians(cfg.diverged_att_sigma_deg) ** 2)

    def checkpoint(self) -> UkfCheckpoint:
        """The filter as it is now, to dead reckon from later (:meth:`dead_reckon_from`).
        A copy of the state the predictions use (about 6 kB: mean, covariance, the output
        queue, the force observer); not the history ring, the configuration or the counters."""
        return UkfCheckpoint(self._now_s, {k: copy.deepcopy(v) for k, v in vars(self).items()
                                           if k not in _CHECKPOINT_SKIP})

    def dead_reckon_from(self, checkpoint: UkfCheckpoint,
                         imu_inputs: Iterable[tuple[float, Vec3Tuple, Vec3Tuple,
                                                    Vec3Tuple | None]]) -> int:
        """Go back to ``checkpoint`` and predict again with the IMU inputs after it (the
        arguments of :meth:`predict`, oldest first), fusing nothing: the estimate the IMU alone
        gives since the checkpoint. For a MoCap found wrong only after it had pulled the
        estimate for a while (a frozen tracker that still streams). A bias the checkpoint had
        not settled (:data:`BIAS_UNSETTLED_VAR_RATIO`) is taken from now. The counters go on;
        the history ring starts again here. Returns the samples replayed."""
        # a bias the checkpoint knew much less well than the filter does now (a checkpoint
        # early in the flight, the biases still settling) is taken from now: the MoCap that
        # went wrong pulls the position and velocity, the biases far less
        x_now, var_now = self._x.copy(), np.diag(self._P).copy()
        for k, v in checkpoint.state.items():
            setattr(self, k, copy.deepcopy(v))     # the checkpoint stays usable
        var_cp = np.diag(self._P)
        for block in (GYRO_BIAS, ACCEL_BIAS):
            if var_cp[block].sum() > BIAS_UNSETTLED_VAR_RATIO * var_now[block].sum():
                self._x[block] = x_now[block]
        self._hist_len = 0
        n = 0
        for t_s, gyro, accel, force in imu_inputs:
            if t_s > checkpoint.t_s:
                self.predict(t_s, gyro, accel, force)
                n += 1
        return n

    @property
    def filter_steps(self) -> int:
        """UKF time updates (sigma-point passes) so far, replays after a late pose included:
        one per IMU sample when nothing is replayed."""
        return self._steps_py + self._hij.item(2)

    @property
    def fusion_delay_s(self) -> float:
        """How far the filter currently runs behind the newest IMU sample (see the config)."""
        return self._delay_s

    def health(self) -> EstimatorHealth:
        cfg = self.cfg
        flags = HealthFlag.OK
        age = self._now_s - self._last_pose_t_s if self._initialized else math.inf
        if not self._initialized:
            flags |= HealthFlag.NOT_INITIALIZED
        else:
            if age > cfg.mocap_stale_s:
                flags |= HealthFlag.MOCAP_STALE
            # plain floats: a handful of numpy reductions on 3-vectors cost more than the logic
            var = self._P.diagonal().tolist()
            if (self._nonfinite or not max(var[0:3]) <= cfg.diverged_pos_sigma_m ** 2
                    or not max(var[6:9]) <= math.radians(cfg.diverged_att_sigma_deg) ** 2):
                flags |= HealthFlag.DIVERGED
            x = self._x.tolist()
            if not max(map(abs, x[9:12])) <= cfg.max_gyro_bias_rad_s:
                flags |= HealthFlag.GYRO_BIAS_OUT_OF_RANGE
            if not max(map(abs, x[12:15])) <= cfg.max_accel_bias_m_s2:
                flags |= HealthFlag.ACCEL_BIAS_OUT_OF_RANGE
        return EstimatorHealth(
            flags=flags, mocap_age_s=age, poses_accepted=self._accepted,
            poses_rejected=self._rejected, consecutive_rejections=self._consecutive,
            poses_too_old=self._too_old, resets=self._resets,
            covariance_repairs=self._repairs, imu_out_of_order=self._imu_out_of_order,
            imu_invalid=self._imu_invalid, poses_invalid=self._poses_invalid,
            last_nis=self._last_nis)

    # -- propagation and fusion -----------------------------------------------------------------
    def _filter_step(self, t: float, dt: float, g_in: FloatArray, a_in: FloatArray) -> None:
        """One UKF predict of the filter itself, from its time to ``t``."""
        x, P, q, finite = self._propagate(self._x, self._P, self._q_ref, dt, g_in, a_in)
        if not finite:
            self._nonfinite = True          # keep the last finite state; a pose re-seeds it
            self._t_s = t
            return
        self._x, self._P, self._q_ref, self._t_s = x, P, q, t
        self._push_history(g_in, a_in)

    # -- fusion horizon and output predictor (PX4 EKF2's delayed horizon, without its lag) -------
    # The filter runs ``_delay_s`` behind the newest IMU sample: about the smallest MoCap
    # latency of the last poses (HORIZON_LOW_OUTLIERS), so a pose usually arrives just after
    # the filter's time and is fused without replaying any IMU sample. The output predictor
    # integrates the queued inputs (mean only, same model) to the newest sample; whenever the
    # filter moves, the difference between the filter's state and the output at the filter's
    # time is added to every newer output (position also by the velocity difference times the
    # time since; applied lazily, see _OutputPredictor), i.e. the outputs are re-based on the
    # filter exactly to first order, without EKF2's smoothing lag.
    def _note_latency(self, latency_s: float) -> None:
        lat = self._latencies
        lat[self._latency_i] = latency_s
        self._latency_i = (self._latency_i + 1) % len(lat)
        low = sorted(lat)[self._horizon_rank] if self._horizon_rank else min(lat)
        self._delay_s = min(max(low, 0.0), self.cfg.max_fusion_delay_s)

    def _queue_input(self, t: float, dt: float, g_in: FloatArray, a_in: FloatArray) -> None:
        pending = self._pending
        if pending.full():                          # IMU faster than configured: catch up
            self._advance_filter(pending.oldest_t_s())
        xl = self._x.tolist()
        if pending:
            p0, v0, q0 = pending.newest()
        else:
            p0, v0, q0 = (xl[0], xl[1], xl[2]), (xl[3], xl[4], xl[5]), tuple(self._q_ref.tolist())
        gx, gy, gz = g_in.tolist()
        ax, ay, az = a_in.tolist()
        pending.push(t, dt, g_in, a_in, p0, v0, q0, (gx - xl[9], gy - xl[10], gz - xl[11]),
                     (ax - xl[12], ay - xl[13], az - xl[14]))

    def _advance_filter(self, t_target_s: float) -> None:
        """Consume the queued inputs up to ``t_target_s`` into the filter; re-base the outputs."""
        pending = self._pending
        step = self._step_kernel
        if step is not None and not self._nonfinite and pending \
                and pending.oldest_t_s() <= t_target_s + _TIME_EPS_S:
            # the sequence below in one compiled call; a repair or a non-finite step is left
            # to it, from the input where the compiled loop stopped
            x, P, q_arr = self._contiguous_state()
            cfg = self.cfg
            status, self._t_s = step.advance(
                t_target_s, self._t_s, x, P, q_arr, pending.buf, pending.ij, pending.corr,
                self._hist_t, self._hist_x, self._hist_P, self._hist_q, self._hist_gyro,
                self._hist_accel, self._hij, self._noise_rates, cfg.min_variance,
                cfg.max_pos_sigma_m ** 2, self._newest_out)
            if status == 0:
                if pending:
                    pending.set_newest(self._newest_out)
                else:
                    pending.clear_newest()
                return
            pending.clear_newest()
        last = None
        while pending and pending.oldest_t_s() <= t_target_s + _TIME_EPS_S:
            last = pending.popleft()
            self._filter_step(last.t_s, last.t_s - self._t_s, last.gyro_in, last.accel_in)
        if last is not None:
            p, v, q = pending.corrected(last)
            self._correct_outputs(p, v, q, last.t_s)

    def _correct_outputs(self, p_ref: Sequence[float], v_ref: Sequence[float],
                         q_ref: Sequence[float], t_ref: float) -> None:
        """The outputs newer than the filter were built on (p_ref, v_ref, q_ref) at t_ref."""
        if not self._pending or self._nonfinite:
            return
        x = self._x[0:6].tolist()
        self._pending.correct(
            (x[0] - p_ref[0], x[1] - p_ref[1], x[2] - p_ref[2]),
            (x[3] - v_ref[0], x[4] - v_ref[1], x[5] - v_ref[2]),
            t_ref, mul_tuple(tuple(self._q_ref.tolist()), conj_tuple(q_ref)))

    def _output_q(self) -> Sequence[float]:
        return self._q_ref.tolist() if not self._pending else self._pending.newest()[2]

    def _half_step_s(self) -> float:
        n_hist = len(self._hist_t)
        if self._hist_len < 2:
            return _TIME_EPS_S
        h = self._hist_head
        return 0.5 * float(self._hist_t[h] - self._hist_t[(h - 1) % n_hist])

    def _fuse_now(self, t_c: float, pos: FloatArray, q_m: FloatArray, shift: bool = True
                  ) -> PoseVerdict:
        """Fuse at the filter's current time (the IMU sample nearest the capture time), the
        pose moved to that time (``shift``) or taken as it is (no latency compensation)."""
        step = self._step_kernel
        if step is not None and not self._nonfinite:     # the sequence below, compiled
            cfg = self.cfg
            pending = self._pending
            x, P, q = self._contiguous_state()
            out = self._pose_out
            status, nis = step.fuse_now(
                t_c, pos, q_m, shift, self._t_s, x, P, q, self._R, cfg.gate_nis, self._hist_x,
                self._hist_P, self._hist_q, self._hist_gyro, self._hij, pending.buf,
                pending.ij, pending.corr, cfg.min_variance, cfg.max_pos_sigma_m ** 2, out,
                self._newest_out)
            if status != 1:         # 1: P not positive definite, the path below repairs it
                return self._compiled_pose_verdict(status, nis, t_c)
        p_r, v_r, q_r = self._x[POS].tolist(), self._x[VEL].tolist(), self._q_ref.tolist()
        if shift:
            pos, q_m = self._shift_pose(pos, q_m, self._t_s - t_c, self._x, self._hist_head)
        fused = self._fuse(self._x, self._P, self._q_ref, pos, q_m)
        if fused is None:
            return self._rejected_pose(pos, q_m, t_c)
        self._x, self._P, self._q_ref = fused
        self._write_history(self._hist_head)
        self._correct_outputs(p_r, v_r, q_r, self._t_s)
        return self._accepted_pose(t_c)

    def _process_noise(self, dt: float) -> FloatArray:
        if dt == self._q_cache_dt:
            return self._q_cache
        cfg = self.cfg
        # one-sided densities -> variance per second of integration (config docstring)
        qa = TWO_SIDED * cfg.accel_noise_m_s2_sqrt_hz ** 2
        Q = np.zeros((STATE_DIM, STATE_DIM))
        i3 = np.eye(3)
        Q[POS, POS] = qa * dt ** 3 / 3.0 * i3
        Q[POS, VEL] = Q[VEL, POS] = qa * dt ** 2 / 2.0 * i3
        Q[VEL, VEL] = qa * dt * i3
        Q[ATT, ATT] = TWO_SIDED * cfg.gyro_noise_rad_s_sqrt_hz ** 2 * dt * i3
        Q[GYRO_BIAS, GYRO_BIAS] = TWO_SIDED * cfg.gyro_bias_walk_rad_s2_sqrt_hz ** 2 * dt * i3
        Q[ACCEL_BIAS, ACCEL_BIAS] = TWO_SIDED * cfg.accel_bias_walk_m_s3_sqrt_hz ** 2 * dt * i3
        self._q_cache_dt, self._q_cache = dt, Q
        return Q

    def _propagate(self, x: FloatArray, P: FloatArray, q_ref: FloatArray, dt: float,
                   gyro: FloatArray, accel: FloatArray
                   ) -> tuple[FloatArray, FloatArray, FloatArray, bool]:
        """One predict -> (x, P, q_ref, finite); ``finite`` false: x or P has a non-finite
        entry (the caller keeps its last finite state)."""
        self._steps_py += 1
        # 1 ns resolution, so that the repeated IMU period hits the cached Q and F
        dt = round(dt, 9)
        step = self._step_kernel
        if step is not None:        # the same sequence as below, in one compiled call
            Q = self._process_noise(dt)
            cfg = self.cfg
            cap = cfg.max_pos_sigma_m ** 2
            out = step.predict_step(x, P, q_ref, Q, dt, gyro, accel, cfg.min_variance, cap)
            if out is None:
                out = step.predict_step(x, self._repair_spd(P), q_ref, Q, dt, gyro, accel,
                                        cfg.min_variance, cap)
                if out is None:
                    raise np.linalg.LinAlgError("covariance not positive definite")
            return out
        q_next = mul_exp_single(q_ref, (gyro - x[GYRO_BIAS]) * dt)
        args = (self._process_noise(dt), dt, gyro, accel, q_ref, quat_conj(q_next))
        try:
            x1, P1 = self._kernel.predict(x, P, *args)
        except np.linalg.LinAlgError:
            x1, P1 = self._kernel.predict(x, self._repair_spd(P), *args)
        finite = math.isfinite(float(x1.sum()) + float(P1.sum()))
        q1 = self._fold_attitude(x1, q_next)
        return x1, self._condition(P1), q1, finite

    def _fuse(self, x: FloatArray, P: FloatArray, q_ref: FloatArray, pos: FloatArray,
              q_m: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray] | None:
        """Gated update; ``None`` when the gate rejects (inputs are never modified)."""
        z = np.concatenate((pos, log_relative_single(q_ref, q_m)))
        step = self._step_kernel
        if step is not None:        # the same sequence as below, in one compiled call
            cfg = self.cfg
            cap = cfg.max_pos_sigma_m ** 2
            res = step.update_step(x, P, q_ref, z, self._R, cfg.min_variance, cap)
            if res is None:
                res = step.update_step(x, self._repair_spd(P), q_ref, z, self._R,
                                       cfg.min_variance, cap)
                if res is None:
                    raise np.linalg.LinAlgError("covariance not positive definite")
            x1, P1, q1, nis, finite = res
            self._last_nis = nis
            if not nis <= cfg.gate_nis or not finite:
                return None
            return x1, P1, q1
        try:
            x1, P1, y, S = self._kernel.update(x, P, z, self._R)
        except np.linalg.LinAlgError:
            x1, P1, y, S = self._kernel.update(x, self._repair_spd(P), z, self._R)
        nis = float(y @ np.linalg.solve(S, y))
        self._last_nis = nis
        if not nis <= self.cfg.gate_nis or not math.isfinite(float(x1.sum()) + float(P1.sum())):
            return None
        q1 = self._fold_attitude(x1, q_ref)
        return x1, self._condition(P1), q1

    def _fold_attitude(self, x: FloatArray, q_ref: FloatArray) -> FloatArray:
        """Move the attitude error into the nominal quaternion and zero it (in place on x)."""
        q = mul_exp_single(q_ref, x[ATT])
        x[ATT] = 0.0
        return q

    def _condition(self, P: FloatArray) -> FloatArray:
        """Symmetrise, floor the variances, cap the position sigma (congruence keeps P SPD)."""
        P = 0.5 * (P + P.T)
        d = P.diagonal().tolist()
        cfg = self.cfg
        if min(d) < cfg.min_variance:
            P[self._diag] = np.maximum(P.diagonal(), cfg.min_variance)
        cap = cfg.max_pos_sigma_m ** 2
        if max(d[0:3]) > cap:
            scale = np.ones(STATE_DIM)
            scale[POS] = np.sqrt(np.minimum(1.0, cap / P.diagonal()[POS]))
            P = P * scale[:, None] * scale[None, :]
        return P

    def _repair_spd(self, P: FloatArray) -> FloatArray:
        self._repairs += 1
        w, V = np.linalg.eigh(0.5 * (P + P.T))
        floor = max(self.cfg.min_variance, 1e-12 * float(np.max(np.abs(w))))
        return (V * np.maximum(w, floor)) @ V.T

    def _fuse_in_past(self, t_c: float, pos: FloatArray, q_m: FloatArray) -> PoseVerdict:
        step = self._step_kernel
        if step is not None and not self._nonfinite:     # the sequence below, compiled
            cfg = self.cfg
            pending = self._pending
            x, P, q = self._contiguous_state()
            out = self._pose_out
            status, nis = step.fuse_in_past(
                t_c, pos, q_m, self._t_s, x, P, q, self._R, cfg.gate_nis, self._hist_t,
                self._hist_x, self._hist_P, self._hist_q, self._hist_gyro, self._hist_accel,
                self._hij, pending.buf, pending.ij, pending.corr, self._noise_rates,
                cfg.min_variance, cfg.max_pos_sigma_m ** 2, out, self._newest_out)
            if status == 3:
                self._too_old += 1
                return PoseVerdict.TOO_OLD
            if status != 1:     # 1: a repair or a non-finite step, the path below takes it
                return self._compiled_pose_verdict(status, nis, t_c)
        n_hist = len(self._hist_t)
        k = 0
        while k < self._hist_len and self._hist_t[(self._hist_head - k) % n_hist] > t_c:
            k += 1
        if k >= self._hist_len:
            self._too_old += 1
            return PoseVerdict.TOO_OLD
        j = (self._hist_head - k) % n_hist
        if k > 0 and float(self._hist_t[(j + 1) % n_hist]) - t_c < t_c - float(self._hist_t[j]):
            k -= 1                          # the next sample is nearer the capture time
            j = (j + 1) % n_hist
        x, P, q = self._hist_x[j].copy(), self._hist_P[j].copy(), self._hist_q[j].copy()
        pos, q_m = self._shift_pose(pos, q_m, float(self._hist_t[j]) - t_c, x, j)
        fused = self._fuse(x, P, q, pos, q_m)
        if fused is None:
            return self._rejected_pose(pos, q_m, t_c)
        x, P, q = fused
        self._store(x, P, q, (self._hist_head - k) % n_hist)
        while k > 0:
            k -= 1
            i = (self._hist_head - k) % n_hist
            dt = float(self._hist_t[i] - self._hist_t[(i - 1) % n_hist])
            x, P, q, _ = self._propagate(x, P, q, dt, self._hist_gyro[i], self._hist_accel[i])
            self._store(x, P, q, i)
        p_r, v_r, q_r = self._x[POS].tolist(), self._x[VEL].tolist(), self._q_ref.tolist()
        self._x, self._P, self._q_ref = x, P, q
        self._correct_outputs(p_r, v_r, q_r, self._t_s)
        return self._accepted_pose(t_c)

    def _shift_pose(self, pos: FloatArray, q_m: FloatArray, dt_s: float, x: FloatArray,
                    j: int) -> tuple[FloatArray, FloatArray]:
        """The pose moved ``dt_s`` forward in time with the state's velocity and rate.

        A capture time between two IMU samples is fused at the nearer one (|dt_s| <= half an
        IMU period, 1 ms at 500 Hz): a 2 mm/s velocity error then moves the pose by 2 um and
        a 0.01 rad/s rate error turns it by 6e-4 deg, far below the MoCap noise, and no IMU
        interval has to be split (which would cost one more predict per pose).
        """
        if abs(dt_s) <= _TIME_EPS_S:
            return pos, q_m
        omega_b = self._hist_gyro[j] - x[GYRO_BIAS]
        return pos + dt_s * x[VEL], mul_exp_single(q_m, dt_s * omega_b)

    def _contiguous_state(self) -> tuple[FloatArray, FloatArray, FloatArray]:
        """x, P and q_ref as C-contiguous arrays, kept as the state (the compiled calls'
        signature: another layout would compile a new one)."""
        self._x = np.ascontiguousarray(self._x)
        self._P = np.ascontiguousarray(self._P)
        self._q_ref = np.ascontiguousarray(self._q_ref)
        return self._x, self._P, self._q_ref

    def _compiled_pose_verdict(self, status: int, nis: float, t_c: float) -> PoseVerdict:
        """The verdict of a compiled fusion that finished (0 fused, 2 refused; the refused
        pose is in ``_pose_out``), with the outputs' newest entry taken from it."""
        self._last_nis = nis
        if status == 2:
            out = self._pose_out
            return self._rejected_pose(out[0:3].copy(), out[3:7].copy(), t_c)
        if self._pending:
            self._pending.set_newest(self._newest_out)
        return self._accepted_pose(t_c)

    def _accepted_pose(self, t_c: float) -> PoseVerdict:
        self._accepted += 1
        self._consecutive = 0
        self._last_pose_t_s = max(self._last_pose_t_s, t_c)
        return PoseVerdict.ACCEPTED

    def _rejected_pose(self, pos: FloatArray, q_m: FloatArray, t_c: float) -> PoseVerdict:
        self._rejected += 1
        if self._consecutive == 0:
            self._refused.clear()
        self._consecutive += 1
        px, py, pz = pos.tolist()
        self._refused.append((t_c, px, py, pz))
        if self._consecutive < self.cfg.max_consecutive_rejections:
            return PoseVerdict.REJECTED
        start_s = self._refused[0][0]
        vel_mocap = self._refused_velocity(t_c)
        suspect = self._imu_anomaly_t_s >= start_s - IMU_ANOMALY_MARGIN_S
        missed = self._imu_missed_t_s >= start_s - IMU_ANOMALY_MARGIN_S
        v = self._x[VEL].tolist()
        self.last_reset = ResetInfo(t_c, start_s, (v[0], v[1], v[2]), vel_mocap, suspect,
                                    missed)
        self._reseed(pos, q_m, zero_velocity=False,
                     velocity=vel_mocap if suspect else None)
        return PoseVerdict.RESET

    def _refused_velocity(self, t_c: float) -> Vec3Tuple | None:
        """Least-squares velocity of the refused poses of the last RESEED_VELOCITY_WINDOW_S
        (the last 3 if fewer: a MoCap slower than 30 Hz)."""
        pts = [r for r in self._refused if r[0] >= t_c - RESEED_VELOCITY_WINDOW_S - _TIME_EPS_S]
        if len(pts) < 3:
            pts = list(self._refused)[-3:]
        if len(pts) < 3:
            return None
        a = np.array(pts)
        t = a[:, 0] - a[:, 0].mean()
        den = float(t @ t)
        if not den > 0.0:
            return None
        vx, vy, vz = (t @ (a[:, 1:] - a[:, 1:].mean(axis=0)) / den).tolist()
        return (vx, vy, vz)

    @property
    def imu_anomaly_t_s(self) -> float:
        """The newest time the IMU was seen failing (:meth:`note_imu_anomaly`), -inf: never."""
        return self._imu_anomaly_t_s

    def note_imu_anomaly(self, t_s: float, motion_missed: bool = False) -> None:
        """The IMU was seen failing at ``t_s`` (samples lost, corrupted or implausible;
        ``motion_missed``: an accelerometer at the link's limit, an impact's step): a re-seed
        soon after takes the velocity from MoCap as well and says so in :attr:`last_reset`
        (:data:`IMU_ANOMALY_MARGIN_S`)."""
        self._imu_anomaly_t_s = max(self._imu_anomaly_t_s, float(t_s))
        if motion_missed:
            self._imu_missed_t_s = max(self._imu_missed_t_s, float(t_s))

    def _reseed(self, pos: FloatArray, q_m: FloatArray, zero_velocity: bool,
                velocity: Vec3Tuple | None = None) -> None:
        """Re-seed position and attitude from MoCap (marker swap that stays, or NaN state);
        the velocity too if given (MoCap's, when the IMU missed part of the motion)."""
        cfg = self.cfg
        self._resets += 1
        self._consecutive = 0
        x = self._x.copy()
        P = self._P.copy()
        if self._nonfinite or not np.all(np.isfinite(x)):
            x = np.zeros(STATE_DIM)
            P = self._initial_covariance()
        x[POS] = pos
        x[ATT] = 0.0
        if zero_velocity:
            x[VEL] = 0.0
        elif velocity is not None:
            x[VEL] = velocity
        # the velocity dead-reckoned while poses were refused is suspect too: decorrelate it
        vel_var = np.maximum(np.diag(P)[VEL], cfg.init_vel_sigma_m_s ** 2)
        for block in (POS, ATT, VEL):
            P[block, :] = 0.0
            P[:, block] = 0.0
        P[POS, POS] = cfg.init_pos_sigma_m ** 2 * np.eye(3)
        P[ATT, ATT] = math.radians(cfg.init_att_sigma_deg) ** 2 * np.eye(3)
        P[VEL, VEL] = np.diag(np.full(3, cfg.init_vel_sigma_m_s ** 2)
                              if zero_velocity or velocity is not None else vel_var)
        self._x, self._P, self._q_ref = x, P, q_m.copy()
        self._nonfinite = False
        self._last_pose_t_s = self._now_s
        # the history no longer matches the re-seeded state: restart it from here
        self._hist_len = 0
        self._push_history(self._prev_gyro if self._prev_gyro is not None else np.zeros(3),
                           self._prev_accel if self._prev_accel is not None else np.zeros(3))
        self._advance_filter(math.inf)

    # -- history ring -----------------------------------------------------------------------------
    def _push_history(self, gyro: FloatArray, accel: FloatArray) -> None:
        n_hist = len(self._hist_t)
        self._hist_head = (self._hist_head + 1) % n_hist
        self._hist_len = min(self._hist_len + 1, n_hist)
        i = self._hist_head
        self._hist_t[i] = self._t_s
        self._hist_gyro[i] = gyro
        self._hist_accel[i] = accel
        self._write_history(i)

    def _write_history(self, i: int) -> None:
        self._hist_x[i] = self._x
        self._hist_P[i] = self._P
        self._hist_q[i] = self._q_ref

    def _store(self, x: FloatArray, P: FloatArray, q: FloatArray, i: int) -> None:
        self._hist_x[i] = x
        self._hist_P[i] = P
        self._hist_q[i] = q

    # -- initialisation and force observer ----------------------------------------------------
    def _try_initialize(self) -> None:
        cfg = self.cfg
        rest = self._rest
        if rest.n_imu < 2 or rest.n_pose < cfg.init_min_poses:
            return
        if self._t_s - rest.t_first_s < cfg.init_rest_s:
            return
        at_rest = (rest.std(rest.gyro_sum, rest.gyro_sq, rest.n_imu) <= cfg.rest_gyro_std_rad_s
                   and rest.std(rest.accel_sum, rest.accel_sq, rest.n_imu)
                   <= cfg.rest_accel_std_m_s2
                   and float(np.max(rest.pos_max - rest.pos_min)) <= cfg.rest_pos_spread_m)
        if not at_rest:
            rest.clear()                    # moving: start a new rest period
            return
        q = quat_normalize(rest.q_sum)
        gyro_bias = rest.gyro_sum / rest.n_imu
        # at rest the specific force is R^T (0, 0, g); the rest of the mean is the bias
        accel_bias = rest.accel_sum / rest.n_imu - quat_to_rot(q).T @ (-self._gravity_w)
        self.initialize(self._t_s, rest.pos_sum / rest.n_pose, q,
                        gyro_bias_rad_s=gyro_bias, accel_bias_m_s2=accel_bias)
        rest.clear()

    def _observe_force(self, dt: float, accel: FloatArray, force_cmd_b_n: ArrayLike | None
                       ) -> None:
        cfg = self.cfg
        self._force_var += cfg.force_walk_n_sqrt_s ** 2 * dt
        if force_cmd_b_n is None:
            return
        m = cfg.mass_kg
        # plain floats throughout: a dozen small numpy operations cost more than the maths
        fx, fy, fz = np.asarray(force_cmd_b_n, dtype=np.float64).tolist()
        if not math.isfinite(fx + fy + fz):
            return
        if cfg.force_cmd_lag_s > 0.0:
            if self._force_produced_b is None:
                self._force_produced_b = (fx, fy, fz)
            else:   # exact discretisation of the first-order lag over dt
                blend = 1.0 - math.exp(-dt / cfg.force_cmd_lag_s)
                px, py, pz = self._force_produced_b
                self._force_produced_b = (px + blend * (fx - px), py + blend * (fy - py),
                                          pz + blend * (fz - pz))
            fx, fy, fz = self._force_produced_b
        ax, ay, az = accel.tolist()
        bx, by, bz = self._x[ACCEL_BIAS].tolist()
        zx, zy, zz = rotate_tuple(self._output_q(), (m * (ax - bx) - fx, m * (ay - by) - fy,
                                                     m * (az - bz) - fz))
        # per-sample accelerometer noise variance (N^2 f / 2) plus the bias uncertainty
        P = self._P
        r = m * m * (TWO_SIDED * cfg.accel_noise_m_s2_sqrt_hz ** 2 / dt
                     + (P.item(12, 12) + P.item(13, 13) + P.item(14, 14)) / 3.0)
        gain = self._force_var / (self._force_var + r)
        wx, wy, wz = self._force_w
        self._force_w = (wx + gain * (zx - wx), wy + gain * (zy - wy), wz + gain * (zz - wz))
        self._force_var *= 1.0 - gain

"""What the estimator publishes every tick: the state estimate and its health."""

from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]

# Index blocks of the 15-element error state and of its covariance.
POS = slice(0, 3)
VEL = slice(3, 6)
ATT = slice(6, 9)      # rotation vector on the right of the nominal quaternion (body frame)
GYRO_BIAS = slice(9, 12)
ACCEL_BIAS = slice(12, 15)
STATE_DIM = 15


class HealthFlag(enum.Flag):
    """Conditions the flight session reacts to (several can hold at once)."""

    OK = 0
    NOT_INITIALIZED = enum.auto()   # still waiting for the rest period and the first poses
    MOCAP_STALE = enum.auto()       # no accepted pose for mocap_stale_s: IMU-only dead reckoning
    DIVERGED = enum.auto()          # non-finite state or sigma above the configured limits
    GYRO_BIAS_OUT_OF_RANGE = enum.auto()
    ACCEL_BIAS_OUT_OF_RANGE = enum.auto()


@dataclass(frozen=True, slots=True)
class EstimatorHealth:
    """Flags plus the counters behind them."""

    flags: HealthFlag
    mocap_age_s: float            # since the capture time of the last accepted pose (inf: none)
    poses_accepted: int
    poses_rejected: int           # by the Mahalanobis gate
    consecutive_rejections: int
    poses_too_old: int            # captured before the history window: dropped
    resets: int                   # position/attitude re-seeded from MoCap after repeated rejects
    covariance_repairs: int       # Cholesky failures repaired by inflating the diagonal
    imu_out_of_order: int         # samples with a non-increasing timestamp: dropped
    imu_invalid: int              # samples with a non-finite value: dropped
    poses_invalid: int            # non-finite position or degenerate quaternion: dropped
    last_nis: float               # normalised innovation squared of the last pose (nan: none)

    @property
    def ok(self) -> bool:
        return self.flags == HealthFlag.OK


@dataclass(frozen=True, slots=True)
class StateEstimate:
    """The full state at ``t_s`` (IMU clock). World z up, q_wb body->world (w, x, y, z).

    ``cov`` is the 15x15 covariance of the error state [p, v, dtheta, b_g, b_a] (dtheta in the
    body frame, rad). ``force_ext_w_n`` is the external-force observer's estimate (zeros when
    the observer is off) and ``force_ext_sigma_n`` its 1-sigma per axis.
    """

    t_s: float
    pos_w_m: FloatArray
    vel_w_m_s: FloatArray
    q_wb: FloatArray
    omega_b_rad_s: FloatArray
    gyro_bias_rad_s: FloatArray
    accel_bias_m_s2: FloatArray
    cov: FloatArray
    force_ext_w_n: FloatArray
    force_ext_sigma_n: float
    health: EstimatorHealth

    @property
    def pos_sigma_m(self) -> FloatArray:
        return np.sqrt(np.diag(self.cov)[POS])

    @property
    def vel_sigma_m_s(self) -> FloatArray:
        return np.sqrt(np.diag(self.cov)[VEL])

    @property
    def att_sigma_rad(self) -> FloatArray:
        return np.sqrt(np.diag(self.cov)[ATT])

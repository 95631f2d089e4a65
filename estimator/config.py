"""Estimator configuration: noise densities, gates, health limits; every number with its range.

Defaults: the paper's sensor class (ADXRS620 gyro, MXR9500M-class accelerometer, sub-mm MoCap)
with some margin. Noise densities are one-sided spectral densities ``N`` (unit/sqrt(Hz)), as the
sensor datasheets give them (rms noise = N sqrt(bandwidth)), and the project uses the same
convention everywhere (``sim_backend.sensors`` too): white noise sampled at ``f`` is band-limited
to the Nyquist frequency ``f / 2``, so one sample has a standard deviation of ``N sqrt(f / 2)``,
and the two-sided density is ``N**2 / 2``: integrated over ``dt`` seconds the noise adds a
variance of ``N**2 / 2 * dt`` (:data:`TWO_SIDED`). The bias random-walk densities follow the
same convention; ``force_walk_n_sqrt_s`` is a model knob, not a sensor figure: the force
variance grows by its square per second.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

from config.schema import ConfigValueError, spec

#: two-sided / one-sided spectral density: the variance a white noise of one-sided density N
#: adds per second of integration is ``TWO_SIDED * N**2``; one sample at rate f has variance
#: ``TWO_SIDED * N**2 * f``.
TWO_SIDED = 0.5


@dataclass(frozen=True)
class EstimatorConfig:
    """Error-state UKF tuning and health limits (schema ``estimator``)."""

    # -- IMU and bias model -------------------------------------------------------------------
    gyro_noise_rad_s_sqrt_hz: float = spec(1e-3, gt=0.0, le=1.0,
                                           doc="gyro white-noise density")
    accel_noise_m_s2_sqrt_hz: float = spec(3e-3, gt=0.0, le=10.0,
                                           doc="accelerometer white-noise density")
    gyro_bias_walk_rad_s2_sqrt_hz: float = spec(1e-4, gt=0.0, le=1.0,
                                                doc="gyro-bias random-walk density")
    accel_bias_walk_m_s3_sqrt_hz: float = spec(1e-3, gt=0.0, le=10.0,
                                               doc="accelerometer-bias random-walk density")
    imu_integration: Literal["trapezoid", "hold"] = spec(
        "trapezoid", doc="input over (t_prev, t]: mean of both samples, or the newest one")
    gravity_m_s2: float = spec(9.81, gt=9.0, lt=10.5, doc="gravity; world z is up")
    # -- MoCap ---------------------------------------------------------------------------------
    mocap_pos_sigma_m: float = spec(5e-4, gt=0.0, le=1.0, doc="MoCap position noise (1 sigma)")
    mocap_att_sigma_deg: float = spec(0.15, gt=0.0, le=30.0, doc="MoCap attitude noise (1 sigma)")
    mocap_stale_s: float = spec(0.05, gt=0.0, le=10.0,
                                doc="no accepted pose for this long -> MOCAP_STALE")
    latency_compensation: bool = spec(True, doc="fuse poses at their capture time")
    max_fusion_delay_s: float = spec(
        0.05, ge=0.0, le=1.0,
        doc="the filter runs behind the newest IMU sample by the smallest recent MoCap latency, "
            "at most this much (an output predictor carries the estimate to the newest sample), "
            "so that poses are fused when they arrive instead of replaying the IMU; "
            "0: the filter stays at the newest sample and every late pose is replayed")
    latency_window: int = spec(32, ge=1, le=10000,
                               doc="poses whose latencies set the horizon (about the smallest)")
    history_s: float = spec(0.25, gt=0.0, le=2.0,
                            doc="how far back a late pose can still be fused")
    max_imu_rate_hz: float = spec(1000.0, gt=0.0, le=10000.0, doc="sizes the history ring")
    # -- gating ---------------------------------------------------------------------------------
    # (the upper bounds from here on are sanity caps: a value past them is a typo, not a tuning;
    # a gate over chi2 = 1000 accepts anything, sigmas beyond metres/radians start the filter lost)
    gate_nis: float = spec(22.46, ge=1.0, le=1000.0, doc="chi2 gate on the 6-D pose innovation "
                           "(22.46 = chi2_6(0.999))")
    max_consecutive_rejections: int = spec(25, ge=1, le=100000,
                                           doc="then reset position and attitude to MoCap")
    # -- sigma points (van der Merwe scaled) ----------------------------------------------------
    sigma_alpha: float = spec(0.5, gt=0.0, le=1.0)
    sigma_beta: float = spec(2.0, ge=0.0, le=10.0)  # 2 is optimal for Gaussians
    sigma_kappa: float = spec(0.0, ge=0.0, le=100.0)
    # -- initialisation -------------------------------------------------------------------------
    init_rest_s: float = spec(0.5, gt=0.0, le=60.0, doc="rest period that starts the filter")
    init_min_poses: int = spec(10, ge=1, le=100000, doc="MoCap poses needed during the rest period")
    rest_gyro_std_rad_s: float = spec(0.05, gt=0.0, le=1.0,
                                      doc="above this the vehicle is not at rest")
    rest_accel_std_m_s2: float = spec(1.0, gt=0.0, le=10.0,
                                      doc="above this the vehicle is not at rest")
    rest_pos_spread_m: float = spec(0.01, gt=0.0, le=1.0,
                                    doc="MoCap spread allowed during the rest")
    init_pos_sigma_m: float = spec(0.01, gt=0.0, le=10.0)
    init_vel_sigma_m_s: float = spec(0.05, gt=0.0, le=10.0)
    init_att_sigma_deg: float = spec(2.0, gt=0.0, le=90.0)
    init_gyro_bias_sigma_rad_s: float = spec(0.02, gt=0.0, le=1.0)
    init_accel_bias_sigma_m_s2: float = spec(0.2, gt=0.0, le=10.0)
    # -- covariance health ----------------------------------------------------------------------
    min_variance: float = spec(1e-14, gt=0.0, le=1e-6, doc="floor of every diagonal element of P")
    max_pos_sigma_m: float = spec(10.0, gt=0.0, le=1000.0, doc="cap of the position sigma")
    diverged_pos_sigma_m: float = spec(0.5, gt=0.0, le=100.0, doc="above this -> DIVERGED")
    diverged_att_sigma_deg: float = spec(10.0, gt=0.0, le=180.0, doc="above this -> DIVERGED")
    max_gyro_bias_rad_s: float = spec(0.2, gt=0.0, le=10.0,
                                      doc="above this -> GYRO_BIAS_OUT_OF_RANGE")
    max_accel_bias_m_s2: float = spec(1.5, gt=0.0, le=20.0,
                                      doc="above this -> ACCEL_BIAS_OUT_OF_RANGE")
    # -- external-force observer ----------------------------------------------------------------
    force_observer: bool = spec(True, doc="estimate the unmodelled external force")
    mass_kg: float = spec(3.1, ge=0.1, le=100.0, doc="vehicle mass (paper Table I)")
    force_walk_n_sqrt_s: float = spec(0.4, gt=0.0, le=100.0,
                                      doc="random-walk density of the external force")
    init_force_sigma_n: float = spec(2.0, gt=0.0, le=1000.0)
    force_cmd_lag_s: float = spec(0.0, ge=0.0, le=1.0,
                                  doc="first-order lag from commanded to produced body force "
                                      "(rotor dynamics); 0: the command is produced at once")

    def __post_init__(self) -> None:
        if self.diverged_pos_sigma_m >= self.max_pos_sigma_m:
            raise ConfigValueError("diverged_pos_sigma_m", "must be below max_pos_sigma_m")
        n = 15
        if self.sigma_alpha ** 2 * (n + self.sigma_kappa) <= 0.0:
            raise ConfigValueError("sigma_alpha", "alpha^2 (n + kappa) must be positive")
        if self.history_s * self.max_imu_rate_hz < 2.0:
            raise ConfigValueError("history_s", "must hold at least two IMU periods")
        if self.max_fusion_delay_s >= self.history_s:
            raise ConfigValueError("max_fusion_delay_s", "must be below history_s (a pose "
                                   "later than the horizon is replayed from the history)")

    @property
    def history_len(self) -> int:
        """Capacity of the ring of past states."""
        return math.ceil(self.history_s * self.max_imu_rate_hz) + 2

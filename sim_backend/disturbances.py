"""Named disturbance presets of the simulator (``config/disturbances/*.yaml``).

A preset gathers everything the simulator adds to the controller's model (paper Sec. III-A
"Discussion on model simplifications" and the project's paper notes): rotor dynamics, the Cardan
drive train, misalignment, thrust spread, tether and Ornstein-Uhlenbeck forces, sensor noise and,
until a state estimator is plugged into ``fasthex simulate``, the noise put on the true state fed
to the controller. ``ideal`` switches all of it off; ``paper-calibrated`` reproduces the
paper's measured tracking errors.
"""

from __future__ import annotations

from dataclasses import dataclass

from config.schema import spec

DISTURBANCES_SCHEMA = "fasthex.disturbances"


@dataclass(frozen=True, kw_only=True)
class DisturbancePreset:
    name: str
    description: str = ""
    physics_rate_hz: float = spec(1000.0, ge=100.0, le=20000.0, doc="RK4 rate")
    rotor_time_constant_s: float = spec(0.03, ge=0.0, le=1.0, doc="first-order rotor lag")
    rotor_inertia_kg_m2: float = spec(1.5e-4, ge=0.0, le=0.01, doc="propeller + bell, gyroscopic")
    cardan_chain: bool = spec(True, doc="per-propeller tilts through the Cardan chain")
    misalignment_deg: float = spec(0.5, ge=0.0, le=10.0, doc="sigma of fixed Ry(beta_i) per prop")
    thrust_coeff_spread: float = spec(0.03, ge=0.0, le=0.5, doc="c_f_i uniform in c_f (1 +- x)")
    tether_force_n: float = spec(0.3, ge=0.0, le=20.0, doc="pull towards the tether anchor")
    tether_anchor_w_m: tuple[float, float, float] = spec((-3.0, 0.0, 0.0))
    ou_force_rms_n: float = spec(0.3, ge=0.0, le=20.0, doc="rms of the OU force vector (N)")
    ou_force_tau_s: float = spec(1.0, gt=0.0, le=100.0, doc="OU correlation time")
    gyro_noise_density_rad_s_rthz: float = spec(8.7e-4, ge=0.0, le=0.1)
    gyro_bias_sigma_rad_s: float = spec(0.005, ge=0.0, le=1.0)
    accel_noise_density_m_s2_rthz: float = spec(2e-3, ge=0.0, le=1.0)
    accel_bias_sigma_m_s2: float = spec(0.05, ge=0.0, le=5.0)
    imu_rate_hz: float = spec(500.0, gt=0.0, le=10000.0)
    mocap_rate_hz: float = spec(100.0, gt=0.0, le=1000.0)
    mocap_pos_noise_m: float = spec(5e-4, ge=0.0, le=0.1)
    mocap_att_noise_rad: float = spec(2e-3, ge=0.0, le=0.5)
    mocap_latency_s: float = spec(0.01, ge=0.0, le=1.0)
    mocap_dropout_prob: float = spec(0.01, ge=0.0, le=1.0)
    estimate_pos_noise_m: float = spec(1e-3, ge=0.0, le=0.1, doc="white noise on the fed state")
    estimate_vel_noise_m_s: float = spec(5e-3, ge=0.0, le=1.0)
    estimate_att_noise_rad: float = spec(2e-3, ge=0.0, le=0.5)
    estimate_rate_noise_rad_s: float = spec(0.01, ge=0.0, le=1.0)

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

from config.schema import ConfigValueError, spec

DISTURBANCES_SCHEMA = "fasthex.disturbances"

#: shortest time constant the simulator takes as a lag (s): 1 ms is faster than any rotor or
#: wind; smaller values are typos (1e-12) and stiffen the RK4 step. 0 means "no lag" where noted
MIN_TIME_CONSTANT_S = 1e-3
#: |x|, |y|, |z| of the tether anchor (m), the same sane workspace as the missions
WORKSPACE_M = 100.0


@dataclass(frozen=True, kw_only=True)
class DisturbancePreset:
    name: str
    description: str = ""
    # at least the 500 Hz control rate's order; 20 kHz is beyond any need for RK4
    physics_rate_hz: float = spec(1000.0, ge=100.0, le=20000.0, doc="RK4 rate")
    # 0: instant rotors (the ideal preset); otherwise >= 1 ms (MIN_TIME_CONSTANT_S)
    rotor_time_constant_s: float = spec(0.03, ge=0.0, le=1.0, doc="first-order rotor lag (0: none)")
    # a 1 m propeller weighs ~1 kg: m D^2 / 12 ~ 0.08; 0.01 is beyond the props we fly
    rotor_inertia_kg_m2: float = spec(1.5e-4, ge=0.0, le=0.01, doc="propeller + bell, gyroscopic")
    cardan_chain: bool = spec(True, doc="per-propeller tilts through the Cardan chain")
    # 10 deg of a propeller's axis off its arm is a broken mount, not a tolerance
    misalignment_deg: float = spec(0.5, ge=0.0, le=10.0, doc="sigma of fixed Ry(beta_i) per prop")
    # +-50 % between rotors of one airframe would be a damaged propeller
    thrust_coeff_spread: float = spec(0.03, ge=0.0, le=0.5, doc="c_f_i uniform in c_f (1 +- x)")
    # 20 N is two thirds of the prototype's weight: a tether that pulls more is an anchor
    tether_force_n: float = spec(0.3, ge=0.0, le=20.0, doc="pull towards the tether anchor")
    tether_anchor_w_m: tuple[float, float, float] = spec((-3.0, 0.0, 0.0), ge=-WORKSPACE_M,
                                                         le=WORKSPACE_M)
    ou_force_rms_n: float = spec(0.3, ge=0.0, le=20.0, doc="rms of the OU force vector (N)")
    # a correlation time, so >= 1 ms; 100 s is a steady wind already
    ou_force_tau_s: float = spec(1.0, ge=MIN_TIME_CONSTANT_S, le=100.0,
                                 doc="OU correlation time")
    # noise and bias caps: 10..100 times the worst MEMS parts (0.1 rad/s/sqrt(Hz) gyro noise
    # is a 6 deg/s rms at 500 Hz)
    gyro_noise_density_rad_s_rthz: float = spec(8.7e-4, ge=0.0, le=0.1)
    gyro_bias_sigma_rad_s: float = spec(0.005, ge=0.0, le=1.0)
    accel_noise_density_m_s2_rthz: float = spec(2e-3, ge=0.0, le=1.0)
    accel_bias_sigma_m_s2: float = spec(0.05, ge=0.0, le=5.0)
    # simulate's loop runs at this IMU rate: 100 Hz .. 2 kHz as in the sessions. In fly the
    # emulated board samples at the rate its host sets (the session's backend.imu_rate_hz),
    # each sample's noise from the densities above at that rate
    imu_rate_hz: float = spec(500.0, ge=100.0, le=2000.0)
    # MoCap systems run at 30 Hz (webcams) .. 1 kHz (OptiTrack Prime at low resolution)
    mocap_rate_hz: float = spec(100.0, ge=10.0, le=1000.0)
    mocap_pos_noise_m: float = spec(5e-4, ge=0.0, le=0.1)
    mocap_att_noise_rad: float = spec(2e-3, ge=0.0, le=0.5)
    # the estimator fuses poses at most a few hundred ms late (its history)
    mocap_latency_s: float = spec(0.01, ge=0.0, le=0.5)
    # more than half of the frames lost is a MoCap outage, rehearsed with faults instead
    mocap_dropout_prob: float = spec(0.01, ge=0.0, le=0.5)
    estimate_pos_noise_m: float = spec(1e-3, ge=0.0, le=0.1, doc="white noise on the fed state")
    estimate_vel_noise_m_s: float = spec(5e-3, ge=0.0, le=1.0)
    estimate_att_noise_rad: float = spec(2e-3, ge=0.0, le=0.5)
    estimate_rate_noise_rad_s: float = spec(0.01, ge=0.0, le=1.0)

    def __post_init__(self) -> None:
        step_s = 1.0 / self.physics_rate_hz
        tau = self.rotor_time_constant_s
        if tau != 0.0 and tau < max(MIN_TIME_CONSTANT_S, step_s):
            raise ConfigValueError(
                "rotor_time_constant_s",
                f"expected 0 (no lag) or >= {max(MIN_TIME_CONSTANT_S, step_s):g} s (1 ms and one "
                f"physics step), got {tau:g}")
        if self.ou_force_tau_s < 2.0 * step_s:
            raise ConfigValueError(
                "ou_force_tau_s", f"expected >= two physics steps ({2.0 * step_s:g} s), "
                f"got {self.ou_force_tau_s:g}")
        # the sensors are sampled on physics steps: a faster sensor than the physics is aliased
        for key, rate in (("imu_rate_hz", self.imu_rate_hz),
                          ("mocap_rate_hz", self.mocap_rate_hz)):
            if rate > self.physics_rate_hz:
                raise ConfigValueError(key, f"must not exceed physics_rate_hz "
                                       f"({self.physics_rate_hz:g} Hz), got {rate:g}")

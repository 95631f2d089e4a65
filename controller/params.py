"""Vehicle parameters (the paper's Table I and the controller constants), as frozen dataclasses.

The YAML files under ``config/vehicles/`` map one to one onto :class:`VehicleParams` (loaded by
``groundstation.configs.load_vehicle``). Every field carries its unit in its name; ranges are
declared with :func:`config.schema.spec` and cross-field consistency is checked in
``__post_init__``, so an inconsistent file is refused before anything is opened.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from config.schema import ConfigValueError, spec

Vec3 = tuple[float, float, float]

VEHICLE_SCHEMA = "fasthex.vehicle"


@dataclass(frozen=True, kw_only=True)
class GeometryParams:
    """Rotor layout: six rotors on a ring, 60 deg apart, rotor 1 on the body x axis."""

    arm_length_m: float = spec(ge=0.05, le=2.0, doc="distance O_B -> propeller centre, l")
    ring_diameter_m: float = spec(ge=0.05, le=4.0, doc="outer ring diameter, d")
    propeller_diameter_m: float = spec(ge=0.02, le=1.5, doc="propeller diameter")

    def __post_init__(self) -> None:
        if self.ring_diameter_m < 2.0 * self.arm_length_m * 0.9:
            raise ConfigValueError(
                "ring_diameter_m",
                f"a ring of {self.ring_diameter_m} m cannot hold arms of {self.arm_length_m} m "
                f"(expected >= {1.8 * self.arm_length_m:.3f} m)",
            )


@dataclass(frozen=True, kw_only=True)
class RotorParams:
    """Propeller and BL-Ctrl limits (paper Table I)."""

    min_spin_hz: float = spec(ge=0.0, le=500.0, doc="lowest commanded spin rate in flight")
    max_spin_hz: float = spec(gt=0.0, le=500.0, doc="highest commanded spin rate")
    thrust_coeff_n_per_hz2: float = spec(gt=0.0, le=1.0, doc="c_f: thrust = c_f w^2, w in Hz")
    drag_coeff_m: float = spec(ge=0.0, le=1.0, doc="c_f^tau: drag torque = c_f^tau * thrust")
    first_rotor_ccw: bool = spec(True, doc="propeller 1 spins counter-clockwise (paper)")

    def __post_init__(self) -> None:
        if self.min_spin_hz >= self.max_spin_hz:
            raise ConfigValueError(
                "min_spin_hz",
                f"must be below max_spin_hz ({self.max_spin_hz:g} Hz), got {self.min_spin_hz:g}",
            )

    @property
    def min_thrust_n(self) -> float:
        return self.thrust_coeff_n_per_hz2 * self.min_spin_hz**2

    @property
    def max_thrust_n(self) -> float:
        return self.thrust_coeff_n_per_hz2 * self.max_spin_hz**2


@dataclass(frozen=True, kw_only=True)
class TiltParams:
    """The synchronised tilt drive: one servo, worm gears and Cardan chains."""

    max_tilt_deg: float = spec(ge=0.0, le=90.0, doc="largest tilt the planner commands")
    mechanical_limit_deg: float = spec(ge=0.0, le=90.0, doc="hard stop of the mechanism")
    max_rate_deg_s: float = spec(ge=0.0, le=360.0, doc="tilt rate limit")
    worm_ratio: float = spec(gt=0.0, le=1.0, doc="k: tilt / drive-shaft angle (0.05 = 20:1)")
    cardan_bend_deg: float = spec(ge=0.0, lt=90.0, doc="bending angle beta of each Cardan joint")

    def __post_init__(self) -> None:
        if self.max_tilt_deg > self.mechanical_limit_deg:
            raise ConfigValueError(
                "max_tilt_deg",
                f"exceeds the mechanical limit ({self.mechanical_limit_deg:g} deg), "
                f"got {self.max_tilt_deg:g}",
            )

    @property
    def max_tilt_rad(self) -> float:
        return math.radians(self.max_tilt_deg)


@dataclass(frozen=True, kw_only=True)
class ControllerParams:
    """Gains and constants of the full-pose geometric controller (paper Sec. IV, Table I)."""

    kp_pos: Vec3 = spec(ge=0.0, doc="K_p, N/m")
    ki_pos: Vec3 = spec(ge=0.0, doc="K_pi, N/(m s)")
    kv_pos: Vec3 = spec(ge=0.0, doc="K_v, N s/m")
    kr_att: Vec3 = spec(ge=0.0, doc="K_R, N m/rad")
    ki_att: Vec3 = spec(ge=0.0, doc="K_Ri, N m/(rad s)")
    kw_att: Vec3 = spec(ge=0.0, doc="K_w, N m s/rad")
    pos_integral_limit_m_s: Vec3 = spec(gt=0.0, doc="|e_pi| bound per axis (anti-windup)")
    att_integral_limit_rad_s: Vec3 = spec(gt=0.0, doc="|e_Ri| bound per axis (anti-windup)")
    bisection_iterations: int = spec(20, ge=1, le=60, doc="n_it of Algorithm 1")
    tikhonov_k1: float = spec(ge=0.0, doc="gamma(alpha) = k1 / (alpha + k2), alpha in rad")
    tikhonov_k2_rad: float = spec(gt=0.0, doc="k2 of gamma(alpha), rad")
    lateral_bound_scale: float = spec(gt=0.0, le=1.0, doc="conservative gain on r_xy(alpha)")
    lateral_bound_dead_zone_deg: float = spec(ge=0.0, le=30.0, doc="r_xy = 0 below this tilt")
    attitude_feedforward: bool = spec(
        False, doc="add the reference angular velocity (not in the paper; paper-notes item 9)"
    )
    force_feedforward: bool = spec(
        False, doc="subtract the estimated external force from f_r (not in the paper; the "
        "estimator's force observer); off = the paper's controller"
    )
    force_feedforward_limit_n: float = spec(
        3.0, gt=0.0, le=100.0, doc="norm clip of the fed-forward force (N): bounds what a "
        "wrong estimate, e.g. the ground's reaction before takeoff, can do"
    )


@dataclass(frozen=True, kw_only=True)
class VehicleParams:
    """One airframe: everything the model, controller and simulator need to know about it."""

    name: str
    description: str = spec(doc="free text")
    mass_kg: float = spec(gt=0.0, le=100.0, doc="total mass m")
    inertia_diag_kg_m2: Vec3 = spec(gt=0.0, le=100.0, doc="diagonal of J about O_B, body")
    gravity_m_s2: float = spec(9.81, ge=9.7, le=9.9, doc="local gravitational acceleration")
    geometry: GeometryParams = spec()
    rotors: RotorParams = spec()
    tilt: TiltParams = spec()
    controller: ControllerParams = spec()

    def __post_init__(self) -> None:
        ixx, iyy, izz = self.inertia_diag_kg_m2
        if ixx + iyy < izz or ixx + izz < iyy or iyy + izz < ixx:
            raise ConfigValueError(
                "inertia_diag_kg_m2",
                "principal moments violate the triangle inequality (not a physical body)",
            )
        max_lift_n = 6.0 * self.rotors.max_thrust_n * math.cos(self.tilt.max_tilt_rad)
        weight_n = self.mass_kg * self.gravity_m_s2
        if max_lift_n < 1.2 * weight_n:
            raise ConfigValueError(
                "mass_kg",
                f"weight {weight_n:.1f} N needs >= 20 % thrust margin, but the rotors lift at "
                f"most {max_lift_n:.1f} N at the largest tilt",
            )
        min_lift_n = 6.0 * self.rotors.min_thrust_n
        if min_lift_n > 0.8 * weight_n:
            raise ConfigValueError(
                "rotors.min_spin_hz",
                f"the idle thrust {min_lift_n:.1f} N leaves too little authority below the "
                f"weight {weight_n:.1f} N (expected <= 80 % of it)",
            )

    @property
    def weight_n(self) -> float:
        return self.mass_kg * self.gravity_m_s2

"""Vehicle parameters (the paper's Table I and the controller constants), as frozen dataclasses.

The YAML files under ``config/vehicles/`` map one to one onto :class:`VehicleParams` (loaded by
``groundstation.configs.load_vehicle``). Every field carries its unit in its name; ranges are
declared with :func:`config.schema.spec` and cross-field consistency is checked in
``__post_init__``, so an inconsistent file is refused before anything is opened.

The bounds are physical, not just "positive": each says why in a comment. The closed-loop checks
treat each axis as the linearised loop the gains set: position ``m e'' + K_v e' + K_p e = 0``
(natural frequency ``sqrt(K_p / m)``, damping ``K_v / (2 sqrt(K_p m))``) and attitude
``J e'' + K_w e' + K_R e = 0`` (``sqrt(K_R / J)``, ``K_w / (2 sqrt(K_R J))``); with the integral
term the cubic ``m s^3 + K_v s^2 + K_p s + K_i`` must stay Hurwitz (``K_v K_p > m K_i``).

A fixed-tilt airframe is written with ``tilt.min_tilt_deg == tilt.max_tilt_deg`` and
``max_rate_deg_s: 0``; a zero rate is refused for a tilt range (it would pin alpha for ever).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from config.schema import ConfigValueError, spec

Vec3 = tuple[float, float, float]

VEHICLE_SCHEMA = "fasthex.vehicle"

#: air density at sea level, 15 degC (kg/m^3): turns c_f into the propeller's thrust coefficient
AIR_DENSITY_KG_M3 = 1.225
#: C_T = c_f / (rho D^4) (c_f per Hz^2) of real propellers lies in ~0.05..0.2; outside this
#: window the thrust coefficient does not belong to a propeller of that diameter
THRUST_COEFF_CT_RANGE = (0.02, 0.4)
#: drag torque per thrust over the diameter (C_Q / C_T): ~0.06 for the shipped propellers
DRAG_PER_DIAMETER_RANGE = (0.005, 0.3)
#: the loops' damping ratio: below 0.2 a step overshoots by > 50 % and rings (near-zero
#: damping = an oscillating vehicle); above 5 one pole is so slow the loop barely acts
DAMPING_RANGE = (0.2, 5.0)
#: the position loop's natural frequency (rad/s): below 0.5 it cannot hold against a 0.3 N
#: gust within metres; above 30 it is faster than the 30 ms rotor lag can follow
POS_BANDWIDTH_RAD_S = (0.5, 30.0)
#: the attitude loop's natural frequency (rad/s): above 150 it is beyond a 500 Hz loop
#: (w dt = 0.3) and any rotor lag
ATT_BANDWIDTH_RAD_S = (1.0, 150.0)
#: the MX-28's no-load speed at 12 V (55 rpm = 330 deg/s) drives the tilt through the worms
SERVO_MAX_SPEED_DEG_S = 330.0


@dataclass(frozen=True, kw_only=True)
class GeometryParams:
    """Rotor layout: six rotors on a ring, 60 deg apart, rotor 1 on the body x axis."""

    # 5 cm arms carry 1 inch props (the smallest multirotors); 2 m is beyond any lab vehicle
    arm_length_m: float = spec(ge=0.05, le=2.0, doc="distance O_B -> propeller centre, l")
    ring_diameter_m: float = spec(ge=0.05, le=4.0, doc="outer ring diameter, d")
    propeller_diameter_m: float = spec(ge=0.02, le=1.5, doc="propeller diameter")

    def __post_init__(self) -> None:
        # neighbouring hubs are one arm length apart (60 deg on a ring of radius l); a little
        # overlap is possible with tilted props, beyond 1.2 l the blades would strike
        if self.propeller_diameter_m > 1.2 * self.arm_length_m:
            raise ConfigValueError(
                "propeller_diameter_m",
                f"propellers of {self.propeller_diameter_m:g} m overlap on arms of "
                f"{self.arm_length_m:g} m (expected <= {1.2 * self.arm_length_m:.3f} m)",
            )
        if self.ring_diameter_m < 2.0 * self.arm_length_m * 0.9:
            raise ConfigValueError(
                "ring_diameter_m",
                f"a ring of {self.ring_diameter_m} m cannot hold arms of {self.arm_length_m} m "
                f"(expected >= {1.8 * self.arm_length_m:.3f} m)",
            )


@dataclass(frozen=True, kw_only=True)
class RotorParams:
    """Propeller and BL-Ctrl limits (paper Table I)."""

    # 500 Hz = 30000 rpm, the fastest small brushless props; the BL-Ctrl speed field tops there
    min_spin_hz: float = spec(ge=0.0, le=500.0, doc="lowest commanded spin rate in flight")
    # below 5 Hz (300 rpm) a propeller gives no usable thrust
    max_spin_hz: float = spec(ge=5.0, le=500.0, doc="highest commanded spin rate")
    # checked against the propeller diameter in VehicleParams (C_T window)
    thrust_coeff_n_per_hz2: float = spec(gt=0.0, le=1.0, doc="c_f: thrust = c_f w^2, w in Hz")
    # every propeller has drag torque: the yaw authority at zero tilt comes from it
    drag_coeff_m: float = spec(gt=0.0, le=1.0, doc="c_f^tau: drag torque = c_f^tau * thrust")
    first_rotor_ccw: bool = spec(
        True, doc="propeller 1 spins counter-clockwise (paper); false only for tilts below "
        "atan(c_tau/l)")

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

    # at 90 deg the rotors lift nothing: the thrust-margin check in VehicleParams bounds it
    max_tilt_deg: float = spec(ge=0.0, le=90.0, doc="largest tilt the planner commands")
    mechanical_limit_deg: float = spec(ge=0.0, le=90.0, doc="hard stop of the mechanism")
    # 0 only for a fixed tilt (min == max); otherwise >= 0.5 deg/s: slower, a 30 deg step
    # takes over a minute, longer than any experiment segment
    max_rate_deg_s: float = spec(ge=0.0, le=360.0, doc="tilt rate limit (0: fixed tilt)")
    # 200:1 is the steepest worm reduction sold; 1 = direct drive
    worm_ratio: float = spec(ge=0.005, le=1.0, doc="k: tilt / drive-shaft angle (0.05 = 20:1)")
    # universal joints bind beyond ~45 deg of bend (and their velocity ripple explodes)
    cardan_bend_deg: float = spec(ge=0.0, le=45.0, doc="bending angle beta of each Cardan joint")
    min_tilt_deg: float = spec(
        0.0, ge=0.0, le=90.0, doc="smallest tilt the planner commands; equal to max_tilt_deg "
        "for a fixed-tilt airframe")

    def __post_init__(self) -> None:
        if self.min_tilt_deg > self.max_tilt_deg:
            raise ConfigValueError(
                "min_tilt_deg",
                f"must not exceed max_tilt_deg ({self.max_tilt_deg:g} deg), "
                f"got {self.min_tilt_deg:g}",
            )
        if self.is_fixed and self.max_rate_deg_s != 0.0:
            raise ConfigValueError(
                "max_rate_deg_s",
                f"a fixed tilt (min_tilt_deg = max_tilt_deg = {self.max_tilt_deg:g}) does not "
                f"move; expected 0, got {self.max_rate_deg_s:g}",
            )
        if not self.is_fixed and self.max_rate_deg_s < 0.5:
            raise ConfigValueError(
                "max_rate_deg_s",
                f"expected >= 0.5 deg/s for a tilt range of {self.min_tilt_deg:g} to "
                f"{self.max_tilt_deg:g} deg, got {self.max_rate_deg_s:g} (a fixed tilt: set "
                "min_tilt_deg equal to max_tilt_deg)",
            )
        if self.max_rate_deg_s > SERVO_MAX_SPEED_DEG_S * self.worm_ratio:
            raise ConfigValueError(
                "max_rate_deg_s",
                f"the servo (<= {SERVO_MAX_SPEED_DEG_S:g} deg/s) drives at most "
                f"{SERVO_MAX_SPEED_DEG_S * self.worm_ratio:.1f} deg/s through a worm ratio of "
                f"{self.worm_ratio:g}, got {self.max_rate_deg_s:g}",
            )
        if self.max_tilt_deg > self.mechanical_limit_deg:
            raise ConfigValueError(
                "max_tilt_deg",
                f"exceeds the mechanical limit ({self.mechanical_limit_deg:g} deg), "
                f"got {self.max_tilt_deg:g}",
            )

    @property
    def max_tilt_rad(self) -> float:
        return math.radians(self.max_tilt_deg)

    @property
    def min_tilt_rad(self) -> float:
        return math.radians(self.min_tilt_deg)

    @property
    def is_fixed(self) -> bool:
        """A fixed-tilt airframe: alpha is min_tilt_deg = max_tilt_deg for the whole flight."""
        return self.min_tilt_deg == self.max_tilt_deg


@dataclass(frozen=True, kw_only=True)
class ControllerParams:
    """Gains and constants of the full-pose geometric controller (paper Sec. IV, Table I)."""

    # Proportional and derivative gains: strictly positive (a zero gain leaves an axis
    # uncontrolled); the pole checks against mass and inertia are in VehicleParams. The caps
    # (1e4 N/m, 1e3 N m/rad) are far above any multirotor's and keep the checks finite.
    kp_pos: Vec3 = spec(gt=0.0, le=1e4, doc="K_p, N/m")
    # integral gains may be 0 (no integral action); the Hurwitz check bounds them from above
    ki_pos: Vec3 = spec(ge=0.0, le=1e4, doc="K_pi, N/(m s)")
    kv_pos: Vec3 = spec(gt=0.0, le=1e4, doc="K_v, N s/m")
    kr_att: Vec3 = spec(gt=0.0, le=1e3, doc="K_R, N m/rad")
    ki_att: Vec3 = spec(ge=0.0, le=1e3, doc="K_Ri, N m/(rad s)")
    kw_att: Vec3 = spec(gt=0.0, le=1e3, doc="K_w, N m s/rad")
    # anti-windup bounds: below 1 mm s / 1 mrad s the integrators do nothing, above
    # 100 m s / 10 rad s they wind up for minutes before they saturate
    pos_integral_limit_m_s: Vec3 = spec(ge=1e-3, le=100.0,
                                        doc="|e_pi| bound per axis (anti-windup)")
    att_integral_limit_rad_s: Vec3 = spec(ge=1e-3, le=10.0,
                                          doc="|e_Ri| bound per axis (anti-windup)")
    # 2^-60 of the bracket is below double precision: more iterations change nothing
    bisection_iterations: int = spec(20, ge=1, le=60, doc="n_it of Algorithm 1")
    # k1 > 0: at alpha = 0 the allocation matrix is singular and needs the regulariser; at
    # alpha = 0 gamma = k1 / k2 is checked below against the allocation's scale
    tikhonov_k1: float = spec(gt=0.0, le=1e-2,
                              doc="gamma(alpha) = k1 / (alpha + k2), alpha in rad")
    # 1 mrad .. 1 rad: k2 sets where gamma falls off; below 1 mrad gamma(0) explodes
    tikhonov_k2_rad: float = spec(ge=1e-3, le=1.0, doc="k2 of gamma(alpha), rad")
    # a scale below 0.1 gives away 90 % of the lateral authority the tilt bought
    lateral_bound_scale: float = spec(ge=0.1, le=1.0, doc="conservative gain on r_xy(alpha)")
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
    # 100 g (a micro hexarotor) .. 100 kg (the heaviest lab multirotors)
    mass_kg: float = spec(ge=0.1, le=100.0, doc="total mass m")
    # 1e-4 kg m^2: 100 g at 3 cm; 100 kg m^2: 100 kg at 1 m; checked against mass and arms
    inertia_diag_kg_m2: Vec3 = spec(ge=1e-4, le=100.0, doc="diagonal of J about O_B, body")
    # Earth's surface spans 9.76 (equator, altitude) .. 9.83 (poles)
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
        # radius of gyration about z against the arms: the motors sit at l, the hub at 0, so
        # sqrt(J_zz / m) lies well inside (0.2 l, 1.5 l) (0.75 l for the prototype)
        gyration_m = math.sqrt(izz / self.mass_kg)
        arm_m = self.geometry.arm_length_m
        if not 0.2 * arm_m <= gyration_m <= 1.5 * arm_m:
            raise ConfigValueError(
                "inertia_diag_kg_m2",
                f"radius of gyration sqrt(J_zz/m) = {gyration_m:.3f} m does not fit a "
                f"{self.mass_kg:g} kg frame with {arm_m:g} m arms (expected "
                f"{0.2 * arm_m:.3f}..{1.5 * arm_m:.3f} m)",
            )
        self._check_rotors()
        self._check_spin_layout()
        self._check_loops()
        upright_lift_n = 6.0 * self.rotors.max_thrust_n
        max_lift_n = upright_lift_n * math.cos(self.tilt.max_tilt_rad)
        weight_n = self.mass_kg * self.gravity_m_s2
        if max_lift_n < 1.2 * weight_n:
            # the key to blame is the one that needs the smaller edit: the mass (down to what
            # the rotors lift at this tilt) or the tilt (down to where they lift this weight;
            # none when they cannot lift it upright either). At 90 deg no thrust is vertical:
            # the tilt, not the mass, makes the file impossible.
            tilt_deg = self.tilt.max_tilt_deg
            fits_deg = (math.degrees(math.acos(1.2 * weight_n / upright_lift_n))
                        if upright_lift_n >= 1.2 * weight_n else None)
            if fits_deg is not None and 1.0 - fits_deg / tilt_deg < 1.0 - max_lift_n / (
                    1.2 * weight_n):
                raise ConfigValueError(
                    "tilt.max_tilt_deg",
                    f"at {tilt_deg:g} deg the rotors lift at most {max_lift_n:.1f} N, but the "
                    f"weight {weight_n:.1f} N needs >= 20 % thrust margin; expected at most "
                    f"{math.floor(fits_deg * 10) / 10:.1f} deg",
                )
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

    def _check_rotors(self) -> None:
        d_m = self.geometry.propeller_diameter_m
        c_t = self.rotors.thrust_coeff_n_per_hz2 / (AIR_DENSITY_KG_M3 * d_m**4)
        lo, hi = THRUST_COEFF_CT_RANGE
        if not lo <= c_t <= hi:
            raise ConfigValueError(
                "rotors.thrust_coeff_n_per_hz2",
                f"means a thrust coefficient C_T = c_f/(rho D^4) = {c_t:.3g} for a "
                f"{d_m:g} m propeller; real propellers have {lo:g}..{hi:g}",
            )
        ratio = self.rotors.drag_coeff_m / d_m
        lo, hi = DRAG_PER_DIAMETER_RANGE
        if not lo <= ratio <= hi:
            raise ConfigValueError(
                "rotors.drag_coeff_m",
                f"drag torque per thrust of {self.rotors.drag_coeff_m:g} m is {ratio:.3g} "
                f"propeller diameters; real propellers have {lo:g}..{hi:g}",
            )

    def _check_spin_layout(self) -> None:
        # Propeller i (tilt sign t_i = (-1)^(i-1)) gives the yaw torque per newton of thrust
        # -t_i (l sin(alpha) + s c_tau cos(alpha)), s = +1 when propeller 1 spins CCW (the paper)
        # and -1 when CW. CCW: both terms add for every alpha >= 0 (they cancel at -3.56 deg,
        # which is why the paper keeps alpha >= 0). CW mirrors that rank loss to +atan(c_tau/l)
        # = +3.56 deg, inside the range, and above it the tilted thrust's yaw torque opposes
        # both the drag torque and the reaction to the rotors' spin-up (-s_i J_r 2 pi dw_i/dt
        # along the axis, the drag's sign): a yaw command first yaws the body the wrong way, a
        # right-half-plane zero at 2 c_f w (l sin a - c_tau cos a) / (J_r 2 pi cos a), ~5 rad/s
        # at 10 deg with the paper-calibrated J_r = 1.5e-4 kg m^2 and 30 ms rotor lag; the
        # paper's yaw gains (K_R 6, K_w 0.5 on J_zz 0.164) are unstable on it from 3.6 to
        # ~27.5 deg. The vehicle file does not know J_r, so any tilt range reaching the
        # cancelling tilt is refused.
        if self.rotors.first_rotor_ccw:
            return
        cancel_deg = math.degrees(math.atan2(self.rotors.drag_coeff_m,
                                             self.geometry.arm_length_m))
        if self.tilt.max_tilt_deg >= cancel_deg:
            raise ConfigValueError(
                "rotors.first_rotor_ccw",
                f"propeller 1 clockwise turns the tilted thrust's yaw torque against the drag "
                f"torque: they cancel at atan(c_tau/l) = {cancel_deg:.2f} deg (no yaw "
                f"authority) and above it the rotors' spin-up reaction yaws the body the wrong "
                f"way first, which the paper's attitude law cannot fly; expected true (the "
                f"paper's layout), or tilt.max_tilt_deg below {cancel_deg:.2f} deg, got false "
                f"with tilts up to {self.tilt.max_tilt_deg:g} deg",
            )

    def _check_loops(self) -> None:
        c = self.controller
        inertia = self.inertia_diag_kg_m2
        att_w_min = math.inf
        for axis in range(3):
            att_w = math.sqrt(c.kr_att[axis] / inertia[axis])
            att_w_min = min(att_w_min, att_w) if axis < 2 else att_w_min
            _check_loop(f"controller.kr_att[{axis}]", f"controller.kw_att[{axis}]",
                        f"controller.ki_att[{axis}]", c.kr_att[axis], c.kw_att[axis],
                        c.ki_att[axis], inertia[axis], "J", ATT_BANDWIDTH_RAD_S)
        for axis in range(3):
            _check_loop(f"controller.kp_pos[{axis}]", f"controller.kv_pos[{axis}]",
                        f"controller.ki_pos[{axis}]", c.kp_pos[axis], c.kv_pos[axis],
                        c.ki_pos[axis], self.mass_kg, "m", POS_BANDWIDTH_RAD_S)
            # at zero tilt the position follows the attitude: it must be the slower loop
            pos_w = math.sqrt(c.kp_pos[axis] / self.mass_kg)
            if pos_w >= att_w_min:
                raise ConfigValueError(
                    f"controller.kp_pos[{axis}]",
                    f"position loop ({pos_w:.1f} rad/s) must be slower than the roll/pitch "
                    f"loop ({att_w_min:.1f} rad/s)",
                )
        # gamma(0) = k1/k2 adds to F^T F, whose yaw entries at zero tilt are ~ (c_f^tau)^2:
        # a larger regulariser would cancel the yaw authority instead of conditioning it
        gamma0 = c.tikhonov_k1 / c.tikhonov_k2_rad
        yaw_scale = self.rotors.drag_coeff_m**2
        if gamma0 > yaw_scale:
            raise ConfigValueError(
                "controller.tikhonov_k1",
                f"gamma(0) = k1/k2 = {gamma0:.3g} swamps the yaw allocation (~ c_f^tau^2 = "
                f"{yaw_scale:.3g}); expected k1 <= {yaw_scale * c.tikhonov_k2_rad:.3g}",
            )

    @property
    def weight_n(self) -> float:
        return self.mass_kg * self.gravity_m_s2


def _check_loop(k_key: str, d_key: str, i_key: str, k: float, d: float, ki: float,
                inertia: float, inertia_name: str, bandwidth: tuple[float, float]) -> None:
    """One linearised axis: natural frequency, damping and the integral's Hurwitz margin."""
    w = math.sqrt(k / inertia)
    if not bandwidth[0] <= w <= bandwidth[1]:
        raise ConfigValueError(
            k_key, f"gives a natural frequency sqrt(k/{inertia_name}) of {w:.3g} rad/s; "
            f"expected {bandwidth[0]:g}..{bandwidth[1]:g} rad/s")
    zeta = d / (2.0 * math.sqrt(k * inertia))
    if not DAMPING_RANGE[0] <= zeta <= DAMPING_RANGE[1]:
        raise ConfigValueError(
            d_key, f"gives a damping ratio of {zeta:.3g}; expected "
            f"{DAMPING_RANGE[0]:g}..{DAMPING_RANGE[1]:g} (near 0 the vehicle oscillates)")
    # Routh-Hurwitz for I s^3 + d s^2 + k s + ki with a factor 2 of margin
    if 2.0 * inertia * ki >= d * k:
        raise ConfigValueError(
            i_key, f"makes the loop unstable: expected < d k / (2 {inertia_name}) = "
            f"{d * k / (2.0 * inertia):.3g}, got {ki:g}")

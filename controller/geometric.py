"""Full-pose geometric control with prioritised position tracking (paper Sec. IV).

One tick, :meth:`GeometricController.step`:

1. position control: ``f_r = m (pdd_r + g e3) - K_p e_p - K_pi e_pi - K_v e_v`` with the
   integral ``e_pi`` clipped per axis (anti-windup); with ``force_feedforward`` on (not in the
   paper) the estimated external force ``F_ext`` is subtracted, clipped to
   ``force_feedforward_limit_n``: the rotors then produce ``f_r - F_ext`` and the two add up
   to ``f_r`` again, so a slowly varying unmodelled force no longer has to be integrated away;
2. ``u_f``: ``f_r`` in the body frame, its lateral part saturated to the cylinder of radius
   ``r_xy(alpha)`` (:class:`controller.model.LateralBound`), the vertical part kept;
3. ``R_d``: Algorithm 1 bisects the angle theta by which b3r turns towards f_r until the lateral
   part of f_r fits the bound, then Rodrigues gives b3d and ``R_d = [b1d b2d b3d]`` with
   ``b2d = b3d x b1r / |.|`` and ``b1d = b2d x b3d`` (normalised, paper-notes item 8);
   ``theta_max = atan2(|b3r x f_r|, b3r . f_r)`` (item 5); f_r = 0 or parallel to b3r gives
   theta = 0, ``|f_r| < r_xy`` clips the square root to 0 (item 6); b3d parallel to b1r falls
   back on b2r;
4. attitude control ``u_tau = w x J w - K_R e_R - K_Ri e_Ri - K_w w`` with the vee-map error
   and a clipped integral (``attitude_feedforward`` in the vehicle config damps
   ``w - R^T R_d w_r`` instead, paper-notes item 9; off by default = the printed law);
5. the Tikhonov wrench mapper (:mod:`controller.wrench`) -> six thrusts -> spin rates
   ``sqrt(f / c_f)`` in Hz, clamped to the rotor limits, with per-rotor saturation flags.

The bisection is done on the vector b3 only (the uavpos form, estimation-notes §6): since k is
orthogonal to b3r, Rodrigues reduces to ``b3d = b3r cos(theta) + (k x b3r) sin(theta)`` and the
feasibility test ``f_r . b3d >= sqrt(|f_r|^2 - r_xy^2)`` to two precomputed dot products.

Everything runs on Python floats (no numpy on the per-tick path); the integrators live in the
explicit :class:`ControllerMemory`. No I/O.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from controller.model import LateralBound, VehicleModel
from controller.params import VehicleParams
from controller.reference import Mat3, Reference, Vec3, VehicleState, quat_to_rot
from controller.wrench import WrenchMapper

Six = tuple[float, float, float, float, float, float]

#: |b3r x f_r| below this fraction of |f_r| counts as "parallel" (theta = 0).
PARALLEL_TOL = 1e-9
#: |f_r| below this (N) counts as zero force.
ZERO_FORCE_N = 1e-9
#: |b3d x b1r| below this means b3d is (nearly) parallel to b1r: fall back on b2r.
SINGULAR_B1_TOL = 1e-6
#: longest step the integrators accept (s): a stalled loop must not dump a huge increment.
MAX_INTEGRATION_STEP_S = 0.05


@dataclass
class ControllerMemory:
    """What the controller remembers between ticks (integrators and the last tick time)."""

    e_pi_m_s: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    e_ri_rad_s: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    last_t_s: float | None = None


@dataclass(frozen=True, slots=True)
class Command:
    """The output of one controller tick, with the intermediate quantities worth plotting."""

    t_s: float
    spin_hz: Six
    thrusts_n: Six
    saturated: tuple[bool, ...]
    f_r_w_n: Vec3
    u_f_b_n: Vec3
    u_tau_b_n_m: Vec3
    r_wd: Mat3
    r_xy_n: float
    theta_rad: float
    alpha_rad: float
    e_r_rad: Vec3

    @property
    def any_saturated(self) -> bool:
        return any(self.saturated)


def bisect_tilt(b3r: Vec3, f_r: Vec3, r_xy_n: float, n_it: int) -> tuple[float, Vec3]:
    """Algorithm 1: the angle theta (rad) by which b3r turns about k = b3r x f_r / |.|.

    Returns ``(theta, b3d)``. Converges to the closed form
    ``max(0, angle(b3r, f_r) - asin(min(1, r_xy / |f_r|)))`` within ``theta_max / 2^(n_it+1)``.
    """
    bx, by, bz = b3r
    fx, fy, fz = f_r
    cx, cy, cz = by * fz - bz * fy, bz * fx - bx * fz, bx * fy - by * fx
    sn = math.sqrt(cx * cx + cy * cy + cz * cz)
    f2 = fx * fx + fy * fy + fz * fz
    fn = math.sqrt(f2)
    if fn < ZERO_FORCE_N or sn <= PARALLEL_TOL * fn:
        return 0.0, b3r
    a = bx * fx + by * fy + bz * fz  # f . b3r
    theta_max = math.atan2(sn, a)
    kx, ky, kz = cx / sn, cy / sn, cz / sn
    # k x b3r: unit, orthogonal to b3r, in the plane of b3r and f_r
    px, py, pz = ky * bz - kz * by, kz * bx - kx * bz, kx * by - ky * bx
    b = px * fx + py * fy + pz * fz  # f . (k x b3r)
    threshold = math.sqrt(max(0.0, f2 - r_xy_n * r_xy_n))
    half = 0.5 * theta_max
    theta = half
    step = half
    cos, sin = math.cos, math.sin
    for _ in range(n_it):
        step *= 0.5
        if a * cos(theta) + b * sin(theta) >= threshold:
            theta -= step
        else:
            theta += step
    c, s = cos(theta), sin(theta)
    return theta, (bx * c + px * s, by * c + py * s, bz * c + pz * s)


def desired_rotation(b3d: Vec3, r_wr: Mat3) -> Mat3:
    """``R_d = [b1d b2d b3d]`` from b3d and the reference's b1r (b2r if b3d ~ parallel b1r)."""
    dx, dy, dz = b3d
    n = math.sqrt(dx * dx + dy * dy + dz * dz)
    dx, dy, dz = dx / n, dy / n, dz / n
    b1x, b1y, b1z = r_wr[0], r_wr[3], r_wr[6]
    ex, ey, ez = dy * b1z - dz * b1y, dz * b1x - dx * b1z, dx * b1y - dy * b1x  # b3d x b1r
    m = math.sqrt(ex * ex + ey * ey + ez * ez)
    if m > SINGULAR_B1_TOL:
        ex, ey, ez = ex / m, ey / m, ez / m
        # b1d = b2d x b3d
        ax, ay, az = ey * dz - ez * dy, ez * dx - ex * dz, ex * dy - ey * dx
    else:
        b2x, b2y, b2z = r_wr[1], r_wr[4], r_wr[7]
        ax, ay, az = b2y * dz - b2z * dy, b2z * dx - b2x * dz, b2x * dy - b2y * dx  # b2r x b3d
        m = math.sqrt(ax * ax + ay * ay + az * az)
        ax, ay, az = ax / m, ay / m, az / m
        ex, ey, ez = dy * az - dz * ay, dz * ax - dx * az, dx * ay - dy * ax  # b3d x b1d
    return (ax, ex, dx, ay, ey, dy, az, ez, dz)


class GeometricController:
    """The paper's controller for one vehicle. Constants here, integrators in ``memory``."""

    def __init__(self, params: VehicleParams, *, model: VehicleModel | None = None,
                 bound: LateralBound | None = None, mapper: WrenchMapper | None = None,
                 memory: ControllerMemory | None = None) -> None:
        self.params = params
        self.model = model if model is not None else VehicleModel(params)
        self.bound = bound if bound is not None else LateralBound.for_model(self.model)
        self.mapper = mapper if mapper is not None else WrenchMapper(self.model)
        self.memory = memory if memory is not None else ControllerMemory()
        c = params.controller
        self._kp, self._ki, self._kv = c.kp_pos, c.ki_pos, c.kv_pos
        self._kr, self._kri, self._kw = c.kr_att, c.ki_att, c.kw_att
        self._pi_lim, self._ri_lim = c.pos_integral_limit_m_s, c.att_integral_limit_rad_s
        self._n_it = c.bisection_iterations
        self._ff = c.attitude_feedforward
        self._force_ff = c.force_feedforward
        self._force_ff_lim = c.force_feedforward_limit_n
        self._m = params.mass_kg
        self._g = params.gravity_m_s2
        self._j = params.inertia_diag_kg_m2
        self._c_f = params.rotors.thrust_coeff_n_per_hz2
        self._w_min = params.rotors.min_spin_hz
        self._w_max = params.rotors.max_spin_hz

    def reset(self) -> None:
        """Forget the integrators (e.g. before a new takeoff)."""
        self.memory = ControllerMemory()

    def step(self, t_s: float, state: VehicleState, ref: Reference, alpha_rad: float,
             force_ext_w_n: Vec3 | None = None) -> Command:
        """One tick: state + reference + measured tilt -> spin-rate command. Updates memory.

        ``force_ext_w_n``: the estimated external force (world, N); used only when the
        vehicle's ``force_feedforward`` is on, ignored otherwise (and when non-finite).
        """
        mem = self.memory
        dt = 0.0 if mem.last_t_s is None else min(max(t_s - mem.last_t_s, 0.0),
                                                  MAX_INTEGRATION_STEP_S)
        mem.last_t_s = t_s
        r = quat_to_rot(state.q_wb)
        rr = quat_to_rot(ref.q_wr)

        # -- position control ------------------------------------------------------------
        p, v, pr, vr, ar = state.pos_w_m, state.vel_w_m_s, ref.pos_w_m, ref.vel_w_m_s, \
            ref.acc_w_m_s2
        kp, ki, kv, lim, epi = self._kp, self._ki, self._kv, self._pi_lim, mem.e_pi_m_s
        f_r = [0.0, 0.0, 0.0]
        for i in range(3):
            ep = p[i] - pr[i]
            e = epi[i] + ep * dt
            epi[i] = e if -lim[i] <= e <= lim[i] else math.copysign(lim[i], e)
            f_r[i] = self._m * ar[i] - kp[i] * ep - ki[i] * epi[i] - kv[i] * (v[i] - vr[i])
        f_r[2] += self._m * self._g
        if self._force_ff and force_ext_w_n is not None:
            ex, ey, ez = force_ext_w_n
            n = math.sqrt(ex * ex + ey * ey + ez * ez)
            if math.isfinite(n):
                s = self._force_ff_lim / n if n > self._force_ff_lim else 1.0
                f_r[0] -= s * ex
                f_r[1] -= s * ey
                f_r[2] -= s * ez
        fx, fy, fz = f_r

        # -- u_f: body-frame force with the cylindric lateral saturation ----------------------
        r_xy = self.bound.radius_n(alpha_rad)
        ubx = r[0] * fx + r[3] * fy + r[6] * fz
        uby = r[1] * fx + r[4] * fy + r[7] * fz
        ubz = r[2] * fx + r[5] * fy + r[8] * fz
        lat = math.sqrt(ubx * ubx + uby * uby)
        if lat > r_xy:
            s = r_xy / lat
            ubx, uby = ubx * s, uby * s
        u_f = (ubx, uby, ubz)

        # -- R_d by bisection + Rodrigues ----------------------------------------------------
        theta, b3d = bisect_tilt((rr[2], rr[5], rr[8]), (fx, fy, fz), r_xy, self._n_it)
        rd = desired_rotation(b3d, rr)

        # -- attitude control ----------------------------------------------------------------
        # E = R_d^T R_B; e_R = 1/2 vee(E - E^T)
        e32 = rd[2] * r[1] + rd[5] * r[4] + rd[8] * r[7]
        e23 = rd[1] * r[2] + rd[4] * r[5] + rd[7] * r[8]
        e13 = rd[0] * r[2] + rd[3] * r[5] + rd[6] * r[8]
        e31 = rd[2] * r[0] + rd[5] * r[3] + rd[8] * r[6]
        e21 = rd[1] * r[0] + rd[4] * r[3] + rd[7] * r[6]
        e12 = rd[0] * r[1] + rd[3] * r[4] + rd[6] * r[7]
        e_r = (0.5 * (e32 - e23), 0.5 * (e13 - e31), 0.5 * (e21 - e12))
        wx, wy, wz = state.omega_b_rad_s
        jx, jy, jz = self._j
        kr, kri, kw, rlim, eri = self._kr, self._kri, self._kw, self._ri_lim, mem.e_ri_rad_s
        for i in range(3):
            e = eri[i] + e_r[i] * dt
            eri[i] = e if -rlim[i] <= e <= rlim[i] else math.copysign(rlim[i], e)
        if self._ff:
            # w_d = R_B^T R_d w_r = E^T w_r
            orx, ory, orz = ref.omega_r_rad_s
            e11 = rd[0] * r[0] + rd[3] * r[3] + rd[6] * r[6]
            e22 = rd[1] * r[1] + rd[4] * r[4] + rd[7] * r[7]
            e33 = rd[2] * r[2] + rd[5] * r[5] + rd[8] * r[8]
            dwx = wx - (e11 * orx + e21 * ory + e31 * orz)
            dwy = wy - (e12 * orx + e22 * ory + e32 * orz)
            dwz = wz - (e13 * orx + e23 * ory + e33 * orz)
        else:
            dwx, dwy, dwz = wx, wy, wz
        hx, hy, hz = jx * wx, jy * wy, jz * wz
        u_tau = (wy * hz - wz * hy - kr[0] * e_r[0] - kri[0] * eri[0] - kw[0] * dwx,
                 wz * hx - wx * hz - kr[1] * e_r[1] - kri[1] * eri[1] - kw[1] * dwy,
                 wx * hy - wy * hx - kr[2] * e_r[2] - kri[2] * eri[2] - kw[2] * dwz)

        # -- wrench mapper -> spin rates ---------------------------------------------------
        thrusts = self.mapper.thrusts_n(alpha_rad, u_f, u_tau)
        c_f, w_min, w_max = self._c_f, self._w_min, self._w_max
        spins = []
        sat = []
        for f in thrusts:
            w = math.sqrt(f / c_f) if f > 0.0 else 0.0
            if w < w_min:
                spins.append(w_min)
                sat.append(True)
            elif w > w_max:
                spins.append(w_max)
                sat.append(True)
            else:
                spins.append(w)
                sat.append(False)
        return Command(t_s, tuple(spins), tuple(thrusts), tuple(sat),  # type: ignore[arg-type]
                       (fx, fy, fz), u_f, u_tau, rd, r_xy, theta, alpha_rad, e_r)

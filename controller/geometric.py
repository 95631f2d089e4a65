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
from typing import Any

import numpy as np

from controller import compiled
from controller.compiled import jit, jitable
from controller.model import LateralBound, VehicleModel
from controller.params import VehicleParams
from controller.reference import Mat3, Reference, Vec3, VehicleState, quat_to_rot
from controller.values import tick_value
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


@tick_value
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


@jitable
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
    for _ in range(n_it):
        step *= 0.5
        if a * math.cos(theta) + b * math.sin(theta) >= threshold:
            theta -= step
        else:
            theta += step
    c, s = math.cos(theta), math.sin(theta)
    return theta, (bx * c + px * s, by * c + py * s, bz * c + pz * s)


@jitable
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


#: offsets into the controller's constants (GeometricController._k), one array per vehicle
K_KP, K_KI, K_KV, K_PI_LIM, K_KR, K_KRI, K_KW, K_RI_LIM = 0, 3, 6, 9, 12, 15, 18, 21
K_M, K_G, K_J, K_C_F, K_W_MIN, K_W_MAX, K_FF, K_FORCE_FF, K_FORCE_FF_LIM = (
    24, 25, 26, 29, 30, 31, 32, 33, 34)
N_K = 35


@jitable
def control_law(k: Any, rows: Any, n_it: int, dt: float, px: float, py: float, pz: float,
                vx: float, vy: float, vz: float, qw: float, qx: float, qy: float, qz: float,
                wx: float, wy: float, wz: float, prx: float, pry: float, prz: float,
                vrx: float, vry: float, vrz: float, arx: float, ary: float, arz: float,
                qrw: float, qrx: float, qry: float, qrz: float, orx: float, ory: float,
                orz: float, r_xy: float, feed_force: bool, fex: float, fey: float,
                fez: float, epx: float, epy: float, epz: float, erx: float, ery: float,
                erz: float) -> tuple[Vec3, Vec3, Vec3, Mat3, float, Vec3, Six, Six,
                                     tuple[bool, bool, bool, bool, bool, bool], Vec3, Vec3]:
    """One tick of the control law on floats (compiled when numba is there, see
    :attr:`GeometricController.step`): constants ``k`` (``K_*`` offsets), the wrench map
    ``rows`` (6 x 6), the integrators ``ep*`` and ``er*`` before the tick ->
    ``(f_r, u_f, u_tau, R_d, theta, e_R, thrusts, spins, saturated, e_pi, e_Ri)``."""
    r = quat_to_rot((qw, qx, qy, qz))
    rr = quat_to_rot((qrw, qrx, qry, qrz))

    # -- position control ------------------------------------------------------------------
    m = k[K_M]
    ep0, ep1, ep2 = px - prx, py - pry, pz - prz
    lim0, lim1, lim2 = k[K_PI_LIM], k[K_PI_LIM + 1], k[K_PI_LIM + 2]
    e = epx + ep0 * dt
    epx = e if -lim0 <= e <= lim0 else math.copysign(lim0, e)
    e = epy + ep1 * dt
    epy = e if -lim1 <= e <= lim1 else math.copysign(lim1, e)
    e = epz + ep2 * dt
    epz = e if -lim2 <= e <= lim2 else math.copysign(lim2, e)
    fx = m * arx - k[K_KP] * ep0 - k[K_KI] * epx - k[K_KV] * (vx - vrx)
    fy = m * ary - k[K_KP + 1] * ep1 - k[K_KI + 1] * epy - k[K_KV + 1] * (vy - vry)
    fz = m * arz - k[K_KP + 2] * ep2 - k[K_KI + 2] * epz - k[K_KV + 2] * (vz - vrz)
    fz += m * k[K_G]
    if k[K_FORCE_FF] != 0.0 and feed_force:
        n = math.sqrt(fex * fex + fey * fey + fez * fez)
        if math.isfinite(n):
            ff_lim = k[K_FORCE_FF_LIM]
            s = ff_lim / n if n > ff_lim else 1.0
            fx -= s * fex
            fy -= s * fey
            fz -= s * fez

    # -- u_f: body-frame force with the cylindric lateral saturation ----------------------
    ubx = r[0] * fx + r[3] * fy + r[6] * fz
    uby = r[1] * fx + r[4] * fy + r[7] * fz
    ubz = r[2] * fx + r[5] * fy + r[8] * fz
    lat = math.sqrt(ubx * ubx + uby * uby)
    if lat > r_xy:
        s = r_xy / lat
        ubx, uby = ubx * s, uby * s

    # -- R_d by bisection + Rodrigues ----------------------------------------------------
    theta, b3d = bisect_tilt((rr[2], rr[5], rr[8]), (fx, fy, fz), r_xy, n_it)
    rd = desired_rotation(b3d, rr)

    # -- attitude control ----------------------------------------------------------------
    # E = R_d^T R_B; e_R = 1/2 vee(E - E^T)
    e32 = rd[2] * r[1] + rd[5] * r[4] + rd[8] * r[7]
    e23 = rd[1] * r[2] + rd[4] * r[5] + rd[7] * r[8]
    e13 = rd[0] * r[2] + rd[3] * r[5] + rd[6] * r[8]
    e31 = rd[2] * r[0] + rd[5] * r[3] + rd[8] * r[6]
    e21 = rd[1] * r[0] + rd[4] * r[3] + rd[7] * r[6]
    e12 = rd[0] * r[1] + rd[3] * r[4] + rd[6] * r[7]
    e_r0, e_r1, e_r2 = 0.5 * (e32 - e23), 0.5 * (e13 - e31), 0.5 * (e21 - e12)
    rl0, rl1, rl2 = k[K_RI_LIM], k[K_RI_LIM + 1], k[K_RI_LIM + 2]
    e = erx + e_r0 * dt
    erx = e if -rl0 <= e <= rl0 else math.copysign(rl0, e)
    e = ery + e_r1 * dt
    ery = e if -rl1 <= e <= rl1 else math.copysign(rl1, e)
    e = erz + e_r2 * dt
    erz = e if -rl2 <= e <= rl2 else math.copysign(rl2, e)
    if k[K_FF] != 0.0:
        # w_d = R_B^T R_d w_r = E^T w_r
        e11 = rd[0] * r[0] + rd[3] * r[3] + rd[6] * r[6]
        e22 = rd[1] * r[1] + rd[4] * r[4] + rd[7] * r[7]
        e33 = rd[2] * r[2] + rd[5] * r[5] + rd[8] * r[8]
        dwx = wx - (e11 * orx + e21 * ory + e31 * orz)
        dwy = wy - (e12 * orx + e22 * ory + e32 * orz)
        dwz = wz - (e13 * orx + e23 * ory + e33 * orz)
    else:
        dwx, dwy, dwz = wx, wy, wz
    hx, hy, hz = k[K_J] * wx, k[K_J + 1] * wy, k[K_J + 2] * wz
    tx = wy * hz - wz * hy - k[K_KR] * e_r0 - k[K_KRI] * erx - k[K_KW] * dwx
    ty = wz * hx - wx * hz - k[K_KR + 1] * e_r1 - k[K_KRI + 1] * ery - k[K_KW + 1] * dwy
    tz = wx * hy - wy * hx - k[K_KR + 2] * e_r2 - k[K_KRI + 2] * erz - k[K_KW + 2] * dwz

    # -- wrench map -> spin rates --------------------------------------------------------
    f0 = rows[0][0] * ubx + rows[0][1] * uby + rows[0][2] * ubz + rows[0][3] * tx \
        + rows[0][4] * ty + rows[0][5] * tz
    f1 = rows[1][0] * ubx + rows[1][1] * uby + rows[1][2] * ubz + rows[1][3] * tx \
        + rows[1][4] * ty + rows[1][5] * tz
    f2 = rows[2][0] * ubx + rows[2][1] * uby + rows[2][2] * ubz + rows[2][3] * tx \
        + rows[2][4] * ty + rows[2][5] * tz
    f3 = rows[3][0] * ubx + rows[3][1] * uby + rows[3][2] * ubz + rows[3][3] * tx \
        + rows[3][4] * ty + rows[3][5] * tz
    f4 = rows[4][0] * ubx + rows[4][1] * uby + rows[4][2] * ubz + rows[4][3] * tx \
        + rows[4][4] * ty + rows[4][5] * tz
    f5 = rows[5][0] * ubx + rows[5][1] * uby + rows[5][2] * ubz + rows[5][3] * tx \
        + rows[5][4] * ty + rows[5][5] * tz
    c_f, w_min, w_max = k[K_C_F], k[K_W_MIN], k[K_W_MAX]
    w0, s0 = _spin(f0, c_f, w_min, w_max)
    w1, s1 = _spin(f1, c_f, w_min, w_max)
    w2, s2 = _spin(f2, c_f, w_min, w_max)
    w3, s3 = _spin(f3, c_f, w_min, w_max)
    w4, s4 = _spin(f4, c_f, w_min, w_max)
    w5, s5 = _spin(f5, c_f, w_min, w_max)
    return ((fx, fy, fz), (ubx, uby, ubz), (tx, ty, tz), rd, theta, (e_r0, e_r1, e_r2),
            (f0, f1, f2, f3, f4, f5), (w0, w1, w2, w3, w4, w5), (s0, s1, s2, s3, s4, s5),
            (epx, epy, epz), (erx, ery, erz))


@jitable
def _spin(f: float, c_f: float, w_min: float, w_max: float) -> tuple[float, bool]:
    """Spin rate (Hz) of thrust ``f``, clamped to the rotor limits, and whether it was."""
    w = math.sqrt(f / c_f) if f > 0.0 else 0.0
    if w < w_min:
        return w_min, True
    if w > w_max:
        return w_max, True
    return w, False


_control_law_compiled = jit(control_law)


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
        k = [0.0] * N_K
        for off, gains in ((K_KP, c.kp_pos), (K_KI, c.ki_pos), (K_KV, c.kv_pos),
                           (K_PI_LIM, c.pos_integral_limit_m_s), (K_KR, c.kr_att),
                           (K_KRI, c.ki_att), (K_KW, c.kw_att),
                           (K_RI_LIM, c.att_integral_limit_rad_s),
                           (K_J, params.inertia_diag_kg_m2)):
            k[off:off + 3] = [float(g) for g in gains]
        k[K_M], k[K_G] = self._m, self._g
        k[K_C_F], k[K_W_MIN], k[K_W_MAX] = self._c_f, self._w_min, self._w_max
        k[K_FF] = 1.0 if self._ff else 0.0
        k[K_FORCE_FF] = 1.0 if self._force_ff else 0.0
        k[K_FORCE_FF_LIM] = self._force_ff_lim
        # compiled: the constants and the map as arrays; plain Python: as tuples (faster there)
        self._compiled = compiled.AVAILABLE
        self._k: Any = np.array(k) if self._compiled else tuple(k)
        self._law = _control_law_compiled if self._compiled else control_law
        self._warm_up()

    def _warm_up(self) -> None:
        """Compile the control law (or load it from numba's on-disk cache) now."""
        if self._compiled:
            z = 0.0  # at rest at the origin, level, on the reference
            self._law(self._k, np.eye(6), 1, z, z, z, z, z, z, z, 1.0, z, z, z, z, z, z,
                      z, z, z, z, z, z, z, z, z, 1.0, z, z, z, z, z, z, 1.0, False,
                      z, z, z, z, z, z, z, z, z)

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
        r_xy = self.bound.radius_n(alpha_rad)
        mapper = self.mapper
        rows = mapper.rows_array(alpha_rad) if self._compiled else mapper.rows(alpha_rad)
        p, v, q, w = state.pos_w_m, state.vel_w_m_s, state.q_wb, state.omega_b_rad_s
        pr, vr, ar, qr, wr = ref.pos_w_m, ref.vel_w_m_s, ref.acc_w_m_s2, ref.q_wr, \
            ref.omega_r_rad_s
        feed = force_ext_w_n is not None
        fe = force_ext_w_n if force_ext_w_n is not None else (0.0, 0.0, 0.0)
        epi, eri = mem.e_pi_m_s, mem.e_ri_rad_s
        f_r, u_f, u_tau, rd, theta, e_r, thrusts, spins, sat, epi_new, eri_new = self._law(
            self._k, rows, self._n_it, dt, p[0], p[1], p[2], v[0], v[1], v[2],
            q[0], q[1], q[2], q[3], w[0], w[1], w[2], pr[0], pr[1], pr[2], vr[0], vr[1], vr[2],
            ar[0], ar[1], ar[2], qr[0], qr[1], qr[2], qr[3], wr[0], wr[1], wr[2], r_xy, feed,
            fe[0], fe[1], fe[2], epi[0], epi[1], epi[2], eri[0], eri[1], eri[2])
        epi[0], epi[1], epi[2] = epi_new
        eri[0], eri[1], eri[2] = eri_new
        return Command(t_s, spins, thrusts, sat, f_r, u_f, u_tau, rd, r_xy, theta, alpha_rad,
                       e_r)

"""The simulator's physics step as a compiled loop (numba, cached on disk): the same maths as
the plain-float code it replaced in :class:`sim_backend.simulator.FastHexSimulator`.

One call of :func:`advance` runs ``n`` RK4 substeps: the rate-limited servo and the Cardan
chain's per-propeller tilts, the first-order rotor lag, the per-propeller wrench with the
gyroscopic terms, the scenario's scheduled wrench (evaluated by the caller per substep), the
tether and Ornstein-Uhlenbeck forces, ground contact and the RK4 step itself. The Python side
keeps what is not arithmetic: the MoCap model (told which substeps are due a capture), the
touchdown list and the random generators.

Everything mutable lives in one float64 array (layout: the ``S_*`` offsets) and every constant
in another (``P_*``), so that one call unboxes a handful of arrays instead of dozens of
arguments; ``S_*`` offsets below :data:`S_READ` are what the simulator reads back after each
call, with one ``tolist``.

Without numba installed :data:`AVAILABLE` is false and the same functions run as plain Python
on the arrays (correct, slow).
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
except ImportError:             # pragma: no cover - exercised where numba is absent
    AVAILABLE = False

    def _jit(fn: F) -> F:
        return fn

N_ROTORS = 6
TWO_PI = 2.0 * math.pi
#: joints between the servo and each propeller's worm, unrolled in :func:`set_tilts` (the
#: simulator checks it against ``controller.model.CARDAN_JOINTS_PER_PROPELLER``)
CARDAN_JOINTS = (1, 3, 5, 5, 3, 1)

# -- the mutable state ------------------------------------------------------------------------
S_X = 0             # 13: centre-of-mass position, velocity, q_wb (w, x, y, z), body rate
S_W = 13            # 6: rotor speeds (Hz)
S_SERVO = 19        # servo-side tilt (rad)
S_LANDED = 20       # 1.0 resting on the ground, else 0.0
S_FB = 21           # 3: body force of the last step (N, body)
S_FEXT = 24         # 3: tether + OU + scheduled world force of the last step (N, world)
S_T = 27            # simulated time (s)
S_SPECIFIC = 28     # 3: what an ideal accelerometer reads now (m/s^2, body)
S_READ = 31         # the simulator reads [0, S_READ) back after every call
S_W_CMD = 31        # 6: rotor speed set-points (Hz, >= 0)
S_SERVO_GOAL = 37   # the servo's goal (rad)
S_OU = 38           # 3: the Ornstein-Uhlenbeck force (N, world)
S_TILTS = 41        # 6: actual signed propeller tilts (rad)
S_AXES = 47         # 6 x 3: thrust axes (body)
S_DAXES = 65        # 6 x 3: d axis / d tilt
S_MOMENTS = 83      # 6 x 3: arm moment + drag torque per unit thrust (about the centre of mass)
S_C_F = 101         # 6: actual thrust coefficients (N/Hz^2)
S_IMPULSE = 107     # 3: a touchdown's velocity change the accelerometer has still to feel (world)
S_IMPULSE_RATE = 110  # 3: ... and how fast it feels it (m/s^2, world)
S_ROT_IMPULSE = 113  # 3: the rotation to level a touchdown made, for the gyro to feel (body)
S_ROT_T = 116       # time since that touchdown (s): the gyro feels it over LEVEL_S
S_GYRO_FELT = 117   # 3: what the gyro reads on top of the body rate in this sample (rad/s)
S_ROT_FELT = 120    # the share of S_ROT_IMPULSE felt so far (0..1)
N_STATE = 121

#: a touchdown stops the body and levels it within one step (the contact is a clamp), but its
#: gear takes about this long: the accelerometer feels the stop and the gyro the levelling
#: spread over it, as real ones feel an impact (a dead reckoning on the IMU then stops at the
#: ground, level, too; 0.12 m/s: 6 m/s^2 for 20 ms; a crash's peak is clipped by the sensor's
#: range, as a real one's is)
CONTACT_S = 0.02
#: ... and it rocks level over this long, the rate rising and falling linearly (a triangle:
#: no step in the gyro, whose driver drops a sample that changes by more than 0.25 rad/s as a
#: corrupted byte; a 5 deg levelling peaks at 0.9 rad/s and changes by 0.02 rad/s per 2 ms)
LEVEL_S = 0.2

# -- the constants ----------------------------------------------------------------------------
P_M = 0             # mass (kg)
P_G = 1             # gravity (m/s^2)
P_J = 2             # 3: inertia diagonal (kg m^2)
P_J_FULL = 5        # 1.0: the full inertia below is used (off-diagonal terms)
P_J_MAT = 6         # 9: full inertia, row-major
P_J_INV = 15        # 9: its inverse, row-major
P_COM = 24          # 3: centre-of-mass offset c (body, m)
P_HAS_COM = 27      # 1.0 when c != 0
P_I_R = 28          # rotor inertia (kg m^2)
P_TAU_ROTOR = 29    # rotor time constant (s), 0: none
P_TILT_RATE = 30    # servo rate limit (rad/s)
P_WORM = 31         # worm ratio
P_COS_BEND = 32     # cos of the Cardan bend
P_CARDAN = 33       # 1.0: tilts through the Cardan chain
P_OU_RMS = 34       # per-axis rms of the OU force (N)
P_OU_TAU = 35       # OU correlation time (s)
P_TETHER = 36       # tether pull (N)
P_ANCHOR = 37       # 3: tether anchor (world, m)
P_GROUND = 40       # height of O_B at rest (m)
P_MISALIGN = 41     # 6: fixed misalignment about each arm's y axis (rad)
P_YAW = 47          # 6: arm yaw angles (rad)
P_POS = 53          # 6 x 3: propeller positions (body, m)
P_SPIN = 71         # 6: +1 where the propeller spins about +axis
P_C_TAU = 77        # 6: drag coefficients (m)
N_PARAMS = 83

# -- one row per substep, written by advance ---------------------------------------------------
O_T = 0             # time after the substep
O_POS = 1           # 3: O_B (world) after the substep
O_Q = 4             # 4: q_wb after the substep
O_TOUCHDOWN = 8     # vertical speed (m/s, down) of a touchdown in this substep, else NaN
O_CAPTURE = 9       # 1.0: a MoCap capture is due after this substep
N_OUT = 10
# -- the scheduled wrench per substep (the caller's, from the scenario) -------------------------
W_ON = 0            # 1.0: a wrench acts in this substep
W_F_W = 1           # 3: world force (N)
W_F_B = 4           # 3: body force (N)
W_T_W = 7           # 3: world torque (N m)
W_T_B = 10          # 3: body torque (N m)
N_WRENCH = 13


@_jit
def _cardan_stage(g: float, cos_bend: float) -> float:
    out = math.atan2(math.sin(g), cos_bend * math.cos(g))
    # round half to even, as Python's round (the ratio is never near a half here)
    return out + TWO_PI * np.rint((g - out) / TWO_PI)


@_jit
def set_tilts(s: FloatArray, p: FloatArray, servo_rad: float) -> None:
    """The six propellers' tilts, thrust axes, their derivatives and the moments per unit
    thrust at servo tilt ``servo_rad`` into ``s``."""
    if p[P_CARDAN] != 0.0:
        worm, cb = p[P_WORM], p[P_COS_BEND]
        g1 = _cardan_stage(servo_rad / worm, cb)
        g2 = _cardan_stage(g1, cb)
        g3 = _cardan_stage(g2, cb)
        g4 = _cardan_stage(g3, cb)
        g5 = _cardan_stage(g4, cb)
        s[S_TILTS + 0] = worm * g1
        s[S_TILTS + 1] = worm * -1.0 * g3
        s[S_TILTS + 2] = worm * g5
        s[S_TILTS + 3] = worm * -1.0 * g5
        s[S_TILTS + 4] = worm * g3
        s[S_TILTS + 5] = worm * -1.0 * g1
    else:
        for i in range(N_ROTORS):
            s[S_TILTS + i] = servo_rad if i % 2 == 0 else -servo_rad
    cx, cy_, cz = p[P_COM], p[P_COM + 1], p[P_COM + 2]
    for i in range(N_ROTORS):
        t = s[S_TILTS + i]
        sa, ca = math.sin(t), math.cos(t)
        sb, cb = math.sin(p[P_MISALIGN + i]), math.cos(p[P_MISALIGN + i])
        sy, cy = math.sin(p[P_YAW + i]), math.cos(p[P_YAW + i])
        lx, ly, lz = sb, -sa * cb, ca * cb          # Rx(a) Ry(b) e3
        dx, dy, dz = 0.0, -ca * cb, -sa * cb        # d/da
        ax0, ax1, ax2 = cy * lx - sy * ly, sy * lx + cy * ly, lz
        k = 3 * i
        s[S_AXES + k], s[S_AXES + k + 1], s[S_AXES + k + 2] = ax0, ax1, ax2
        s[S_DAXES + k] = cy * dx - sy * dy
        s[S_DAXES + k + 1] = sy * dx + cy * dy
        s[S_DAXES + k + 2] = dz
        # the rotor moments act about the centre of mass
        px, py, pz = p[P_POS + k] - cx, p[P_POS + k + 1] - cy_, p[P_POS + k + 2] - cz
        d = -p[P_SPIN + i] * p[P_C_TAU + i]
        s[S_MOMENTS + k] = py * ax2 - pz * ax1 + d * ax0
        s[S_MOMENTS + k + 1] = pz * ax0 - px * ax2 + d * ax1
        s[S_MOMENTS + k + 2] = px * ax1 - py * ax0 + d * ax2


@_jit
def _r_com(p: FloatArray, qw: float, qx: float, qy: float, qz: float
           ) -> tuple[float, float, float]:
    """R c: from O_B to the centre of mass, world frame."""
    if p[P_HAS_COM] == 0.0:
        return 0.0, 0.0, 0.0
    xx, yy, zz = qx * qx, qy * qy, qz * qz
    xy, xz, yz = qx * qy, qx * qz, qy * qz
    wx, wy, wz = qw * qx, qw * qy, qw * qz
    c0, c1, c2 = p[P_COM], p[P_COM + 1], p[P_COM + 2]
    return ((1.0 - 2.0 * (yy + zz)) * c0 + 2.0 * (xy - wz) * c1 + 2.0 * (xz + wy) * c2,
            2.0 * (xy + wz) * c0 + (1.0 - 2.0 * (xx + zz)) * c1 + 2.0 * (yz - wx) * c2,
            2.0 * (xz - wy) * c0 + 2.0 * (yz + wx) * c1 + (1.0 - 2.0 * (xx + yy)) * c2)


@_jit
def _deriv(x: FloatArray, out: FloatArray, p: FloatArray, fx: float, fy: float, fz: float,
           tx: float, ty: float, tz: float, hx: float, hy: float, hz: float, ex: float,
           ey: float, ez: float) -> None:
    qw, qx, qy, qz = x[6], x[7], x[8], x[9]
    wx, wy, wz = x[10], x[11], x[12]
    inv_m, g = 1.0 / p[P_M], p[P_G]
    # R (body -> world) applied to F_b
    xx, yy, zz = qx * qx, qy * qy, qz * qz
    xy, xz, yz = qx * qy, qx * qz, qy * qz
    wqx, wqy, wqz = qw * qx, qw * qy, qw * qz
    out[0], out[1], out[2] = x[3], x[4], x[5]
    out[3] = ((1.0 - 2.0 * (yy + zz)) * fx + 2.0 * (xy - wqz) * fy + 2.0 * (xz + wqy) * fz
              + ex) * inv_m
    out[4] = (2.0 * (xy + wqz) * fx + (1.0 - 2.0 * (xx + zz)) * fy + 2.0 * (yz - wqx) * fz
              + ey) * inv_m
    out[5] = (2.0 * (xz - wqy) * fx + 2.0 * (yz + wqx) * fy + (1.0 - 2.0 * (xx + yy)) * fz
              + ez) * inv_m - g
    if p[P_J_FULL] == 0.0:
        jx, jy, jz = p[P_J], p[P_J + 1], p[P_J + 2]
        lx, ly, lz = jx * wx + hx, jy * wy + hy, jz * wz + hz
        dwx = (tx - (wy * lz - wz * ly)) / jx
        dwy = (ty - (wz * lx - wx * lz)) / jy
        dwz = (tz - (wx * ly - wy * lx)) / jz
    else:  # J w' = tau - w x (J w + h), J full
        j, ji = P_J_MAT, P_J_INV
        lx = p[j] * wx + p[j + 1] * wy + p[j + 2] * wz + hx
        ly = p[j + 3] * wx + p[j + 4] * wy + p[j + 5] * wz + hy
        lz = p[j + 6] * wx + p[j + 7] * wy + p[j + 8] * wz + hz
        rx_ = tx - (wy * lz - wz * ly)
        ry_ = ty - (wz * lx - wx * lz)
        rz_ = tz - (wx * ly - wy * lx)
        dwx = p[ji] * rx_ + p[ji + 1] * ry_ + p[ji + 2] * rz_
        dwy = p[ji + 3] * rx_ + p[ji + 4] * ry_ + p[ji + 5] * rz_
        dwz = p[ji + 6] * rx_ + p[ji + 7] * ry_ + p[ji + 8] * rz_
    out[6] = 0.5 * (-qx * wx - qy * wy - qz * wz)
    out[7] = 0.5 * (qw * wx + qy * wz - qz * wy)
    out[8] = 0.5 * (qw * wy - qx * wz + qz * wx)
    out[9] = 0.5 * (qw * wz + qx * wy - qy * wx)
    out[10], out[11], out[12] = dwx, dwy, dwz


@_jit
def _substep(s: FloatArray, p: FloatArray, h: float, normals: FloatArray, k_normal: int,
             wrench: FloatArray, k1: FloatArray, k2: FloatArray, k3: FloatArray,
             k4: FloatArray, tmp: FloatArray) -> float:
    """One RK4 step of ``h`` seconds; the speed of a touchdown in it (NaN: none)."""
    # servo: rate-limited towards the goal; per-propeller tilt rates for the gyroscopic term
    moving = False
    rate0 = rate1 = rate2 = rate3 = rate4 = rate5 = 0.0
    if s[S_SERVO] != s[S_SERVO_GOAL]:
        moving = True
        step = p[P_TILT_RATE] * h
        d = s[S_SERVO_GOAL] - s[S_SERVO]
        s[S_SERVO] += step if d > step else (-step if d < -step else d)
        o0, o1, o2 = s[S_TILTS], s[S_TILTS + 1], s[S_TILTS + 2]
        o3, o4, o5 = s[S_TILTS + 3], s[S_TILTS + 4], s[S_TILTS + 5]
        set_tilts(s, p, s[S_SERVO])
        rate0 = (s[S_TILTS] - o0) / h
        rate1 = (s[S_TILTS + 1] - o1) / h
        rate2 = (s[S_TILTS + 2] - o2) / h
        rate3 = (s[S_TILTS + 3] - o3) / h
        rate4 = (s[S_TILTS + 4] - o4) / h
        rate5 = (s[S_TILTS + 5] - o5) / h

    # rotors (first-order lag, exact over the step) and the body wrench, propeller by propeller
    tau = p[P_TAU_ROTOR]
    a = 1.0 - math.exp(-h / tau) if tau > 0.0 else 0.0
    i_r = p[P_I_R]
    fx = fy = fz = tx = ty = tz = hx = hy = hz = 0.0
    for i in range(N_ROTORS):
        cmd, w = s[S_W_CMD + i], s[S_W + i]
        if tau > 0.0:
            wdot = (cmd - w) / tau
            w = w + (cmd - w) * a
        else:
            wdot = 0.0
            w = cmd
        s[S_W + i] = w
        f = s[S_C_F + i] * w * w
        k = 3 * i
        ax0, ax1, ax2 = s[S_AXES + k], s[S_AXES + k + 1], s[S_AXES + k + 2]
        fx += f * ax0
        fy += f * ax1
        fz += f * ax2
        tx += f * s[S_MOMENTS + k]
        ty += f * s[S_MOMENTS + k + 1]
        tz += f * s[S_MOMENTS + k + 2]
        if i_r > 0.0:
            kk = i_r * TWO_PI * p[P_SPIN + i]
            kw = kk * w
            hx += kw * ax0
            hy += kw * ax1
            hz += kw * ax2
            # reaction to dh/dt: spin-up along the axis, tilting turns the axis
            kd = kk * wdot
            tx -= kd * ax0
            ty -= kd * ax1
            tz -= kd * ax2
            if moving:
                rate = (rate0 if i == 0 else rate1 if i == 1 else rate2 if i == 2
                        else rate3 if i == 3 else rate4 if i == 4 else rate5)
                kt = kw * rate
                tx -= kt * s[S_DAXES + k]
                ty -= kt * s[S_DAXES + k + 1]
                tz -= kt * s[S_DAXES + k + 2]

    x = s[S_X:S_X + 13]
    ex = ey = ez = 0.0
    if wrench[W_ON] != 0.0:  # the scenario's: world force, body force, torques (at C)
        ex, ey, ez = wrench[W_F_W], wrench[W_F_W + 1], wrench[W_F_W + 2]
        fx, fy, fz = fx + wrench[W_F_B], fy + wrench[W_F_B + 1], fz + wrench[W_F_B + 2]
        tx, ty, tz = tx + wrench[W_T_B], ty + wrench[W_T_B + 1], tz + wrench[W_T_B + 2]
        twx, twy, twz = wrench[W_T_W], wrench[W_T_W + 1], wrench[W_T_W + 2]
        if twx != 0.0 or twy != 0.0 or twz != 0.0:
            qw, qx, qy, qz = x[6], x[7], x[8], x[9]
            xx, yy, zz = qx * qx, qy * qy, qz * qz
            xy, xz, yz = qx * qy, qx * qz, qy * qz
            wx, wy, wz = qw * qx, qw * qy, qw * qz
            r0, r1, r2 = 1.0 - 2.0 * (yy + zz), 2.0 * (xy - wz), 2.0 * (xz + wy)
            r3, r4, r5 = 2.0 * (xy + wz), 1.0 - 2.0 * (xx + zz), 2.0 * (yz - wx)
            r6, r7, r8 = 2.0 * (xz - wy), 2.0 * (yz + wx), 1.0 - 2.0 * (xx + yy)
            # body torque = R^T world torque
            tx += r0 * twx + r3 * twy + r6 * twz
            ty += r1 * twx + r4 * twy + r7 * twz
            tz += r2 * twx + r5 * twy + r8 * twz
    s[S_FB], s[S_FB + 1], s[S_FB + 2] = fx, fy, fz

    # external forces (world)
    tether = p[P_TETHER]
    if tether > 0.0:
        dx, dy, dz = p[P_ANCHOR] - x[0], p[P_ANCHOR + 1] - x[1], p[P_ANCHOR + 2] - x[2]
        n = math.sqrt(dx * dx + dy * dy + dz * dz)
        if n > 1e-9:
            ex, ey, ez = ex + tether * dx / n, ey + tether * dy / n, ez + tether * dz / n
    ou_rms = p[P_OU_RMS]
    if ou_rms > 0.0:
        phi = math.exp(-h / p[P_OU_TAU])
        sd = ou_rms * math.sqrt(1.0 - phi * phi)
        s[S_OU] = phi * s[S_OU] + sd * normals[k_normal]
        s[S_OU + 1] = phi * s[S_OU + 1] + sd * normals[k_normal + 1]
        s[S_OU + 2] = phi * s[S_OU + 2] + sd * normals[k_normal + 2]
        ex, ey, ez = ex + s[S_OU], ey + s[S_OU + 1], ez + s[S_OU + 2]
    s[S_FEXT], s[S_FEXT + 1], s[S_FEXT + 2] = ex, ey, ez

    m, g = p[P_M], p[P_G]
    if s[S_LANDED] != 0.0:
        qw, qx, qy, qz = x[6], x[7], x[8], x[9]
        # the third row of R
        r6 = 2.0 * (qx * qz - qw * qy)
        r7 = 2.0 * (qy * qz + qw * qx)
        r8 = 1.0 - 2.0 * (qx * qx + qy * qy)
        lift = r6 * fx + r7 * fy + r8 * fz + ez - m * g
        if lift <= 0.0:
            return math.nan
        s[S_LANDED] = 0.0

    hh = 0.5 * h
    _deriv(x, k1, p, fx, fy, fz, tx, ty, tz, hx, hy, hz, ex, ey, ez)
    for j in range(13):
        tmp[j] = x[j] + hh * k1[j]
    _deriv(tmp, k2, p, fx, fy, fz, tx, ty, tz, hx, hy, hz, ex, ey, ez)
    for j in range(13):
        tmp[j] = x[j] + hh * k2[j]
    _deriv(tmp, k3, p, fx, fy, fz, tx, ty, tz, hx, hy, hz, ex, ey, ez)
    for j in range(13):
        tmp[j] = x[j] + h * k3[j]
    _deriv(tmp, k4, p, fx, fy, fz, tx, ty, tz, hx, hy, hz, ex, ey, ez)
    h6 = h / 6.0
    for j in range(13):
        x[j] = x[j] + h6 * (k1[j] + 2.0 * (k2[j] + k3[j]) + k4[j])
    qn = 1.0 / math.sqrt(x[6] * x[6] + x[7] * x[7] + x[8] * x[8] + x[9] * x[9])
    x[6] *= qn
    x[7] *= qn
    x[8] *= qn
    x[9] *= qn
    rc0, rc1, rc2 = _r_com(p, x[6], x[7], x[8], x[9])
    ground = p[P_GROUND]
    if x[2] - rc2 < ground:  # O_B below its resting height: comes to rest level
        speed = -x[5]
        qw, qx, qy, qz = x[6], x[7], x[8], x[9]
        yaw = math.atan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz))
        yw, yz_ = math.cos(0.5 * yaw), math.sin(0.5 * yaw)
        c0, c1, c2 = _r_com(p, yw, 0.0, 0.0, yz_)
        x[0] = x[0] - rc0 + c0
        x[1] = x[1] - rc1 + c1
        x[2] = ground + c2
        for j in range(3):
            s[S_IMPULSE + j] -= x[3 + j]
            s[S_IMPULSE_RATE + j] = s[S_IMPULSE + j] / CONTACT_S
        # the rotation from the touching attitude to the level one, in the body frame:
        # conj(q) (x) (yw, 0, 0, yz)
        dw = qw * yw + qz * yz_
        dx = -yw * qx - qy * yz_
        dy = -yw * qy + qx * yz_
        dz = qw * yz_ - yw * qz
        if dw < 0.0:
            dw, dx, dy, dz = -dw, -dx, -dy, -dz
        nv = math.sqrt(dx * dx + dy * dy + dz * dz)
        to_angle = 2.0 * math.atan2(nv, dw) / nv if nv > 1e-15 else 2.0
        left = 1.0 - s[S_ROT_FELT]   # of a levelling still under way (a hop), then this one
        s[S_ROT_IMPULSE] = left * s[S_ROT_IMPULSE] + to_angle * dx
        s[S_ROT_IMPULSE + 1] = left * s[S_ROT_IMPULSE + 1] + to_angle * dy
        s[S_ROT_IMPULSE + 2] = left * s[S_ROT_IMPULSE + 2] + to_angle * dz
        s[S_ROT_T] = 0.0
        s[S_ROT_FELT] = 0.0
        x[3] = x[4] = x[5] = 0.0
        x[6], x[7], x[8], x[9] = yw, 0.0, 0.0, yz_
        x[10] = x[11] = x[12] = 0.0
        s[S_LANDED] = 1.0
        return speed
    return math.nan


@_jit
def specific_force(s: FloatArray, p: FloatArray) -> None:
    """What an ideal accelerometer reads (m/s^2, body) into ``s[S_SPECIFIC:]``: (F_b + R^T
    F_ext) / m of the last step, or the ground's reaction when resting."""
    qw, qx, qy, qz = s[S_X + 6], s[S_X + 7], s[S_X + 8], s[S_X + 9]
    xx, yy, zz = qx * qx, qy * qy, qz * qz
    xy, xz, yz = qx * qy, qx * qz, qy * qz
    wx, wy, wz = qw * qx, qw * qy, qw * qz
    r0, r1, r2 = 1.0 - 2.0 * (yy + zz), 2.0 * (xy - wz), 2.0 * (xz + wy)
    r3, r4, r5 = 2.0 * (xy + wz), 1.0 - 2.0 * (xx + zz), 2.0 * (yz - wx)
    r6, r7, r8 = 2.0 * (xz - wy), 2.0 * (yz + wx), 1.0 - 2.0 * (xx + yy)
    if s[S_LANDED] != 0.0:
        g = p[P_G]
        s[S_SPECIFIC], s[S_SPECIFIC + 1], s[S_SPECIFIC + 2] = r6 * g, r7 * g, r8 * g
        return
    m = p[P_M]
    fe0, fe1, fe2 = s[S_FEXT], s[S_FEXT + 1], s[S_FEXT + 2]
    s[S_SPECIFIC] = (s[S_FB] + r0 * fe0 + r3 * fe1 + r6 * fe2) / m
    s[S_SPECIFIC + 1] = (s[S_FB + 1] + r1 * fe0 + r4 * fe1 + r7 * fe2) / m
    s[S_SPECIFIC + 2] = (s[S_FB + 2] + r2 * fe0 + r5 * fe1 + r8 * fe2) / m


@_jit
def advance(s: FloatArray, p: FloatArray, h: float, n: int, normals: FloatArray,
            k_normal: int, wrenches: FloatArray, next_capture_s: float, capture_period_s: float,
            out: FloatArray, w_cmd_0: float, w_cmd_1: float, w_cmd_2: float, w_cmd_3: float,
            w_cmd_4: float, w_cmd_5: float, servo_goal: float) -> int:
    """``n`` substeps of ``h`` seconds towards the rotor speed set-points ``w_cmd_*`` (Hz,
    >= 0) and the servo goal (rad); row k of ``out`` (``O_*``) tells what happened in
    substep k. ``normals[k_normal:]`` are the OU force's standard normals (three per substep
    when the OU force is on), ``wrenches[k]`` the scheduled wrench of substep k (``W_*``).
    Returns how many substeps had a touchdown or are due a MoCap capture (at 1 kHz physics
    with a 100 Hz MoCap most calls have none)."""
    s[S_W_CMD], s[S_W_CMD + 1], s[S_W_CMD + 2] = w_cmd_0, w_cmd_1, w_cmd_2
    s[S_W_CMD + 3], s[S_W_CMD + 4], s[S_W_CMD + 5] = w_cmd_3, w_cmd_4, w_cmd_5
    s[S_SERVO_GOAL] = servo_goal
    k1, k2, k3, k4, tmp = np.empty(13), np.empty(13), np.empty(13), np.empty(13), np.empty(13)
    ou = p[P_OU_RMS] > 0.0
    events = 0
    for k in range(n):
        speed = _substep(s, p, h, normals, k_normal, wrenches[k], k1, k2, k3, k4, tmp)
        if ou:
            k_normal += 3
        t = s[S_T] + h
        s[S_T] = t
        row = out[k]
        row[O_T] = t
        x = s[S_X:S_X + 13]
        rc0, rc1, rc2 = _r_com(p, x[6], x[7], x[8], x[9])
        row[O_POS], row[O_POS + 1], row[O_POS + 2] = x[0] - rc0, x[1] - rc1, x[2] - rc2
        row[O_Q], row[O_Q + 1], row[O_Q + 2], row[O_Q + 3] = x[6], x[7], x[8], x[9]
        row[O_TOUCHDOWN] = speed
        capture = False
        while t + 1e-12 >= next_capture_s:  # as MocapModel.maybe_capture counts its frames
            next_capture_s += capture_period_s
            capture = True
        row[O_CAPTURE] = 1.0 if capture else 0.0
        if capture or not math.isnan(speed):
            events += 1
    specific_force(s, p)
    s[S_GYRO_FELT] = s[S_GYRO_FELT + 1] = s[S_GYRO_FELT + 2] = 0.0
    if s[S_IMPULSE] != 0.0 or s[S_IMPULSE + 1] != 0.0 or s[S_IMPULSE + 2] != 0.0 \
            or s[S_ROT_FELT] < 1.0:
        _feel_contact(s, n * h)
    return events


@_jit
def _feel_contact(s: FloatArray, dt: float) -> None:
    """Add to the specific force of this ``dt`` the part of a touchdown's velocity change felt
    in it (``S_IMPULSE`` at ``S_IMPULSE_RATE``, see :data:`CONTACT_S`), and set the gyro's
    share of the levelling (``S_GYRO_FELT`` from ``S_ROT_IMPULSE``, see :data:`LEVEL_S`)."""
    a = np.zeros(3)
    for j in range(3):
        rem = s[S_IMPULSE + j]
        use = s[S_IMPULSE_RATE + j] * dt
        if abs(use) >= abs(rem):
            use = rem
        s[S_IMPULSE + j] = rem - use
        a[j] = use / dt
    if s[S_ROT_FELT] < 1.0:
        # the triangle's share between t and t + dt: F(u) = 2 u^2 (u <= 1/2), 1 - 2 (1 - u)^2
        t1 = s[S_ROT_T] + dt
        s[S_ROT_T] = t1
        u = min(t1 / LEVEL_S, 1.0)
        felt = 2.0 * u * u if u <= 0.5 else 1.0 - 2.0 * (1.0 - u) * (1.0 - u)
        share = felt - s[S_ROT_FELT]
        s[S_ROT_FELT] = felt
        for j in range(3):
            s[S_GYRO_FELT + j] = s[S_ROT_IMPULSE + j] * share / dt
    qw, qx, qy, qz = s[S_X + 6], s[S_X + 7], s[S_X + 8], s[S_X + 9]
    xx, yy, zz = qx * qx, qy * qy, qz * qz
    xy, xz, yz = qx * qy, qx * qz, qy * qz
    wx, wy, wz = qw * qx, qw * qy, qw * qz
    # R^T a: the world acceleration in the body frame
    s[S_SPECIFIC] += (1.0 - 2.0 * (yy + zz)) * a[0] + 2.0 * (xy + wz) * a[1] \
        + 2.0 * (xz - wy) * a[2]
    s[S_SPECIFIC + 1] += 2.0 * (xy - wz) * a[0] + (1.0 - 2.0 * (xx + zz)) * a[1] \
        + 2.0 * (yz + wx) * a[2]
    s[S_SPECIFIC + 2] += 2.0 * (xz + wy) * a[0] + 2.0 * (yz - wx) * a[1] \
        + (1.0 - 2.0 * (xx + yy)) * a[2]
    if s[S_ROT_FELT] < 1.0:
        # The accelerometer in the frame the gyro has felt so far, not in the level one: the
        # body levels within the step, the gyro over LEVEL_S, so an IMU that read the level
        # frame's specific force would tell a dead reckoning it accelerated sideways by
        # g sin(tilt) for the levelling (seen: 0.2 m/s after a 9.5 deg touchdown, MoCap
        # then "off" the IMU). f_felt = R(exp(rem)) f_level, rem the rotation not felt yet.
        left = 1.0 - s[S_ROT_FELT]
        k0, k1, k2 = left * s[S_ROT_IMPULSE], left * s[S_ROT_IMPULSE + 1], \
            left * s[S_ROT_IMPULSE + 2]
        th = math.sqrt(k0 * k0 + k1 * k1 + k2 * k2)
        if th > 1e-12:
            k0, k1, k2 = k0 / th, k1 / th, k2 / th
            c, sn = math.cos(th), math.sin(th)
            v0, v1, v2 = s[S_SPECIFIC], s[S_SPECIFIC + 1], s[S_SPECIFIC + 2]
            kv = (k0 * v0 + k1 * v1 + k2 * v2) * (1.0 - c)
            s[S_SPECIFIC] = v0 * c + (k1 * v2 - k2 * v1) * sn + k0 * kv
            s[S_SPECIFIC + 1] = v1 * c + (k2 * v0 - k0 * v2) * sn + k1 * kv
            s[S_SPECIFIC + 2] = v2 * c + (k0 * v1 - k1 * v0) * sn + k2 * kv

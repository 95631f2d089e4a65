"""The flying FAST-Hex: rigid-body physics with what the controller's model leaves out.

Newton-Euler in the world frame (z up) for position and body frame for rotation::

    m pdd   = R_B F_b + F_ext - m g e3
    J wd    = tau_b - w x (J w + h)
    qd      = 1/2 q (x) (0, w)

integrated with a fixed-step RK4 at ``physics_rate_hz`` (default 1 kHz, twice the controller
rate); the quaternion is renormalised after each step. The body wrench is summed per propeller
from first principles, not from the controller's allocation matrix:

- propeller i sits at ``l Rz((i-1) pi/3) e1``; its axis is ``Rz((i-1) pi/3) Rx(alpha_i) Ry(beta_i)
  e3`` where alpha_i is the *actual* tilt of that propeller through the Cardan chain
  (:func:`cardan_tilts`, paper eq. Cardan with the index fixed; nominal ``+-alpha`` when the chain
  is off) and beta_i a fixed random misalignment (paper-notes item 1);
- thrust ``c_f,i w_i^2`` along the axis with a per-rotor spread of c_f; drag torque
  ``(-1)^i c_tau f_i`` along the axis; arm moment ``p_i x f_i``;
- rotor speeds follow their set-points with a first-order lag (exact discretisation);
- the servo moves the synchronised tilt towards its goal at the tilt rate limit;
- gyroscopic effects of the spinning rotors: ``w x h`` in Euler's equation and the reaction
  ``-dh/dt`` to spinning up/down and to tilting (h_i = I_r 2 pi w_i s_i axis_i);
- external forces: a tether pulling towards an anchor point and a 3-axis Ornstein-Uhlenbeck
  force (slowly varying unmodelled aerodynamics, paper-notes), plus a scenario's scheduled
  forces and torques (:class:`sim_backend.scenario.DisturbanceSchedule`, from
  :meth:`start_scenario` on);
- a scenario's plant (:class:`sim_backend.scenario.PlantOverrides`): ``params`` is then the
  plant's (:func:`sim_backend.scenario.plant_params`: mass with the payload) and the overrides
  add a full inertia, a centre-of-mass offset ``c`` (body), per-rotor c_f and c_tau scales,
  propeller and arm misalignment and the rotor lag. With an offset the state integrated is the
  centre of mass's (Newton about it, Euler about it with the rotor moments taken about it);
  :meth:`state` and the MoCap report O_B (``p_B = p_C - R c``), and the accelerometer reads the
  specific force of the centre of mass (its lever-arm terms vanish in hover);
- ground contact: the vehicle starts at rest on its landing gear (``ground_height_m`` is the
  height of O_B when resting). It stays put while the net vertical force pushes it down, lifts
  off when the rotors carry it, and on touchdown it comes to rest level (inelastic contact; the
  touchdown speeds are recorded).

All random quantities come from one seeded ``numpy`` generator: two simulators with the same
parameters and seed produce the same flight. The per-step code runs on Python floats.

Besides its fast in-process API (:meth:`state`, :meth:`specific_force_b`, :meth:`poll_mocap`)
the simulator implements :class:`sim_backend.vehicle.EmulatedVehicle` for the device emulators.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from controller.model import CARDAN_JOINTS_PER_PROPELLER
from controller.params import VehicleParams
from controller.reference import IDENTITY_Q, Quat, Vec3, VehicleState, quat_to_rot
from sim_backend.disturbances import DisturbancePreset
from sim_backend.scenario import DisturbanceEvent, DisturbanceSchedule, PlantOverrides
from sim_backend.sensors import ImuModel, MocapModel, NormalStream
from sim_backend.vehicle import ImuReading, PoseReading

TWO_PI = 2.0 * math.pi
N_ROTORS = 6


def cardan_tilts(alpha_des_rad: float, worm_ratio: float, cos_bend: float) -> list[float]:
    """Signed actual tilts of the six propellers (plain-float twin of
    :func:`controller.model.cardan_tilts_rad`)."""
    g = alpha_des_rad / worm_ratio
    stages = [g]
    for _ in range(max(CARDAN_JOINTS_PER_PROPELLER)):
        out = math.atan2(math.sin(g), cos_bend * math.cos(g))
        out += TWO_PI * round((g - out) / TWO_PI)
        stages.append(out)
        g = out
    return [worm_ratio * (1.0 if i % 2 == 0 else -1.0) * stages[n]
            for i, n in enumerate(CARDAN_JOINTS_PER_PROPELLER)]


def _yaw_only(q: Quat) -> Quat:
    w, x, y, z = q
    yaw = math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    return (math.cos(0.5 * yaw), 0.0, 0.0, math.sin(0.5 * yaw))


class FastHexSimulator:
    """The simulated FAST-Hex. Not thread-safe: one owner (or calls under one lock)."""

    def __init__(self, params: VehicleParams, preset: DisturbancePreset, *, seed: int = 0,
                 start_pos_w_m: Vec3 = (0.0, 0.0, 0.1), start_q_wb: Quat = IDENTITY_Q,
                 ground_height_m: float | None = None, plant: PlantOverrides | None = None,
                 disturbances: Sequence[DisturbanceEvent] = ()) -> None:
        self.params = params
        self.plant = plant if plant is not None else PlantOverrides()
        self.preset = preset
        self.seed = seed
        rng = np.random.default_rng(seed)
        self._normal = NormalStream(np.random.default_rng(rng.integers(1 << 62)))
        self.imu = ImuModel(preset, np.random.default_rng(rng.integers(1 << 62)))
        self.mocap = MocapModel(preset, np.random.default_rng(rng.integers(1 << 62)))

        self._m = params.mass_kg
        self._g = params.gravity_m_s2
        plant = self.plant
        j = plant.inertia_matrix(params.inertia_diag_kg_m2)
        self._j = (float(j[0, 0]), float(j[1, 1]), float(j[2, 2]))
        # a full inertia takes the slower matrix path of Euler's equation
        off_diagonal = float(abs(j[0, 1]) + abs(j[0, 2]) + abs(j[1, 2]))
        self._j_full = [float(v) for v in j.ravel()] if off_diagonal > 0.0 else None
        self._j_inv = [float(v) for v in np.linalg.inv(j).ravel()]
        self._com = plant.com_offset_b_m
        self._has_com = self._com != (0.0, 0.0, 0.0)
        l_m = params.geometry.arm_length_m
        self._yaw = [i * math.pi / 3.0 + math.radians(plant.arm_yaw_error_deg[i])
                     for i in range(N_ROTORS)]
        self._pos = [(l_m * math.cos(y), l_m * math.sin(y), 0.0) for y in self._yaw]
        ccw = 1.0 if params.rotors.first_rotor_ccw else -1.0
        #: +1 where the propeller spins about +axis; the drag torque opposes the spin
        self._spin_sign = [ccw * (1.0 if i % 2 == 0 else -1.0) for i in range(N_ROTORS)]
        self._c_tau = [params.rotors.drag_coeff_m * s for s in plant.drag_coeff_scale]
        spread = preset.thrust_coeff_spread
        c_f = params.rotors.thrust_coeff_n_per_hz2
        # the random draws do not depend on the plant: one seed, the same noise for any plant
        #: actual per-rotor thrust coefficients (N/Hz^2)
        self.c_f_actual = [float(c_f * (1.0 + spread * u)) * s
                           for u, s in zip(rng.uniform(-1.0, 1.0, N_ROTORS),
                                           plant.thrust_coeff_scale, strict=True)]
        #: fixed misalignment of each propeller about its arm's y axis (rad)
        self.misalignment_rad = [
            float(b) + math.radians(extra) for b, extra in
            zip(rng.normal(0.0, math.radians(preset.misalignment_deg), N_ROTORS),
                plant.propeller_misalignment_deg, strict=True)]
        self._i_r = preset.rotor_inertia_kg_m2
        self._tau_rotor = (preset.rotor_time_constant_s if plant.rotor_time_constant_s is None
                           else plant.rotor_time_constant_s)
        #: the scenario's scheduled forces and torques (they act from start_scenario on)
        self.schedule = DisturbanceSchedule(disturbances)
        self._tilt_frozen = False
        self._worm = params.tilt.worm_ratio
        self._cos_bend = math.cos(math.radians(params.tilt.cardan_bend_deg))
        self._cardan = preset.cardan_chain
        self._tilt_rate = math.radians(params.tilt.max_rate_deg_s)
        self._tilt_max = math.radians(params.tilt.mechanical_limit_deg)
        # the preset gives the rms of the force vector; each axis carries a third of the power
        self._ou_rms = preset.ou_force_rms_n / math.sqrt(3.0)
        self._ou_tau = preset.ou_force_tau_s
        self._tether_n = preset.tether_force_n
        self._anchor = preset.tether_anchor_w_m

        self._dt = 1.0 / preset.physics_rate_hz
        self._t = 0.0
        self.ground_height_m = start_pos_w_m[2] if ground_height_m is None else ground_height_m
        q0 = _yaw_only(start_q_wb)
        # the state is the centre of mass's: O_B + R c
        rc = self._r_com(q0)
        self._x = [start_pos_w_m[0] + rc[0], start_pos_w_m[1] + rc[1],
                   self.ground_height_m + rc[2], 0.0, 0.0, 0.0,
                   q0[0], q0[1], q0[2], q0[3], 0.0, 0.0, 0.0]
        self.landed = True
        #: vertical speeds (m/s, positive down) at each touchdown
        self.touchdown_speeds_m_s: list[float] = []
        self._w = [0.0] * N_ROTORS
        self._w_cmd = [0.0] * N_ROTORS
        # a fixed-tilt airframe (min = max tilt, rate 0) is built at its tilt
        self._servo = self._servo_goal = math.radians(params.tilt.min_tilt_deg)
        self._ou = [0.0, 0.0, 0.0]
        self._fb: Vec3 = (0.0, 0.0, 0.0)
        self._fext: Vec3 = (0.0, 0.0, 0.0)
        self._set_tilts(self._servo)

    def _r_com(self, q: Quat) -> Vec3:
        """R c: from O_B to the centre of mass, world frame."""
        if not self._has_com:
            return (0.0, 0.0, 0.0)
        r, c = quat_to_rot(q), self._com
        return (r[0] * c[0] + r[1] * c[1] + r[2] * c[2],
                r[3] * c[0] + r[4] * c[1] + r[5] * c[2],
                r[6] * c[0] + r[7] * c[1] + r[8] * c[2])

    def _origin_w_m(self) -> Vec3:
        """Position of O_B (world): the centre of mass less R c."""
        x = self._x
        rc = self._r_com((x[6], x[7], x[8], x[9]))
        return (x[0] - rc[0], x[1] - rc[1], x[2] - rc[2])

    def start_scenario(self, t0_s: float | None = None) -> None:
        """Mission time 0 of the scenario's schedule is simulated time ``t0_s`` (default:
        now)."""
        self.schedule.t0_s = self._t if t0_s is None else t0_s

    # -- geometry of the propellers ---------------------------------------------------------
    def _set_tilts(self, servo_rad: float) -> list[float]:
        if self._cardan:
            tilts = cardan_tilts(servo_rad, self._worm, self._cos_bend)
        else:
            tilts = [servo_rad if i % 2 == 0 else -servo_rad for i in range(N_ROTORS)]
        axes, daxes, moments = [], [], []
        for i in range(N_ROTORS):
            sa, ca = math.sin(tilts[i]), math.cos(tilts[i])
            sb, cb = math.sin(self.misalignment_rad[i]), math.cos(self.misalignment_rad[i])
            sy, cy = math.sin(self._yaw[i]), math.cos(self._yaw[i])
            lx, ly, lz = sb, -sa * cb, ca * cb          # Rx(a) Ry(b) e3
            dx, dy, dz = 0.0, -ca * cb, -sa * cb        # d/da
            ax = (cy * lx - sy * ly, sy * lx + cy * ly, lz)
            axes.append(ax)
            daxes.append((cy * dx - sy * dy, sy * dx + cy * dy, dz))
            # the rotor moments act about the centre of mass
            c = self._com
            px, py, pz = (self._pos[i][0] - c[0], self._pos[i][1] - c[1],
                          self._pos[i][2] - c[2])
            d = -self._spin_sign[i] * self._c_tau[i]
            moments.append((py * ax[2] - pz * ax[1] + d * ax[0],
                            pz * ax[0] - px * ax[2] + d * ax[1],
                            px * ax[1] - py * ax[0] + d * ax[2]))
        self._tilts = tilts
        self._axes, self._daxes, self._moments = axes, daxes, moments
        return tilts

    def propeller_tilts_rad(self) -> tuple[float, ...]:
        """The six actual signed propeller tilts (rad)."""
        return tuple(self._tilts)

    # -- physics -----------------------------------------------------------------------------
    def _substep(self, h: float) -> None:
        # servo: rate-limited towards the goal; per-propeller tilt rates for the gyroscopic term
        tilt_rates = None
        if self._servo != self._servo_goal:
            step = self._tilt_rate * h
            d = self._servo_goal - self._servo
            self._servo += step if d > step else (-step if d < -step else d)
            old = self._tilts
            new = self._set_tilts(self._servo)
            tilt_rates = [(new[i] - old[i]) / h for i in range(N_ROTORS)]

        # rotors: first-order lag, exact over the step
        w, cmd = self._w, self._w_cmd
        if self._tau_rotor > 0.0:
            a = 1.0 - math.exp(-h / self._tau_rotor)
            wdot = [(cmd[i] - w[i]) / self._tau_rotor for i in range(N_ROTORS)]
            w = [w[i] + (cmd[i] - w[i]) * a for i in range(N_ROTORS)]
        else:
            wdot = [0.0] * N_ROTORS
            w = list(cmd)
        self._w = w

        # body wrench, propeller by propeller
        fx = fy = fz = tx = ty = tz = hx = hy = hz = 0.0
        axes, moments, c_f = self._axes, self._moments, self.c_f_actual
        i_r = self._i_r
        for i in range(N_ROTORS):
            f = c_f[i] * w[i] * w[i]
            ax, mo = axes[i], moments[i]
            fx += f * ax[0]
            fy += f * ax[1]
            fz += f * ax[2]
            tx += f * mo[0]
            ty += f * mo[1]
            tz += f * mo[2]
            if i_r > 0.0:
                k = i_r * TWO_PI * self._spin_sign[i]
                kw = k * w[i]
                hx += kw * ax[0]
                hy += kw * ax[1]
                hz += kw * ax[2]
                # reaction to dh/dt: spin-up along the axis, tilting turns the axis
                kd = k * wdot[i]
                tx -= kd * ax[0]
                ty -= kd * ax[1]
                tz -= kd * ax[2]
                if tilt_rates is not None:
                    da = self._daxes[i]
                    kt = kw * tilt_rates[i]
                    tx -= kt * da[0]
                    ty -= kt * da[1]
                    tz -= kt * da[2]

        x = self._x
        ex = ey = ez = 0.0
        wrench = self.schedule.wrench(self._t) if self.schedule.t0_s is not None else None
        if wrench is not None:  # the scenario's: world force, body force, torques (at C)
            (ex, ey, ez), f_b, t_w, t_b = wrench
            fx, fy, fz = fx + f_b[0], fy + f_b[1], fz + f_b[2]
            tx, ty, tz = tx + t_b[0], ty + t_b[1], tz + t_b[2]
            if t_w != (0.0, 0.0, 0.0):
                r = quat_to_rot((x[6], x[7], x[8], x[9]))  # body torque = R^T world torque
                tx += r[0] * t_w[0] + r[3] * t_w[1] + r[6] * t_w[2]
                ty += r[1] * t_w[0] + r[4] * t_w[1] + r[7] * t_w[2]
                tz += r[2] * t_w[0] + r[5] * t_w[1] + r[8] * t_w[2]
        self._fb = (fx, fy, fz)

        # external forces (world)
        if self._tether_n > 0.0:
            dx, dy, dz = (self._anchor[0] - x[0], self._anchor[1] - x[1],
                          self._anchor[2] - x[2])
            n = math.sqrt(dx * dx + dy * dy + dz * dz)
            if n > 1e-9:
                ex, ey, ez = (ex + self._tether_n * dx / n, ey + self._tether_n * dy / n,
                              ez + self._tether_n * dz / n)
        if self._ou_rms > 0.0:
            phi = math.exp(-h / self._ou_tau)
            s = self._ou_rms * math.sqrt(1.0 - phi * phi)
            ou, nrm = self._ou, self._normal
            ou[0] = phi * ou[0] + s * nrm()
            ou[1] = phi * ou[1] + s * nrm()
            ou[2] = phi * ou[2] + s * nrm()
            ex, ey, ez = ex + ou[0], ey + ou[1], ez + ou[2]
        self._fext = (ex, ey, ez)

        m, g = self._m, self._g
        if self.landed:
            r = quat_to_rot((x[6], x[7], x[8], x[9]))
            lift = r[6] * fx + r[7] * fy + r[8] * fz + ez - m * g
            if lift <= 0.0:
                self._advance_time(h)
                return
            self.landed = False

        jx, jy, jz = self._j
        j_full, ji = self._j_full, self._j_inv
        inv_m = 1.0 / m

        def deriv(s: list[float]) -> list[float]:
            qw, qx, qy, qz = s[6], s[7], s[8], s[9]
            wx, wy, wz = s[10], s[11], s[12]
            # R (body -> world) applied to F_b
            xx, yy, zz = qx * qx, qy * qy, qz * qz
            xy, xz, yz = qx * qy, qx * qz, qy * qz
            wqx, wqy, wqz = qw * qx, qw * qy, qw * qz
            ax_ = ((1.0 - 2.0 * (yy + zz)) * fx + 2.0 * (xy - wqz) * fy + 2.0 * (xz + wqy) * fz
                   + ex) * inv_m
            ay_ = (2.0 * (xy + wqz) * fx + (1.0 - 2.0 * (xx + zz)) * fy + 2.0 * (yz - wqx) * fz
                   + ey) * inv_m
            az_ = (2.0 * (xz - wqy) * fx + 2.0 * (yz + wqx) * fy + (1.0 - 2.0 * (xx + yy)) * fz
                   + ez) * inv_m - g
            if j_full is None:
                lx, ly, lz = jx * wx + hx, jy * wy + hy, jz * wz + hz
                dwx = (tx - (wy * lz - wz * ly)) / jx
                dwy = (ty - (wz * lx - wx * lz)) / jy
                dwz = (tz - (wx * ly - wy * lx)) / jz
            else:  # J w' = tau - w x (J w + h), J full
                j = j_full
                lx = j[0] * wx + j[1] * wy + j[2] * wz + hx
                ly = j[3] * wx + j[4] * wy + j[5] * wz + hy
                lz = j[6] * wx + j[7] * wy + j[8] * wz + hz
                rx_ = tx - (wy * lz - wz * ly)
                ry_ = ty - (wz * lx - wx * lz)
                rz_ = tz - (wx * ly - wy * lx)
                dwx = ji[0] * rx_ + ji[1] * ry_ + ji[2] * rz_
                dwy = ji[3] * rx_ + ji[4] * ry_ + ji[5] * rz_
                dwz = ji[6] * rx_ + ji[7] * ry_ + ji[8] * rz_
            return [s[3], s[4], s[5], ax_, ay_, az_,
                    0.5 * (-qx * wx - qy * wy - qz * wz),
                    0.5 * (qw * wx + qy * wz - qz * wy),
                    0.5 * (qw * wy - qx * wz + qz * wx),
                    0.5 * (qw * wz + qx * wy - qy * wx),
                    dwx, dwy, dwz]

        hh = 0.5 * h
        k1 = deriv(x)
        k2 = deriv([a + hh * b for a, b in zip(x, k1, strict=True)])
        k3 = deriv([a + hh * b for a, b in zip(x, k2, strict=True)])
        k4 = deriv([a + h * b for a, b in zip(x, k3, strict=True)])
        h6 = h / 6.0
        x = [a + h6 * (b1 + 2.0 * (b2 + b3) + b4)
             for a, b1, b2, b3, b4 in zip(x, k1, k2, k3, k4, strict=True)]
        qn = 1.0 / math.sqrt(x[6] * x[6] + x[7] * x[7] + x[8] * x[8] + x[9] * x[9])
        x[6] *= qn
        x[7] *= qn
        x[8] *= qn
        x[9] *= qn
        rc = self._r_com((x[6], x[7], x[8], x[9]))
        if x[2] - rc[2] < self.ground_height_m:  # O_B below its resting height
            self.touchdown_speeds_m_s.append(-x[5])
            q = _yaw_only((x[6], x[7], x[8], x[9]))
            rc0 = self._r_com(q)
            x = [x[0] - rc[0] + rc0[0], x[1] - rc[1] + rc0[1], self.ground_height_m + rc0[2],
                 0.0, 0.0, 0.0, q[0], q[1], q[2], q[3], 0.0, 0.0, 0.0]
            self.landed = True
        self._x = x
        self._advance_time(h)

    def _advance_time(self, h: float) -> None:
        self._t += h
        x = self._x
        self.mocap.maybe_capture(self._t, self._origin_w_m(), (x[6], x[7], x[8], x[9]))

    # -- fast in-process API -----------------------------------------------------------------
    def state(self) -> VehicleState:
        """The true state of O_B (with a centre-of-mass offset: moved from the centre of
        mass's, v_B = v_C - R (w x c))."""
        x = self._x
        if not self._has_com:
            return VehicleState((x[0], x[1], x[2]), (x[3], x[4], x[5]),
                                (x[6], x[7], x[8], x[9]), (x[10], x[11], x[12]))
        q: Quat = (x[6], x[7], x[8], x[9])
        r, c = quat_to_rot(q), self._com
        wx, wy, wz = x[10], x[11], x[12]
        wc = (wy * c[2] - wz * c[1], wz * c[0] - wx * c[2], wx * c[1] - wy * c[0])
        rc = self._r_com(q)
        return VehicleState(
            (x[0] - rc[0], x[1] - rc[1], x[2] - rc[2]),
            (x[3] - (r[0] * wc[0] + r[1] * wc[1] + r[2] * wc[2]),
             x[4] - (r[3] * wc[0] + r[4] * wc[1] + r[5] * wc[2]),
             x[5] - (r[6] * wc[0] + r[7] * wc[1] + r[8] * wc[2])),
            q, (wx, wy, wz))

    def specific_force_b(self) -> Vec3:
        """What an ideal accelerometer reads (m/s^2, body): (F_b + R^T F_ext) / m, or the
        ground's reaction when resting."""
        x = self._x
        r = quat_to_rot((x[6], x[7], x[8], x[9]))
        if self.landed:
            g = self._g
            return (r[6] * g, r[7] * g, r[8] * g)
        fb, fe, m = self._fb, self._fext, self._m
        return ((fb[0] + r[0] * fe[0] + r[3] * fe[1] + r[6] * fe[2]) / m,
                (fb[1] + r[1] * fe[0] + r[4] * fe[1] + r[7] * fe[2]) / m,
                (fb[2] + r[2] * fe[0] + r[5] * fe[1] + r[8] * fe[2]) / m)

    def external_force_w_n(self) -> Vec3:
        """Tether + OU force of the last step (world, N)."""
        return self._fext

    def poll_mocap(self) -> list[PoseReading]:
        """MoCap frames that have arrived by now (capture-time stamped)."""
        return self.mocap.poll(self._t)

    # -- EmulatedVehicle ---------------------------------------------------------------------
    def now_s(self) -> float:
        return self._t

    def advance(self, dt_s: float) -> None:
        if dt_s <= 0.0:
            return
        n = max(1, math.ceil(dt_s / self._dt - 1e-9))
        h = dt_s / n
        for _ in range(n):
            self._substep(h)

    def command_rotor_speeds_hz(self, speeds_hz: Sequence[float]) -> None:
        if len(speeds_hz) != N_ROTORS:
            raise ValueError(f"expected {N_ROTORS} rotor speeds, got {len(speeds_hz)}")
        self._w_cmd = [max(0.0, float(s)) for s in speeds_hz]

    def rotor_speeds_hz(self) -> tuple[float, ...]:
        return tuple(self._w)

    def motor_currents_a(self) -> tuple[float, ...]:
        # ~0.2 A idle, ~8 A at 100 Hz for a 12" propeller on an MK3638: cubic in speed
        return tuple(0.2 * (s > 0.5) + 8.0 * (s / 100.0) ** 3 for s in self._w)

    def read_imu(self) -> ImuReading:
        x = self._x
        return self.imu.sample(self._t, (x[10], x[11], x[12]), self.specific_force_b())

    def scale_rotor_thrust(self, scale: float, rotor: int | None = None) -> None:
        """Fault hook: every rotor's thrust coefficient, or only rotor ``rotor`` (1..6), times
        ``scale`` from now on (0: the propellers are off or the rotors produce no thrust; 0.5:
        a weak battery or wrong props). The drag torques follow the rotor speeds as before."""
        self.c_f_actual = [c * scale if rotor is None or i == rotor - 1 else c
                           for i, c in enumerate(self.c_f_actual)]

    def freeze_tilt(self) -> None:
        """Fault hook (a silent servo): tilt commands are ignored from now on; the drive still
        finishes the move it was last told to make, as the servo does."""
        self._tilt_frozen = True

    def kick_body_rate(self, d_omega_b_rad_s: Vec3) -> None:
        """Fault hook: an impulsive torque (a blow to the airframe) changes the body rate by
        ``d_omega_b_rad_s`` at once. No effect while resting on the ground."""
        if self.landed:
            return
        x = self._x
        x[10] += d_omega_b_rad_s[0]
        x[11] += d_omega_b_rad_s[1]
        x[12] += d_omega_b_rad_s[2]

    def command_tilt_rad(self, tilt_rad: float) -> None:
        if self._tilt_frozen:
            return
        self._servo_goal = min(max(float(tilt_rad), 0.0), self._tilt_max)

    def tilt_rad(self) -> float:
        return self._servo

    def true_pose(self) -> PoseReading:
        x = self._x
        return PoseReading(self._t, self._origin_w_m(), (x[6], x[7], x[8], x[9]))

    def battery_voltage_v(self) -> float:
        return 16.4 - 0.02 * sum(self.motor_currents_a())

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
parameters and seed produce the same flight. The physics step is compiled
(:mod:`sim_backend.physics`, numba, warmed up in the constructor); the per-tick API (state,
IMU, MoCap) hands out Python floats.

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
from sim_backend import physics as phy
from sim_backend.disturbances import DisturbancePreset
from sim_backend.scenario import DisturbanceEvent, DisturbanceSchedule, PlantOverrides
from sim_backend.sensors import ImuModel, MocapModel
from sim_backend.vehicle import ImuReading, PoseReading

TWO_PI = 2.0 * math.pi
N_ROTORS = 6
#: standard normals drawn at a time for the OU force
NORMAL_BLOCK = 4096
assert tuple(CARDAN_JOINTS_PER_PROPELLER) == phy.CARDAN_JOINTS, "physics.set_tilts unrolls it"


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
        # the OU force's standard normals, drawn in blocks (as sensors.NormalStream hands them)
        self._normal_rng = np.random.default_rng(rng.integers(1 << 62))
        self.imu = ImuModel(preset, np.random.default_rng(rng.integers(1 << 62)))
        self.mocap = MocapModel(preset, np.random.default_rng(rng.integers(1 << 62)))

        self._m = params.mass_kg
        self._g = params.gravity_m_s2
        plant = self.plant
        j = plant.inertia_matrix(params.inertia_diag_kg_m2)
        # a full inertia takes the slower matrix path of Euler's equation
        off_diagonal = float(abs(j[0, 1]) + abs(j[0, 2]) + abs(j[1, 2]))
        self._com = plant.com_offset_b_m
        self._has_com = self._com != (0.0, 0.0, 0.0)
        l_m = params.geometry.arm_length_m
        yaw = [i * math.pi / 3.0 + math.radians(plant.arm_yaw_error_deg[i])
               for i in range(N_ROTORS)]
        ccw = 1.0 if params.rotors.first_rotor_ccw else -1.0
        spread = preset.thrust_coeff_spread
        c_f = params.rotors.thrust_coeff_n_per_hz2
        # the random draws do not depend on the plant: one seed, the same noise for any plant
        c_f_actual = [float(c_f * (1.0 + spread * u)) * s
                      for u, s in zip(rng.uniform(-1.0, 1.0, N_ROTORS),
                                      plant.thrust_coeff_scale, strict=True)]
        #: fixed misalignment of each propeller about its arm's y axis (rad)
        self.misalignment_rad = [
            float(b) + math.radians(extra) for b, extra in
            zip(rng.normal(0.0, math.radians(preset.misalignment_deg), N_ROTORS),
                plant.propeller_misalignment_deg, strict=True)]
        #: the scenario's scheduled forces and torques (they act from start_scenario on)
        self.schedule = DisturbanceSchedule(disturbances)
        self._tilt_frozen = False
        self._tilt_max = math.radians(params.tilt.mechanical_limit_deg)
        self._dt = 1.0 / preset.physics_rate_hz

        p = np.zeros(phy.N_PARAMS)
        p[phy.P_M], p[phy.P_G] = self._m, self._g
        p[phy.P_J:phy.P_J + 3] = (j[0, 0], j[1, 1], j[2, 2])
        p[phy.P_J_FULL] = 1.0 if off_diagonal > 0.0 else 0.0
        p[phy.P_J_MAT:phy.P_J_MAT + 9] = j.ravel()
        p[phy.P_J_INV:phy.P_J_INV + 9] = np.linalg.inv(j).ravel()
        p[phy.P_COM:phy.P_COM + 3] = self._com
        p[phy.P_HAS_COM] = 1.0 if self._has_com else 0.0
        p[phy.P_I_R] = preset.rotor_inertia_kg_m2
        p[phy.P_TAU_ROTOR] = (preset.rotor_time_constant_s if plant.rotor_time_constant_s is None
                              else plant.rotor_time_constant_s)
        p[phy.P_TILT_RATE] = math.radians(params.tilt.max_rate_deg_s)
        p[phy.P_WORM] = params.tilt.worm_ratio
        p[phy.P_COS_BEND] = math.cos(math.radians(params.tilt.cardan_bend_deg))
        p[phy.P_CARDAN] = 1.0 if preset.cardan_chain else 0.0
        # the preset gives the rms of the force vector; each axis carries a third of the power
        p[phy.P_OU_RMS] = preset.ou_force_rms_n / math.sqrt(3.0)
        p[phy.P_OU_TAU] = preset.ou_force_tau_s
        p[phy.P_TETHER] = preset.tether_force_n
        p[phy.P_ANCHOR:phy.P_ANCHOR + 3] = preset.tether_anchor_w_m
        p[phy.P_MISALIGN:phy.P_MISALIGN + N_ROTORS] = self.misalignment_rad
        p[phy.P_YAW:phy.P_YAW + N_ROTORS] = yaw
        p[phy.P_POS:phy.P_POS + 3 * N_ROTORS] = [
            v for y in yaw for v in (l_m * math.cos(y), l_m * math.sin(y), 0.0)]
        #: +1 where the propeller spins about +axis; the drag torque opposes the spin
        p[phy.P_SPIN:phy.P_SPIN + N_ROTORS] = [ccw * (1.0 if i % 2 == 0 else -1.0)
                                               for i in range(N_ROTORS)]
        p[phy.P_C_TAU:phy.P_C_TAU + N_ROTORS] = [params.rotors.drag_coeff_m * s
                                                 for s in plant.drag_coeff_scale]
        self._p = p
        self._ou_on = p[phy.P_OU_RMS] > 0.0

        self._t = 0.0
        self.ground_height_m = start_pos_w_m[2] if ground_height_m is None else ground_height_m
        q0 = _yaw_only(start_q_wb)
        # the state is the centre of mass's: O_B + R c
        rc = self._r_com(q0)
        st = np.zeros(phy.N_STATE)
        st[phy.S_X:phy.S_X + 13] = [
            start_pos_w_m[0] + rc[0], start_pos_w_m[1] + rc[1], self.ground_height_m + rc[2],
            0.0, 0.0, 0.0, q0[0], q0[1], q0[2], q0[3], 0.0, 0.0, 0.0]
        st[phy.S_LANDED] = 1.0
        st[phy.S_ROT_FELT] = 1.0   # no touchdown's levelling to feel
        self._felt_last = False     # the previous IMU sample still felt a levelling
        st[phy.S_C_F:phy.S_C_F + N_ROTORS] = c_f_actual
        # a fixed-tilt airframe (min = max tilt, rate 0) is built at its tilt
        st[phy.S_SERVO] = st[phy.S_SERVO_GOAL] = math.radians(params.tilt.min_tilt_deg)
        phy.set_tilts(st, p, st[phy.S_SERVO])
        phy.specific_force(st, p)
        self._s = st
        self._w_cmd: tuple[float, ...] = (0.0,) * N_ROTORS
        self._servo_goal = float(st[phy.S_SERVO_GOAL])
        #: vertical speeds (m/s, positive down) at each touchdown
        self.touchdown_speeds_m_s: list[float] = []
        self._normals = np.zeros(0)
        self._k_normal = 0
        self._out = np.empty((0, phy.N_OUT))
        self._wrenches = np.zeros((0, phy.N_WRENCH))
        self._read_back()
        self.warm_up()

    @property
    def ground_height_m(self) -> float:
        """Height of O_B resting on the landing gear (m)."""
        return float(self._p[phy.P_GROUND])

    @ground_height_m.setter
    def ground_height_m(self, value: float) -> None:
        self._p[phy.P_GROUND] = value

    @property
    def c_f_actual(self) -> list[float]:
        """Actual per-rotor thrust coefficients (N/Hz^2)."""
        return self._s[phy.S_C_F:phy.S_C_F + N_ROTORS].tolist()

    @c_f_actual.setter
    def c_f_actual(self, value: Sequence[float]) -> None:
        self._s[phy.S_C_F:phy.S_C_F + N_ROTORS] = value

    @property
    def landed(self) -> bool:
        """Resting on the ground."""
        return self._r[phy.S_LANDED] != 0.0

    def _read_back(self) -> None:
        """Python floats of what the per-tick API reads (after every change of the state)."""
        r = self._s[:phy.S_READ].tolist()
        self._r = r
        self._x = r[phy.S_X:phy.S_X + 13]
        self._t = r[phy.S_T]
        self._state: VehicleState | None = None  # built on first use (state())

    def warm_up(self) -> None:
        """Compile the physics (or load it from numba's on-disk cache) now, on a copy of the
        state, so that no flight tick waits on the JIT. The constructor calls it."""
        s, wrenches = self._s.copy(), np.zeros((1, phy.N_WRENCH))
        phy.advance(s, self._p, self._dt, 1, np.zeros(3), 0, wrenches, math.inf, 1.0,
                    np.empty((1, phy.N_OUT)), 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, self._servo_goal)
        phy.set_tilts(s, self._p, s[phy.S_SERVO])
        phy.specific_force(s, self._p)

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

    def propeller_tilts_rad(self) -> tuple[float, ...]:
        """The six actual signed propeller tilts (rad)."""
        return tuple(self._s[phy.S_TILTS:phy.S_TILTS + N_ROTORS].tolist())

    # -- physics (sim_backend.physics) --------------------------------------------------------
    def _physics(self, h: float, n: int) -> None:
        """``n`` RK4 substeps of ``h`` seconds, then the MoCap captures and touchdowns they
        brought."""
        if self._ou_on:  # the OU force draws three standard normals per substep
            need = 3 * n
            if self._k_normal + need > len(self._normals):
                fresh = [self._normals[self._k_normal:]]
                have = len(fresh[0])
                while have < need:  # the same sequence as blocks handed out one by one
                    fresh.append(self._normal_rng.standard_normal(NORMAL_BLOCK))
                    have += NORMAL_BLOCK
                self._normals = np.concatenate(fresh)
                self._k_normal = 0
        if len(self._out) < n:
            self._out = np.empty((n, phy.N_OUT))
        if len(self._wrenches) < n:
            self._wrenches = np.zeros((n, phy.N_WRENCH))
        schedule = self.schedule
        scheduled = schedule.t0_s is not None and bool(schedule.events)
        if scheduled:
            wrenches, t = self._wrenches, self._t
            for k in range(n):
                wrench = schedule.wrench(t)
                if wrench is None:
                    wrenches[k, phy.W_ON] = 0.0
                else:
                    (ex, ey, ez), f_b, t_w, t_b = wrench
                    wrenches[k] = (1.0, ex, ey, ez, *f_b, *t_w, *t_b)
                t += h
        mocap = self.mocap
        w = self._w_cmd
        events = phy.advance(self._s, self._p, h, n, self._normals, self._k_normal,
                             self._wrenches, mocap.next_capture_s, mocap.period_s, self._out,
                             w[0], w[1], w[2], w[3], w[4], w[5], self._servo_goal)
        if scheduled:
            self._wrenches[:n, phy.W_ON] = 0.0
        if self._ou_on:
            self._k_normal += 3 * n
        self._read_back()
        if events:
            for row in self._out[:n].tolist():
                if row[phy.O_CAPTURE] != 0.0:
                    mocap.maybe_capture(row[phy.O_T], (row[1], row[2], row[3]),
                                        (row[4], row[5], row[6], row[7]))
                if not math.isnan(row[phy.O_TOUCHDOWN]):
                    self.touchdown_speeds_m_s.append(row[phy.O_TOUCHDOWN])

    # -- fast in-process API -----------------------------------------------------------------
    def state(self) -> VehicleState:
        """The true state of O_B (with a centre-of-mass offset: moved from the centre of
        mass's, v_B = v_C - R (w x c)). Built once per step: the state source and the record
        both read it."""
        if self._state is None:
            self._state = self._build_state()
        return self._state

    def _build_state(self) -> VehicleState:
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
        v = self._r
        return (v[phy.S_SPECIFIC], v[phy.S_SPECIFIC + 1], v[phy.S_SPECIFIC + 2])

    def external_force_w_n(self) -> Vec3:
        """Tether + OU force of the last step (world, N)."""
        v = self._r
        return (v[phy.S_FEXT], v[phy.S_FEXT + 1], v[phy.S_FEXT + 2])

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
        self._physics(dt_s / n, n)

    def command_rotor_speeds_hz(self, speeds_hz: Sequence[float]) -> None:
        if len(speeds_hz) != N_ROTORS:
            raise ValueError(f"expected {N_ROTORS} rotor speeds, got {len(speeds_hz)}")
        # NaN or negative: stopped
        self._w_cmd = tuple([float(s) if s > 0.0 else 0.0 for s in speeds_hz])

    def rotor_speeds_hz(self) -> tuple[float, ...]:
        return tuple(self._r[phy.S_W:phy.S_W + N_ROTORS])

    def motor_currents_a(self) -> tuple[float, ...]:
        # ~0.2 A idle, ~8 A at 100 Hz for a 12" propeller on an MK3638: cubic in speed
        return tuple(0.2 * (s > 0.5) + 8.0 * (s / 100.0) ** 3
                     for s in self._r[phy.S_W:phy.S_W + N_ROTORS])

    def read_imu(self) -> ImuReading:
        v = self._r
        w = phy.S_X + 10
        omega = (v[w], v[w + 1], v[w + 2])
        if self._s.item(phy.S_ROT_FELT) < 1.0 or self._felt_last:
            # a touchdown's levelling, felt by the gyro (physics.LEVEL_S); the sample that
            # completes it carries a share too
            f = self._s[phy.S_GYRO_FELT:phy.S_GYRO_FELT + 3].tolist()
            self._felt_last = self._s.item(phy.S_ROT_FELT) < 1.0
            omega = (omega[0] + f[0], omega[1] + f[1], omega[2] + f[2])
        return self.imu.sample(self._t, omega,
                               (v[phy.S_SPECIFIC], v[phy.S_SPECIFIC + 1], v[phy.S_SPECIFIC + 2]))

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
        w = phy.S_X + 10
        self._s[w:w + 3] += d_omega_b_rad_s
        phy.specific_force(self._s, self._p)
        self._read_back()

    def command_tilt_rad(self, tilt_rad: float) -> None:
        if self._tilt_frozen:
            return
        self._servo_goal = min(max(float(tilt_rad), 0.0), self._tilt_max)

    def tilt_rad(self) -> float:
        return self._r[phy.S_SERVO]

    def true_pose(self) -> PoseReading:
        x = self._x
        return PoseReading(self._t, self._origin_w_m(), (x[6], x[7], x[8], x[9]))

    def battery_voltage_v(self) -> float:
        return 16.4 - 0.02 * sum(self.motor_currents_a())

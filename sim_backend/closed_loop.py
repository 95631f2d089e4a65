"""In-process closed loop: mission -> tilt planner -> controller -> simulator, 500 Hz, no bytes.

The controller acts on what a :class:`StateSource` makes of the sensors: ``update(t_s, imu,
mocap_frames) -> VehicleState`` (the IMU sample of the tick and the MoCap frames that arrived
since the previous tick). :class:`UkfStateSource` runs the project's UKF on the simulated IMU
and MoCap; the default :class:`TruthPlusNoise` feeds the simulator's true state plus white noise
of the preset's ``estimate_*`` standard deviations. A source with a force observer
(:class:`ForceObservingSource`) is told every commanded body force, and its estimate of the
external force goes to the controller, which feeds it forward when the vehicle's
``force_feedforward`` is on.

The loop stops the motors when the mission is over and hands one row per tick to a
:class:`RowSink`, in the field order of the flight record (``groundstation.record.RECORD_DTYPE``,
which the composition root passes in as a ``RecordWriter``; sim_backend does not import the
ground station).

A flight that crashes ends at the crash (:class:`CrashLimits`, :class:`Crash`): a touchdown
faster than :data:`SAFE_TOUCHDOWN_SPEED_M_S`, the vehicle leaving the workspace box, or a
non-finite true state or estimate. What follows a crash has no physical meaning, so the loop
stops there and the result names the reason.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

import numpy as np

from controller.missions import Mission
from controller.params import VehicleParams
from controller.pipeline import FlightComputer
from controller.reference import (
    Quat,
    Vec3,
    VehicleState,
    quat_from_axis_angle,
    quat_mul,
    rot_to_quat,
)
from sim_backend.disturbances import DisturbancePreset
from sim_backend.scenario import InProcessFaults, Scenario
from sim_backend.sensors import NormalStream
from sim_backend.simulator import FastHexSimulator
from sim_backend.vehicle import ImuReading, PoseReading

if TYPE_CHECKING:
    from estimator import EstimatorConfig

CONTROL_RATE_HZ = 500.0
#: a flight ends this long after its mission: the motors are off from the mission's end, so
#: later ticks would only record the vehicle standing (or lying) where it came down
AFTER_MISSION_S = 0.5

SAFE_TOUCHDOWN_SPEED_M_S = 1.0
"""Fastest vertical speed at ground contact that still counts as a landing (m/s).

A planned touchdown (the missions' land segments) arrives at about 0.1 m/s. 1.0 m/s is ten
times that, the speed of a free drop from v^2 / (2 g) = 5 cm, and 0.5 m v^2 = 1.6 J into the
landing gear of the 3.1 kg prototype: above it the gear or the propellers take damage, and what
the simulator records as an inelastic stop is in truth an impact.
"""


@dataclass(frozen=True)
class CrashLimits:
    """What ends a simulated flight as a crash. ``None`` bounds are not checked."""

    max_touchdown_speed_m_s: float = SAFE_TOUCHDOWN_SPEED_M_S
    workspace_min_w_m: Vec3 | None = None
    workspace_max_w_m: Vec3 | None = None


@dataclass(frozen=True)
class Crash:
    """Why and when (mission time, s) a flight crashed; ``kind``: ``impact``, ``workspace`` or
    ``non-finite``."""

    t_s: float
    kind: str
    reason: str


def _finite(s: VehicleState) -> bool:
    # a sum is NaN/inf as soon as one term is (and cheaper than a test per element)
    p, v, q, w = s.pos_w_m, s.vel_w_m_s, s.q_wb, s.omega_b_rad_s
    return math.isfinite(p[0] + p[1] + p[2] + v[0] + v[1] + v[2] + q[0] + q[1] + q[2] + q[3]
                         + w[0] + w[1] + w[2])


def check_crash(t_s: float, limits: CrashLimits, truth: VehicleState, estimate: VehicleState,
                touchdown_speed_m_s: float | None) -> Crash | None:
    """The crash of this tick, if any: ``touchdown_speed_m_s`` is the vertical speed of a
    touchdown that happened during the tick (``None``: none)."""
    if not _finite(truth):
        return Crash(t_s, "non-finite", f"non-finite vehicle state at t = {t_s:.3f} s")
    if not _finite(estimate):
        return Crash(t_s, "non-finite", f"non-finite state estimate at t = {t_s:.3f} s")
    if touchdown_speed_m_s is not None and touchdown_speed_m_s > limits.max_touchdown_speed_m_s:
        return Crash(t_s, "impact", f"impact at {touchdown_speed_m_s:.2f} m/s vertical at "
                     f"t = {t_s:.3f} s (a safe touchdown is <= "
                     f"{limits.max_touchdown_speed_m_s:.2f} m/s)")
    lo, hi = limits.workspace_min_w_m, limits.workspace_max_w_m
    if lo is not None and hi is not None:
        p = truth.pos_w_m
        if lo[0] <= p[0] <= hi[0] and lo[1] <= p[1] <= hi[1] and lo[2] <= p[2] <= hi[2]:
            return None
        for axis, (x, a, b) in enumerate(zip(p, lo, hi, strict=True)):
            if not a <= x <= b:
                where = ", ".join(f"{c:.2f}" for c in p)
                return Crash(t_s, "workspace", f"left the workspace at t = {t_s:.3f} s: "
                             f"({where}) m, {'xyz'[axis]} outside [{a:g}, {b:g}] m")
    return None


class StateSource(Protocol):
    """What turns the tick's sensor data into the state the controller acts on."""

    def update(self, t_s: float, imu: ImuReading, mocap: list[PoseReading]) -> VehicleState:
        ...


class RowSink(Protocol):
    """Receives one flight-record row per tick as its flat values: the ``RECORD_DTYPE``
    fields in order, sub-arrays spelled out (``groundstation.record.flat_row``; the record
    writer packs them without numpy)."""

    def append_flat(self, values: tuple[Any, ...]) -> None:
        ...


class _NullSink:
    def append_flat(self, values: tuple[Any, ...]) -> None:
        pass


class TruthPlusNoise:
    """The simulator's true state plus white noise (the stand-in for the estimator)."""

    def __init__(self, truth: Callable[[], VehicleState], preset: DisturbancePreset,
                 rng: np.random.Generator) -> None:
        self._truth = truth
        self._n = NormalStream(rng)
        self._sp = preset.estimate_pos_noise_m
        self._sv = preset.estimate_vel_noise_m_s
        self._sa = preset.estimate_att_noise_rad
        self._sw = preset.estimate_rate_noise_rad_s

    def update(self, t_s: float, imu: ImuReading, mocap: list[PoseReading]) -> VehicleState:
        s = self._truth()
        sp, sv, sa, sw = self._sp, self._sv, self._sa, self._sw
        if sp == 0.0 and sv == 0.0 and sa == 0.0 and sw == 0.0:
            return s
        p, v, w = s.pos_w_m, s.vel_w_m_s, s.omega_b_rad_s
        q: Quat = s.q_wb
        if sa > 0.0:  # the attitude noise first, then position, velocity and rate
            ax, ay, az, *n = self._n.take(12)  # one draw: the same sequence as 3 then 9
            rx, ry, rz = sa * ax, sa * ay, sa * az
            ang = math.sqrt(rx * rx + ry * ry + rz * rz)
            if ang > 0.0:
                q = quat_mul(q, quat_from_axis_angle((rx / ang, ry / ang, rz / ang), ang))
        else:
            n = self._n.take(9)
        return VehicleState((p[0] + sp * n[0], p[1] + sp * n[1], p[2] + sp * n[2]),
                            (v[0] + sv * n[3], v[1] + sv * n[4], v[2] + sv * n[5]), q,
                            (w[0] + sw * n[6], w[1] + sw * n[7], w[2] + sw * n[8]))


@runtime_checkable
class ForceObservingSource(StateSource, Protocol):
    """A state source with an external-force observer (the controller's force feed-forward).

    The loop reports the body force it commanded (``command_issued``, after every controller
    step) and asks for the estimate before the next one (``external_force_w_n``; ``None``:
    nothing to feed forward yet).
    """

    def command_issued(self, force_b_n: Vec3) -> None:
        ...

    def external_force_w_n(self) -> Vec3 | None:
        ...


class UkfStateSource:
    """The project's UKF (:mod:`estimator`) fed with the simulated IMU and MoCap.

    Until the filter has initialised (a rest period on the ground with MoCap poses), the
    controller gets the newest MoCap pose with zero velocity and the raw gyro. ``cfg`` tunes
    the filter (its mass and gravity are replaced by the vehicle's).

    The force observer gets the body force of the commanded rotor speeds at the measured tilt
    (:meth:`command_issued`): the IMU sample of a tick measures what the previous tick's command
    produced, so each command is handed to the next predict.
    """

    def __init__(self, mass_kg: float, gravity_m_s2: float,
                 cfg: EstimatorConfig | None = None) -> None:
        from estimator import EstimatorConfig, Ukf

        base = cfg if cfg is not None else EstimatorConfig()
        self.ukf = Ukf(replace(base, mass_kg=mass_kg, gravity_m_s2=gravity_m_s2))
        self._last_pose: PoseReading | None = None
        self._force_cmd_b_n: Vec3 | None = None

    def command_issued(self, force_b_n: Vec3) -> None:
        self._force_cmd_b_n = force_b_n

    def external_force_w_n(self) -> Vec3 | None:
        """The observer's estimate (world, N); ``None`` before the filter has initialised or
        while the observer is off."""
        if not self.ukf.initialized or not self.ukf.cfg.force_observer:
            return None
        return self.ukf.force_ext_w_n()

    def update(self, t_s: float, imu: ImuReading, mocap: list[PoseReading]) -> VehicleState:
        self.ukf.predict(imu.t_s, imu.gyro_rad_s, imu.accel_m_s2, self._force_cmd_b_n)
        for f in mocap:
            self.ukf.update_pose(f.t_s, f.pos_w_m, f.q_wb)
            self._last_pose = f
        if not self.ukf.initialized:
            pose = self._last_pose
            if pose is None:
                return VehicleState((0.0, 0.0, 0.0), (0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0),
                                    imu.gyro_rad_s)
            return VehicleState(pose.pos_w_m, (0.0, 0.0, 0.0), pose.q_wb, imu.gyro_rad_s)
        return VehicleState(*self.ukf.output_state())


@dataclass(frozen=True)
class FlightResult:
    metadata: dict[str, Any]
    sim_time_s: float
    wall_time_s: float
    touchdown_speeds_m_s: tuple[float, ...]
    crash: Crash | None = None

    @property
    def realtime_factor(self) -> float:
        """Simulated seconds per wall-clock second."""
        return self.sim_time_s / self.wall_time_s if self.wall_time_s > 0 else math.inf


def fly_mission(params: VehicleParams, mission: Mission, preset: DisturbancePreset, *,
                seed: int = 0, sink: RowSink | None = None,
                duration_s: float | None = None,
                state_source: StateSource | None = None,
                tilt_override_rad: float | None = None,
                preroll_s: float = 0.0,
                on_tick: Callable[[float, FastHexSimulator], None] | None = None,
                crash_limits: CrashLimits | None = None,
                scenario: Scenario | None = None,
                ) -> FlightResult:
    """Fly ``mission`` in the simulator from rest on the ground, one row per tick to ``sink``.

    ``duration_s`` cuts the flight short; it never runs past its default, the mission plus
    :data:`AFTER_MISSION_S` with the motors off.
    ``tilt_override_rad`` replaces the mission's alpha profile by a constant (comparisons).
    ``preroll_s`` runs the sensors and the state source that long on the ground with the motors
    off before the mission clock starts (an estimator's rest-period initialisation); the record
    and the mission time start after it. A :class:`ForceObservingSource` is told every
    commanded body force and its force estimate is handed to the controller (used when the
    vehicle's ``force_feedforward`` is on). ``on_tick(t, sim)`` is called once per mission tick
    after the state source, before the controller (analysis: the simulator's truth).
    ``crash_limits`` (default :class:`CrashLimits` with no workspace) end the flight at a crash,
    named in the result's ``crash``; the crash tick is the last row.
    ``scenario`` (:mod:`sim_backend.scenario`): the simulator flies its plant (the controller
    keeps ``params``), and its disturbances and faults are scheduled from mission time 0. An
    IMU sample a fault loses reaches neither the state source nor the controller: the tick
    holds the last command and writes no row (the ground station's answer to a lost sample);
    the MoCap frames of that tick arrive with the next sample.
    Returns the metadata a record header should carry, with timing.
    """
    computer = FlightComputer(params, mission, tilt_override_rad=tilt_override_rad)
    plant = params if scenario is None else scenario.plant_params(params)
    sim = FastHexSimulator(plant, preset, seed=seed, start_pos_w_m=mission.start_pos_w_m,
                           start_q_wb=mission.start_q_wb,
                           plant=None if scenario is None else scenario.plant,
                           disturbances=() if scenario is None else scenario.disturbances)
    computer.warm_up(sim.tilt_rad())  # before the flight clock starts
    rng = np.random.default_rng([seed, 7])
    source: StateSource = state_source if state_source is not None else \
        TruthPlusNoise(sim.state, preset, rng)
    observer = source if isinstance(source, ForceObservingSource) else None
    meta = {"mission": mission.name, "vehicle": params.name, "preset": preset.name,
            "seed": seed, "rate_hz": CONTROL_RATE_HZ,
            "measured_interval_s": mission.measured_interval_s()}
    if tilt_override_rad is not None:
        meta["tilt_override_deg"] = math.degrees(tilt_override_rad)
    if scenario is not None:
        meta["scenario"] = scenario.name
    writer: RowSink = sink if sink is not None else _NullSink()
    append_flat = writer.append_flat
    end_s = mission.duration_s + AFTER_MISSION_S
    if duration_s is not None:
        end_s = min(end_s, duration_s)
    dt = 1.0 / CONTROL_RATE_HZ
    n_ticks = round(end_s * CONTROL_RATE_HZ)
    c_f = params.rotors.thrust_coeff_n_per_hz2
    limits = crash_limits if crash_limits is not None else CrashLimits()
    crash: Crash | None = None
    wall0 = time.perf_counter()
    for _ in range(round(preroll_s * CONTROL_RATE_HZ)):
        source.update(sim.now_s(), sim.read_imu(), sim.poll_mocap())
        sim.advance(dt)
    t_offset = sim.now_s()
    faults: InProcessFaults | None = None
    if scenario is not None:
        sim.start_scenario(t_offset)
        faults = InProcessFaults(sim, scenario.scheduled_faults(), t_offset)
    touchdowns = len(sim.touchdown_speeds_m_s)
    ticks = 0
    held_mocap: list[PoseReading] = []
    for k in range(n_ticks):
        t = k * dt
        if faults is not None:
            faults.run_due(sim.now_s())
            if faults.imu_lost(sim.now_s()):
                held_mocap += sim.poll_mocap()  # the socket keeps them for the next sample
                sim.advance(dt)  # the last command holds
                continue
        imu = sim.read_imu()
        mocap_frames = sim.poll_mocap()
        if held_mocap:
            mocap_frames, held_mocap = held_mocap + mocap_frames, []
        est = source.update(t + t_offset, imu, mocap_frames)
        if on_tick is not None:
            on_tick(t, sim)
        alpha = sim.tilt_rad()
        tick = computer.step(t, est, alpha, force_ext_w_n=None if observer is None
                             else observer.external_force_w_n())
        ref, cmd = tick.ref, tick.cmd
        sim.command_tilt_rad(tick.alpha_cmd_rad)
        done = t >= mission.duration_s
        spins = (0.0,) * 6 if done else cmd.spin_hz
        sim.command_rotor_speeds_hz(spins)
        # body force and internal-force efficiency of the commanded (clamped) thrusts
        thrusts = [c_f * w * w for w in spins]
        force_b, eta = computer.thrust_force_b(alpha, thrusts)
        if observer is not None:
            observer.command_issued(force_b)
        s = sim.state()
        mask = 0
        for i, flag in enumerate(cmd.saturated):
            if flag:
                mask |= 1 << i
        append_flat((
            t, ref.segment, ref.measured, mask, sim.landed,
            *ref.pos_w_m, *ref.vel_w_m_s, *ref.acc_w_m_s2, *ref.q_wr,
            tick.alpha_ref_rad, tick.alpha_cmd_rad, alpha,
            *rot_to_quat(cmd.r_wd), *s.pos_w_m, *s.vel_w_m_s, *s.q_wb, *s.omega_b_rad_s,
            *est.pos_w_m, *est.q_wb, *spins, *sim.rotor_speeds_hz(), *thrusts,
            *cmd.f_r_w_n, *cmd.u_f_b_n, *cmd.u_tau_b_n_m, cmd.r_xy_n, cmd.theta_rad, eta,
        ))
        sim.advance(dt)
        ticks += 1
        touchdown = None
        if len(sim.touchdown_speeds_m_s) > touchdowns:  # ground contact during this step
            touchdown = max(sim.touchdown_speeds_m_s[touchdowns:])
            touchdowns = len(sim.touchdown_speeds_m_s)
        crash = check_crash(t, limits, s, est, touchdown)
        if crash is not None:
            break
    wall = time.perf_counter() - wall0
    return FlightResult(meta, ticks * dt + t_offset, wall, tuple(sim.touchdown_speeds_m_s),
                        crash)

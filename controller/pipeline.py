"""One control tick of the paper's stack, shared by the simulator and the ground station.

mission reference -> tilt planner (rate-limited alpha command, or ``auto``) -> full-pose
geometric controller (spin rates). Pure: no I/O, no clock; the caller passes the mission time,
the state estimate and the measured tilt, and sends the outputs to its actuators.

Also the failsafe landing reference (:class:`LandHere`): a smooth descent from wherever the
vehicle is when a failsafe fires, keeping its heading, level attitude requested.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

from controller.geometric import Command, GeometricController
from controller.missions import Mission
from controller.model import LateralBound, VehicleModel
from controller.params import VehicleParams
from controller.reference import Quat, Reference, Vec3, VehicleState
from controller.tilt_planner import TiltPlanner
from controller.values import tick_value

#: how often the auto tilt mode re-evaluates the look-ahead lateral demand (s)
AUTO_UPDATE_PERIOD_S = 0.1
#: control ticks :meth:`FlightComputer.rehearse` flies on a copy (CPython 3.11 specialises a
#: function's bytecode after 8 calls; a few more for the branches a hover takes)
REHEARSAL_STEPS = 16


@tick_value
class ControlTick:
    """Everything one tick decided, for the actuators and the flight record."""

    ref: Reference
    alpha_ref_rad: float  # NaN while the planner is in auto mode
    alpha_cmd_rad: float
    cmd: Command


class FlightComputer:
    """Mission, tilt planner and controller for one vehicle (explicit state inside)."""

    def __init__(self, params: VehicleParams, mission: Mission, *,
                 model: VehicleModel | None = None,
                 tilt_override_rad: float | None = None) -> None:
        self.params = params
        self.mission = mission
        self.model = model or VehicleModel(params)
        bound = LateralBound.for_model(self.model)
        self.controller = GeometricController(params, model=self.model, bound=bound)
        # auto plans for the bound the controller enforces: with a larger (unscaled) capability
        # the planner would stop short of the tilt at which R_d stays on R_r
        self.planner = TiltPlanner(params, capability=bound)
        self.tilt_override_rad = tilt_override_rad
        self._next_auto_s = 0.0
        self._axes_alpha = math.nan
        self._axes: list[tuple[float, float, float]] = []
        #: per rotor (sin yaw, cos yaw, tilt sign): the thrust axes in plain floats
        self._axis_terms = [(math.sin(y), math.cos(y), s) for y, s in zip(
            self.model.arm_yaw_rad.tolist(), self.model.tilt_signs.tolist(), strict=True)]

    def warm_up(self, alpha_rad: float | None = None) -> None:
        """Build the per-tilt caches of a tick now (the wrench mapper's 6x6 map, compiled or
        loaded from numba's cache on first use, and the thrust axes of :meth:`thrust_force_b`)
        at the measured tilt ``alpha_rad`` (default: the planner's initial command), so that
        the first step after arming does not. Changes no controller or planner state."""
        alpha = self.planner.alpha_cmd_rad if alpha_rad is None else alpha_rad
        self.controller.mapper.warm_up(alpha)
        self.thrust_force_b(alpha, (0.0,) * len(self.model.arm_yaw_rad))

    def rehearse(self, steps: int = REHEARSAL_STEPS, alpha_rad: float | None = None) -> None:
        """Fly ``steps`` ticks of the mission's start on a throwaway copy of this computer, at
        rest on the start pose: the interpreter specialises a function's bytecode over its
        first few calls, so the first real control tick would run the slow generic path. The
        copy is discarded: this computer's integrators, planner and caches are untouched (its
        ticks are bit-identical with or without a rehearsal)."""
        import copy

        twin = copy.deepcopy(self)
        start = self.mission.reference(0.0)
        state = VehicleState(start.pos_w_m, (0.0, 0.0, 0.0), start.q_wr, (0.0, 0.0, 0.0))
        alpha = self.planner.alpha_cmd_rad if alpha_rad is None else alpha_rad
        zero = (0.0, 0.0, 0.0)
        for k in range(steps):
            tick = twin.step(k * 0.002, state, alpha, force_ext_w_n=zero)
            twin.thrust_force_b(alpha, tick.cmd.thrusts_n)

    def step(self, t_s: float, state: VehicleState, alpha_rad: float,
             ref: Reference | None = None, hold_tilt: bool = False,
             force_ext_w_n: Vec3 | None = None,
             ref_offset_w_m: Vec3 | None = None) -> ControlTick:
        """One tick at mission time ``t_s``. ``ref`` overrides the mission's reference (a
        failsafe landing); ``hold_tilt`` freezes the tilt command at the measured tilt;
        ``force_ext_w_n`` is the estimator's external force, fed forward when the vehicle's
        ``force_feedforward`` is on; ``ref_offset_w_m`` moves the mission's reference (the
        estimate was re-seeded that far: a MoCap frame that jumped)."""
        mission = self.mission
        if ref is None:
            ref = mission.reference(t_s)
            if ref_offset_w_m is not None:
                p, o = ref.pos_w_m, ref_offset_w_m
                ref = replace(ref, pos_w_m=(p[0] + o[0], p[1] + o[1], p[2] + o[2]))
        alpha_ref = ref.alpha_rad if self.tilt_override_rad is None else self.tilt_override_rad
        demand = None
        margin = 0.0
        if hold_tilt:
            alpha_ref = alpha_rad
        elif alpha_ref is None:
            auto = mission.auto_profile(t_s)
            margin = auto.margin_n if auto is not None else 0.0
            if t_s >= self._next_auto_s:
                self._next_auto_s = t_s + AUTO_UPDATE_PERIOD_S
                demand = mission.lateral_demand_n(
                    t_s, auto.horizon_s if auto is not None else 0.0, self.params.mass_kg,
                    self.params.gravity_m_s2)
        alpha_cmd = self.planner.step(t_s, alpha_ref, demand, margin)
        cmd = self.controller.step(t_s, state, ref, alpha_rad, force_ext_w_n)
        return ControlTick(ref, math.nan if alpha_ref is None else alpha_ref, alpha_cmd, cmd)

    def thrust_force_b(self, alpha_rad: float, thrusts_n: Sequence[float]
                       ) -> tuple[Vec3, float]:
        """The body force of the given thrusts at tilt ``alpha_rad`` (N, body frame) and its
        force efficiency eta_f (axes cached per alpha; plain floats, no numpy per call)."""
        if alpha_rad != self._axes_alpha:  # VehicleModel.thrust_axes, without numpy
            axes = []
            for sy, cy, sign in self._axis_terms:
                a = sign * alpha_rad
                s = math.sin(a)
                axes.append((sy * s, -cy * s, math.cos(a)))
            self._axes = axes
            self._axes_alpha = alpha_rad
        fx = fy = fz = tot = 0.0
        for f, a in zip(thrusts_n, self._axes, strict=True):
            fx += f * a[0]
            fy += f * a[1]
            fz += f * a[2]
            tot += f
        eta = math.sqrt(fx * fx + fy * fy + fz * fz) / tot if tot > 0.0 else 1.0
        return (fx, fy, fz), eta

    def force_efficiency(self, alpha_rad: float, thrusts_n: Sequence[float]) -> float:
        """eta_f of the given thrusts at the measured tilt."""
        return self.thrust_force_b(alpha_rad, thrusts_n)[1]


@dataclass(frozen=True)
class LandHere:
    """A failsafe landing: from ``start_pos_w_m`` at ``t0_s`` straight down to ``ground_z_m``
    (O_B height at rest) less ``sink_m``; the heading is kept and a level attitude requested.
    Hands the tilt to the caller (``None``).

    The descent eases in over the first second to ``descent_m_s``, then flares: over the last
    ``flare_m`` above the ground it slows at a constant rate to ``touchdown_m_s``, which it
    keeps into the ground (the estimator does not see a harder impact: see
    ``controller.missions.MAX_TOUCHDOWN_SPEED_M_S``; at 0.3 m/s all the way the vehicle hopped
    off again). From lower than the ease-in and the flare need, it descends at
    ``touchdown_m_s`` throughout.

    ``deep_m_s`` (a blind landing's): once the reference is ``settle_m`` under the ground, past
    where a vehicle flying on a right estimate has touched down, it speeds up at
    ``deep_accel_m_s2`` to this speed. An estimate that gets there without a touchdown is below
    the vehicle, and sinking at the touchdown speed may only hold the vehicle where it is: a dead
    reckoning whose height sinks as fast (seen: 0.12 m/s) hovers it until its sink runs out."""

    t0_s: float
    start_pos_w_m: Vec3
    q_yaw: Quat
    ground_z_m: float
    descent_m_s: float = 0.3
    sink_m: float = 0.05  # aim slightly below the gear so the vehicle settles
    touchdown_m_s: float = 0.12
    flare_m: float = 0.15
    ease_s: float = 1.0  # the descent speed follows a smoothstep over the first second
    deep_m_s: float | None = None
    settle_m: float = 0.05
    deep_accel_m_s2: float = 0.5

    def _profile(self, tau: float) -> tuple[float, float, float]:
        """Distance down (m), descent speed (m/s), its rate (m/s^2) at ``tau`` s in."""
        v1, v2 = self.touchdown_m_s, self.deep_m_s
        if v2 is None or v2 <= v1:
            return self._approach(tau)
        tau_d, dist_d = self._deep_start()
        if tau <= tau_d:
            return self._approach(tau)
        s, a = tau - tau_d, self.deep_accel_m_s2
        t_acc = (v2 - v1) / a
        if s < t_acc:
            return dist_d + v1 * s + 0.5 * a * s * s, v1 + a * s, a
        return dist_d + v1 * t_acc + 0.5 * a * t_acc * t_acc + v2 * (s - t_acc), v2, 0.0

    def _deep_start(self) -> tuple[float, float]:
        """When (s in) and how far down (m) the approach is ``settle_m`` under the ground at
        the touchdown speed (or ends its ease-in, when that is deeper already)."""
        v0, to_ground = self._cruise()
        v1, te = self.touchdown_m_s, self.ease_s
        s_e = 0.5 * v0 * te
        if v0 > v1:
            decel = (v0 * v0 - v1 * v1) / (2.0 * self.flare_m)
            tau_g = te + (to_ground - self.flare_m - s_e) / v0 + (v0 - v1) / decel
            return tau_g + self.settle_m / v1, to_ground + self.settle_m
        dist = max(s_e, to_ground + self.settle_m)
        return te + (dist - s_e) / v1, dist

    def _cruise(self) -> tuple[float, float]:
        """The cruise speed (the touchdown speed's when too low for the ease-in and the
        flare) and the distance to the ground."""
        to_ground = self.start_pos_w_m[2] - self.ground_z_m
        v0 = self.descent_m_s if to_ground >= 0.5 * self.descent_m_s * self.ease_s \
            + self.flare_m else self.touchdown_m_s
        return v0, to_ground

    def _approach(self, tau: float) -> tuple[float, float, float]:
        """The profile down to the ground and on into it at the touchdown speed."""
        v1 = self.touchdown_m_s
        v0, to_ground = self._cruise()
        te = self.ease_s
        if tau < te:
            u = tau / te
            return (v0 * te * (u**3 - 0.5 * u**4), v0 * (3.0 * u**2 - 2.0 * u**3),
                    v0 * (6.0 * u - 6.0 * u**2) / te)
        s_e = 0.5 * v0 * te
        if v0 > v1:  # cruise, then the flare's constant deceleration to v1 at the ground
            decel = (v0 * v0 - v1 * v1) / (2.0 * self.flare_m)
            t_cruise = te + (to_ground - self.flare_m - s_e) / v0
            if tau < t_cruise:
                return s_e + v0 * (tau - te), v0, 0.0
            t_flare = (v0 - v1) / decel
            s_c = to_ground - self.flare_m
            if tau < t_cruise + t_flare:
                d = tau - t_cruise
                return s_c + v0 * d - 0.5 * decel * d * d, v0 - decel * d, -decel
            return to_ground + v1 * (tau - t_cruise - t_flare), v1, 0.0
        return s_e + v1 * (tau - te), v1, 0.0

    def reference(self, t_s: float, alpha_rad: float) -> Reference:
        x, y, z0 = self.start_pos_w_m
        target = self.ground_z_m - self.sink_m
        drop = max(0.0, z0 - target)
        dz, vz, az = self._profile(max(0.0, t_s - self.t0_s))
        if dz >= drop:
            dz, vz, az = drop, 0.0, 0.0
        return Reference(t_s, (x, y, z0 - dz), (0.0, 0.0, -vz), (0.0, 0.0, -az), self.q_yaw,
                         (0.0, 0.0, 0.0), alpha_rad, segment=-1, measured=False)

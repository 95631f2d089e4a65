"""Scenarios: what the flown vehicle and its world do that the controller does not know.

A scenario file (``config/scenarios/*.yaml``, schema ``fasthex.scenario``) is written once and
means the same in ``fasthex simulate --scenario FILE`` (in-process) and in an emulated ``fasthex
fly`` whose session names it (``backend.scenario``; the emulated vehicle process reads the same
file). It has three parts:

- ``plant``: overrides of the *simulated* vehicle (:class:`PlantOverrides`): mass or an added
  payload, inertia (diagonal or full), centre-of-mass offset, per-rotor c_f and c_tau scales,
  propeller and arm misalignment, rotor time constant. The simulator flies
  :func:`plant_params` of the vehicle plus these extras; the controller keeps the nominal
  vehicle.
- ``disturbances``: scheduled forces and torques (:class:`DisturbanceEvent`): ``step``,
  ``ramp``, ``pulse`` and ``gust`` (1 - cos), in the world or the body frame, acting at the
  centre of mass.
- ``faults``: scheduled faults in the backend's own ``KIND@T[:VALUE]`` text
  (:mod:`sim_backend.faults`), restricted to the kinds that mean the same in-process and through
  the byte path (:data:`SCENARIO_FAULT_KINDS`).

**Time.** Every scenario time is in mission seconds: 0 is the start of the mission (its
take-off), as in the mission file. ``simulate`` starts the schedule when the mission clock
starts (after the estimator's rest on the ground); in ``fly`` the ground station tells the
emulated vehicle when it enters the take-off and the backend anchors the schedule at that
simulated time (:meth:`sim_backend.backend.EmulatedVehicleBackend.start_scenario`). A take-off
that waits for its height in ``fly`` shifts the mission clock, not the scenario's.

Validation: ranges per field on load (``FILE:LINE: KEY.PATH: expectation``), then against the
vehicle (:func:`check_scenario_against_vehicle`: the plant must still be a vehicle that lifts
itself; the centre of mass inside the rotor ring) and the mission
(:func:`check_scenario_against_mission`: every event inside the mission).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Literal

import numpy as np

from config.schema import ConfigError, ConfigValueError, line_of, spec
from sim_backend.disturbances import MIN_TIME_CONSTANT_S
from sim_backend.faults import (
    TILT_KICK_S,
    TILT_KICK_STEPS,
    ImuWireLoss,
    ScheduledFault,
)

if TYPE_CHECKING:
    from controller.params import VehicleParams
    from sim_backend.simulator import FastHexSimulator

SCENARIO_SCHEMA = "fasthex.scenario"

Vec3 = tuple[float, float, float]
Vec6 = tuple[float, float, float, float, float, float]
ONES6: Vec6 = (1.0, 1.0, 1.0, 1.0, 1.0, 1.0)
ZEROS6: Vec6 = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)

#: faults that mean the same in ``simulate`` and in emulated ``fly``. A link or a battery only
#: exists on the byte path: ``fc-disconnect`` and ``battery-sag`` stay session faults.
SCENARIO_FAULT_KINDS = ("mocap-dropout", "mocap-latency", "mocap-jump", "mocap-freeze",
                        "imu-gap", "imu-rate", "rotor-thrust", "servo-silent", "tilt-kick")
#: an event may end this long after the mission (a flight record runs 0.5 s past it)
MISSION_END_SLACK_S = 0.5


@dataclass(frozen=True, kw_only=True)
class PlantOverrides:
    """The simulated vehicle's departures from the vehicle file (the controller's model)."""

    # the same sane range as a vehicle file's mass
    mass_kg: float | None = spec(None, ge=0.1, le=100.0, doc="total mass of the plant; "
                                 "omitted: the vehicle's")
    # a payload heavier than the vehicle itself is another vehicle
    payload_kg: float = spec(0.0, ge=0.0, le=50.0, doc="added mass at the centre of mass "
                             "(the inertia stays unless given)")
    inertia_kg_m2: tuple[float, ...] | None = spec(
        None, ge=-100.0, le=100.0, doc="about the centre of mass, body axes: 3 values (the "
        "diagonal) or 9 (the full matrix, row by row); omitted: the vehicle's diagonal")
    # checked against the arm length with the vehicle (check_scenario_against_vehicle)
    com_offset_b_m: Vec3 = spec((0.0, 0.0, 0.0), ge=-1.0, le=1.0,
                                doc="centre of mass relative to O_B, body frame")
    # +-50 % is a wrong propeller, not a tolerance; a lost rotor is a fault (rotor-thrust)
    thrust_coeff_scale: Vec6 = spec(ONES6, ge=0.5, le=1.5, doc="c_f of rotor i times this")
    drag_coeff_scale: Vec6 = spec(ONES6, ge=0.5, le=1.5, doc="c_tau of rotor i times this")
    # small angles: beyond 5 deg a propeller mount is broken, not misaligned
    propeller_misalignment_deg: Vec6 = spec(
        ZEROS6, ge=-5.0, le=5.0, doc="propeller axis about its arm's y axis (Ry(beta_i)), "
        "added to the preset's random misalignment")
    arm_yaw_error_deg: Vec6 = spec(ZEROS6, ge=-5.0, le=5.0,
                                   doc="arm i at (i-1) 60 deg + this, in the body xy plane")
    # 0: instant rotors; otherwise a time constant >= 1 ms (as in a preset)
    rotor_time_constant_s: float | None = spec(None, ge=0.0, le=1.0, doc="first-order rotor "
                                               "lag; omitted: the preset's")

    def __post_init__(self) -> None:
        tau = self.rotor_time_constant_s
        if tau is not None and tau != 0.0 and tau < MIN_TIME_CONSTANT_S:
            raise ConfigValueError("rotor_time_constant_s", f"expected 0 (no lag) or >= "
                                   f"{MIN_TIME_CONSTANT_S:g} s, got {tau:g}")
        if self.inertia_kg_m2 is not None:
            check_inertia(self.inertia_kg_m2)

    def inertia_matrix(self, nominal_diag_kg_m2: Vec3) -> np.ndarray:
        """The plant's 3x3 inertia (kg m^2, body axes, about the centre of mass)."""
        j = self.inertia_kg_m2
        if j is None:
            return np.diag(nominal_diag_kg_m2)
        return np.diag(j) if len(j) == 3 else np.asarray(j, dtype=np.float64).reshape(3, 3)

    @property
    def is_nominal(self) -> bool:
        return self == PlantOverrides()


def check_inertia(values: tuple[float, ...]) -> None:
    """3 positive principal moments, or a symmetric positive definite 3x3 matrix; either way
    moments that obey the triangle inequality (a real body)."""
    key = "inertia_kg_m2"
    if len(values) not in (3, 9):
        raise ConfigValueError(key, f"expected 3 values (diagonal) or 9 (full matrix, row by "
                               f"row), got {len(values)}")
    if len(values) == 3:
        if min(values) <= 0.0:
            raise ConfigValueError(key, "expected positive moments of inertia")
        moments = sorted(values)
    else:
        j = np.asarray(values, dtype=np.float64).reshape(3, 3)
        scale = float(np.max(np.abs(j)))
        if float(np.max(np.abs(j - j.T))) > 1e-9 * max(scale, 1e-12):
            raise ConfigValueError(key, "expected a symmetric matrix (J[i][j] = J[j][i])")
        moments = sorted(float(v) for v in np.linalg.eigvalsh(j))
        if moments[0] <= 0.0:
            raise ConfigValueError(key, "expected a positive definite matrix, smallest "
                                   f"eigenvalue {moments[0]:.3g} kg m^2")
    if moments[0] + moments[1] < moments[2] * (1.0 - 1e-9):
        raise ConfigValueError(key, "principal moments violate the triangle inequality (not a "
                               "physical body)")


@dataclass(frozen=True, kw_only=True)
class DisturbanceEvent:
    """A scheduled force and torque at the centre of mass.

    Profiles (``start_s`` and ``duration_s`` in mission seconds), each scaling ``force_n`` and
    ``torque_n_m``:

    - ``step``: full from ``start_s`` on, for ``duration_s`` (0: to the end of the flight);
    - ``ramp``: rises linearly from 0 to full over ``duration_s``, then holds;
    - ``pulse``: full for ``duration_s`` (> 0), then off;
    - ``gust``: ``(1 - cos(2 pi s / duration_s)) / 2`` over ``duration_s`` (> 0): a smooth
      rise and fall that peaks at full halfway.
    """

    kind: Literal["step", "ramp", "pulse", "gust"]
    frame: Literal["world", "body"] = spec("world", doc="frame of force_n and torque_n_m")
    # 50 N is over one and a half times the prototype's weight: more is a crash, not a test
    force_n: Vec3 = spec((0.0, 0.0, 0.0), ge=-50.0, le=50.0)
    # 10 N m is four times the largest rotor moment of the prototype (10 N at 0.3 m)
    torque_n_m: Vec3 = spec((0.0, 0.0, 0.0), ge=-10.0, le=10.0)
    start_s: float = spec(ge=0.0, le=3600.0, doc="mission time (s)")
    duration_s: float = spec(0.0, ge=0.0, le=3600.0)

    def __post_init__(self) -> None:
        if self.kind in ("ramp", "pulse", "gust") and self.duration_s <= 0.0:
            raise ConfigValueError("duration_s", f"a {self.kind} needs a positive duration_s")
        if self.force_n == (0.0, 0.0, 0.0) and self.torque_n_m == (0.0, 0.0, 0.0):
            raise ConfigValueError("force_n", "expected a force_n or a torque_n_m (both zero)")

    @property
    def end_s(self) -> float:
        """When the event stops changing (``inf``: a step that holds to the end)."""
        if self.kind == "step" and self.duration_s == 0.0:
            return math.inf
        return self.start_s + self.duration_s

    def factor(self, t_s: float) -> float:
        """The profile (0..1) at mission time ``t_s``."""
        s = t_s - self.start_s
        if s < 0.0:
            return 0.0
        d = self.duration_s
        if self.kind == "ramp":
            return min(s / d, 1.0)
        if self.kind == "gust":
            return 0.5 * (1.0 - math.cos(2.0 * math.pi * s / d)) if s < d else 0.0
        if self.kind == "step" and d == 0.0:
            return 1.0
        return 1.0 if s < d else 0.0


@dataclass(frozen=True, kw_only=True)
class Scenario:
    """One scenario file: the plant, the scheduled disturbances and faults (module docstring)."""

    name: str
    description: str = spec("")
    plant: PlantOverrides = field(default_factory=PlantOverrides)
    disturbances: tuple[DisturbanceEvent, ...] = spec(())
    faults: tuple[str, ...] = spec((), doc="KIND@T[:VALUE], T in mission seconds; kinds: "
                                   + ", ".join(SCENARIO_FAULT_KINDS))

    def __post_init__(self) -> None:
        for i, text in enumerate(self.faults):
            try:
                fault = ScheduledFault.parse(text)
            except ValueError as exc:
                raise ConfigValueError(f"faults[{i}]", str(exc)) from None
            if fault.kind not in SCENARIO_FAULT_KINDS:
                raise ConfigValueError(
                    f"faults[{i}]", f"{fault.kind} only exists on the emulated byte path (a "
                    "session's backend.faults); a scenario takes "
                    + ", ".join(SCENARIO_FAULT_KINDS))

    def scheduled_faults(self) -> tuple[ScheduledFault, ...]:
        return tuple(ScheduledFault.parse(f) for f in self.faults)

    def plant_params(self, vehicle: VehicleParams) -> VehicleParams:
        return plant_params(vehicle, self.plant)


#: the do-nothing scenario (the vehicle as the controller knows it, nothing scheduled)
NOMINAL = Scenario(name="nominal")


def plant_params(vehicle: VehicleParams, plant: PlantOverrides) -> VehicleParams:
    """The vehicle the simulator flies: mass (+ payload) and the inertia's diagonal replaced.
    What :class:`~controller.params.VehicleParams` cannot hold (a full inertia, the centre of
    mass, per-rotor scales, misalignment) the simulator takes from ``plant`` itself.

    The result passes the vehicle file's own checks (thrust margin, loop bandwidths with the
    controller's gains), or :class:`ConfigValueError` says which failed."""
    if plant.is_nominal:
        return vehicle
    mass_kg = (vehicle.mass_kg if plant.mass_kg is None else plant.mass_kg) + plant.payload_kg
    j = plant.inertia_matrix(vehicle.inertia_diag_kg_m2)
    diag = (float(j[0, 0]), float(j[1, 1]), float(j[2, 2]))
    try:
        return replace(vehicle, mass_kg=mass_kg, inertia_diag_kg_m2=diag,
                       description=f"{vehicle.description} (scenario plant)")
    except ConfigValueError as exc:
        key = "payload_kg" if exc.key == "mass_kg" and plant.payload_kg else (
            "mass_kg" if exc.key == "mass_kg" else "inertia_kg_m2"
            if exc.key.startswith("inertia") else exc.key)
        raise ConfigValueError(key, f"the plant ({mass_kg:g} kg) fails the vehicle's check of "
                               f"{exc.key}: {exc.message}") from None


def check_scenario_against_vehicle(scenario: Scenario, vehicle: VehicleParams, file: str,
                                   lines: dict[str, int]) -> None:
    """The plant must still be a vehicle (:func:`plant_params`) with its centre of mass well
    inside the rotor ring (half the arm length: beyond it one rotor carries the vehicle)."""
    try:
        plant_params(vehicle, scenario.plant)
    except ConfigValueError as exc:
        key = f"plant.{exc.key}"
        raise ConfigError(file, line_of(lines, key), key, exc.message) from None
    c = scenario.plant.com_offset_b_m
    limit = 0.5 * vehicle.geometry.arm_length_m
    if math.sqrt(c[0] ** 2 + c[1] ** 2 + c[2] ** 2) > limit:
        key = "plant.com_offset_b_m"
        raise ConfigError(file, line_of(lines, key), key,
                          f"expected |offset| <= {limit:g} m (half the arm length of vehicle "
                          f"{vehicle.name!r})")


def check_scenario_against_mission(scenario: Scenario, mission_duration_s: float, file: str,
                                   lines: dict[str, int]) -> None:
    """Every event starts inside the mission and ends by its end (+ :data:`MISSION_END_SLACK_S`)."""
    end = mission_duration_s + MISSION_END_SLACK_S
    items: list[tuple[str, float, float]] = [
        (f"disturbances[{i}].start_s", ev.start_s,
         ev.start_s + (ev.duration_s if ev.kind != "ramp" else 0.0))
        for i, ev in enumerate(scenario.disturbances)]
    items += [(f"faults[{i}]", f.t_s, f.end_s)
              for i, f in enumerate(scenario.scheduled_faults())]
    for key, start, stop in items:
        if start >= mission_duration_s or stop > end:
            raise ConfigError(file, line_of(lines, key), key,
                              f"{start:g}..{stop:g} s is not within the mission "
                              f"(0..{mission_duration_s:g} s)")


class DisturbanceSchedule:
    """The scenario's forces and torques at a simulated time (plain floats: per physics step).

    ``t0_s`` is the simulated time of mission time 0 (``None``: not started, nothing acts)."""

    def __init__(self, events: Sequence[DisturbanceEvent]) -> None:
        self.events = tuple(events)
        self.t0_s: float | None = None

    def wrench(self, t_s: float) -> tuple[Vec3, Vec3, Vec3, Vec3] | None:
        """(force world, force body, torque world, torque body) at simulated time ``t_s``, or
        ``None`` when nothing acts."""
        if self.t0_s is None or not self.events:
            return None
        tm = t_s - self.t0_s
        fw = [0.0, 0.0, 0.0]
        fb = [0.0, 0.0, 0.0]
        tw = [0.0, 0.0, 0.0]
        tb = [0.0, 0.0, 0.0]
        active = False
        for ev in self.events:
            k = ev.factor(tm)
            if k == 0.0:
                continue
            active = True
            f, t = (fw, tw) if ev.frame == "world" else (fb, tb)
            for a in range(3):
                f[a] += k * ev.force_n[a]
                t[a] += k * ev.torque_n_m[a]
        if not active:
            return None
        return ((fw[0], fw[1], fw[2]), (fb[0], fb[1], fb[2]), (tw[0], tw[1], tw[2]),
                (tb[0], tb[1], tb[2]))


class InProcessFaults:
    """The scenario's faults acting on the in-process simulator and its sensors (``simulate``).

    The same kinds as the emulated backend, on the in-process sensors: a MoCap dropout, jump,
    freeze or latency step changes :class:`~sim_backend.sensors.MocapModel`; an IMU gap or a
    degraded IMU rate loses samples before the state source sees them (the loop holds its last
    command, as the ground station does); ``rotor-thrust`` and ``tilt-kick`` act on the physics;
    ``servo-silent`` freezes the tilt where it is.
    """

    def __init__(self, sim: FastHexSimulator, faults: Sequence[ScheduledFault],
                 t0_s: float) -> None:
        shifted = [replace(f, t_s=f.t_s + t0_s) for f in faults]
        actions: list[tuple[float, Callable[[], None]]] = []
        for f in shifted:
            if f.kind == "tilt-kick":  # spread as on the byte path: a plausible rate change
                step = math.radians(f.value) / TILT_KICK_STEPS
                actions += [(f.t_s + i * TILT_KICK_S / TILT_KICK_STEPS,
                             _kick(sim, step)) for i in range(TILT_KICK_STEPS)]
            elif f.kind not in ("imu-gap", "imu-rate"):
                actions.append((f.t_s, _action(sim, f)))
        self._actions = sorted(actions, key=lambda a: a[0])
        wire = [f for f in shifted if f.kind in ("imu-gap", "imu-rate")]
        self._imu_loss = ImuWireLoss(wire) if wire else None
        self._imu_index = 0

    def run_due(self, t_s: float) -> None:
        """Apply every fault due by simulated time ``t_s``."""
        while self._actions and self._actions[0][0] <= t_s + 1e-9:
            self._actions.pop(0)[1]()

    def imu_lost(self, t_s: float) -> bool:
        """Is the IMU sample of simulated time ``t_s`` lost? (call once per sample)"""
        index = self._imu_index
        self._imu_index += 1
        return self._imu_loss is not None and self._imu_loss(index, t_s)


def _kick(sim: FastHexSimulator, step_rad_s: float) -> Callable[[], None]:
    return lambda: sim.kick_body_rate((step_rad_s, 0.0, 0.0))


def _action(sim: FastHexSimulator, f: ScheduledFault) -> Callable[[], None]:
    mocap = sim.mocap
    if f.kind == "mocap-dropout":
        def occlude() -> None:
            mocap.occluded_until_s = max(mocap.occluded_until_s, f.t_s + f.value)
        return occlude
    if f.kind == "mocap-latency":
        def latency() -> None:
            mocap.latency_s = f.value
        return latency
    if f.kind == "mocap-jump":
        def jump() -> None:
            o = mocap.offset_w_m
            mocap.offset_w_m = (o[0] + f.value, o[1], o[2])
        return jump
    if f.kind == "mocap-freeze":
        def freeze() -> None:
            pose = sim.true_pose()
            mocap.frozen = (pose.pos_w_m, pose.q_wb)
        return freeze
    if f.kind == "rotor-thrust":
        return lambda: sim.scale_rotor_thrust(f.value, f.rotor)
    if f.kind == "servo-silent":
        return sim.freeze_tilt
    raise ValueError(f"fault kind {f.kind!r} has no in-process meaning")

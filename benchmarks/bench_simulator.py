"""Speed of the simulator: simulated seconds per wall-clock second, and where a tick goes.

Prints (1) the plant alone: median and p99 (microseconds) of one 2 ms control period of physics
(two RK4 steps with the per-propeller wrench, sensors) under the ``paper-calibrated`` preset, and
the same for a baseline measured in the same run: the identical rigid-body RK4 written with
numpy arrays; (2) the whole in-process closed loop (:func:`sim_backend.closed_loop.fly_mission`:
mission, tilt planner, controller, state source, physics, flight-record rows) on 30 s of Exp. 1
with the true state plus noise and with the UKF, as the median microseconds per tick of each
component and the real-time factor. Targets (the simulate issue): truth >= 60x, ukf >= 30x.

The breakdown times the unchanged :func:`fly_mission` through timed subclasses of its parts
(simulator, state source, flight computer, record writer): ``physics`` is ``advance`` (RK4,
rotors, servo, tether and OU forces, MoCap capture), ``sensors`` the IMU sample and the MoCap
poll, ``source`` the state source (truth + noise or UKF), ``controller`` the flight computer's
step, ``record`` the writer's append (amortised flushes included), ``glue`` the rest of the
tick (the loop's own arithmetic, the row tuple, the crash check; plus the timers themselves,
about 0.1 us per timed call). The real-time factor is that of an untimed flight.

Run: ``python benchmarks/bench_simulator.py``.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import numpy.typing as npt

import sim_backend.closed_loop as closed_loop
from controller.missions import Mission
from controller.model import VehicleModel
from controller.params import VehicleParams
from controller.pipeline import ControlTick, FlightComputer
from controller.reference import Reference, Vec3, VehicleState
from groundstation.configs import load_disturbances, load_mission, load_vehicle
from groundstation.record import RecordWriter
from sim_backend.closed_loop import StateSource, TruthPlusNoise, UkfStateSource, fly_mission
from sim_backend.disturbances import DisturbancePreset
from sim_backend.simulator import FastHexSimulator
from sim_backend.vehicle import ImuReading, PoseReading

FloatArray = npt.NDArray[np.float64]
PERIOD_S = 0.002
MISSION = "exp1-hover-tilt-steps"
FLIGHT_S = 30.0
COMPONENTS = ("physics", "sensors", "source", "controller", "record")

_ns = time.perf_counter_ns


class NumpyRk4Baseline:
    """13-state rigid body + per-propeller wrench with numpy arrays, RK4 at 1 kHz."""

    def __init__(self, model: VehicleModel, spins: FloatArray) -> None:
        p = model.params
        self.m, self.g = p.mass_kg, p.gravity_m_s2
        self.j = np.array(p.inertia_diag_kg_m2)
        self.axes = model.thrust_axes(math.radians(30.0))
        self.arms = model.rotor_positions_b_m
        self.drag = model.drag_signs * model.c_tau_m
        self.c_f = model.c_f
        self.spins = spins
        self.x = np.zeros(13)
        self.x[2], self.x[6] = 1.0, 1.0

    def deriv(self, x: FloatArray, fb: FloatArray, tb: FloatArray) -> FloatArray:
        qw, qx, qy, qz = x[6:10]
        r = np.array([
            [1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qw * qz), 2 * (qx * qz + qw * qy)],
            [2 * (qx * qy + qw * qz), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qw * qx)],
            [2 * (qx * qz - qw * qy), 2 * (qy * qz + qw * qx), 1 - 2 * (qx * qx + qy * qy)]])
        w = x[10:13]
        acc = r @ fb / self.m - np.array([0.0, 0.0, self.g])
        wdot = (tb - np.cross(w, self.j * w)) / self.j
        qdot = 0.5 * np.array([-qx * w[0] - qy * w[1] - qz * w[2],
                               qw * w[0] + qy * w[2] - qz * w[1],
                               qw * w[1] - qx * w[2] + qz * w[0],
                               qw * w[2] + qx * w[1] - qy * w[0]])
        return np.concatenate([x[3:6], acc, qdot, wdot])

    def advance(self, dt: float) -> None:
        for _ in range(2):
            h = dt / 2
            f = self.c_f * self.spins**2
            forces = self.axes * f[:, None]
            fb = forces.sum(axis=0)
            tb = (np.cross(self.arms, forces) + (self.drag * f)[:, None] * self.axes).sum(axis=0)
            x = self.x
            k1 = self.deriv(x, fb, tb)
            k2 = self.deriv(x + 0.5 * h * k1, fb, tb)
            k3 = self.deriv(x + 0.5 * h * k2, fb, tb)
            k4 = self.deriv(x + h * k3, fb, tb)
            x = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
            x[6:10] /= np.linalg.norm(x[6:10])
            self.x = x


def _time_us(fn: Callable[[], object], repeats: int) -> FloatArray:
    out = np.empty(repeats)
    for i in range(repeats):
        t0 = _ns()
        fn()
        out[i] = (_ns() - t0) / 1e3
    return out


class _Ticks:
    """Per-tick nanoseconds of each component; a tick starts at the IMU read."""

    def __init__(self) -> None:
        self.current = dict.fromkeys(COMPONENTS, 0)
        self.rows: list[dict[str, int]] = []
        self.tick_start: int | None = None
        self.totals: list[int] = []

    def new_tick(self, now: int) -> None:
        if self.tick_start is not None:
            self.totals.append(now - self.tick_start)
            self.rows.append(self.current)
            self.current = dict.fromkeys(COMPONENTS, 0)
        self.tick_start = now

    def add(self, key: str, ns: int) -> None:
        self.current[key] += ns


def _timed_classes(ticks: _Ticks) -> tuple[type[FastHexSimulator], type[FlightComputer],
                                           type[TruthPlusNoise]]:
    class TimedSimulator(FastHexSimulator):
        def advance(self, dt_s: float) -> None:
            t0 = _ns()
            super().advance(dt_s)
            ticks.add("physics", _ns() - t0)

        def read_imu(self) -> ImuReading:
            t0 = _ns()
            ticks.new_tick(t0)
            out = super().read_imu()
            ticks.add("sensors", _ns() - t0)
            return out

        def poll_mocap(self) -> list[PoseReading]:
            t0 = _ns()
            out = super().poll_mocap()
            ticks.add("sensors", _ns() - t0)
            return out

    class TimedComputer(FlightComputer):
        def step(self, t_s: float, state: VehicleState, alpha_rad: float,
                 ref: Reference | None = None, hold_tilt: bool = False,
                 force_ext_w_n: Vec3 | None = None,
                 ref_offset_w_m: Vec3 | None = None) -> ControlTick:
            t0 = _ns()
            out = super().step(t_s, state, alpha_rad, ref, hold_tilt, force_ext_w_n,
                               ref_offset_w_m)
            ticks.add("controller", _ns() - t0)
            return out

    class TimedTruth(TruthPlusNoise):
        def update(self, t_s: float, imu: ImuReading, mocap: list[PoseReading]
                   ) -> VehicleState:
            t0 = _ns()
            out = super().update(t_s, imu, mocap)
            ticks.add("source", _ns() - t0)
            return out

    return TimedSimulator, TimedComputer, TimedTruth


class _TimedUkf(UkfStateSource):
    ticks: _Ticks | None = None

    def update(self, t_s: float, imu: ImuReading, mocap: list[PoseReading]) -> VehicleState:
        t0 = _ns()
        out = super().update(t_s, imu, mocap)
        if self.ticks is not None:
            self.ticks.add("source", _ns() - t0)
        return out


class _TimedWriter(RecordWriter):
    def __init__(self, ticks: _Ticks) -> None:
        super().__init__(None)
        self._ticks = ticks

    def append_flat(self, values: tuple[Any, ...]) -> None:
        t0 = _ns()
        super().append_flat(values)
        self._ticks.add("record", _ns() - t0)


def _source(params: VehicleParams, estimator: str, ticks: _Ticks
            ) -> tuple[StateSource | None, float]:
    if estimator == "ukf":
        source = _TimedUkf(params.mass_kg, params.gravity_m_s2)
        source.ticks = ticks
        return source, 1.0
    return None, 0.0


def breakdown(params: VehicleParams, mission: Mission, preset: DisturbancePreset,
              estimator: str) -> dict[str, float]:
    """Median microseconds per tick of each component (and ``glue``, ``tick``) of one timed
    flight, the UKF's rest period excluded."""
    ticks = _Ticks()
    sim_cls, computer_cls, truth_cls = _timed_classes(ticks)
    names = ("FastHexSimulator", "FlightComputer", "TruthPlusNoise")
    saved = [getattr(closed_loop, n) for n in names]
    for name, cls in zip(names, (sim_cls, computer_cls, truth_cls), strict=True):
        setattr(closed_loop, name, cls)
    try:
        source, preroll = _source(params, estimator, ticks)
        writer = _TimedWriter(ticks)
        fly_mission(params, mission, preset, seed=0, sink=writer, duration_s=FLIGHT_S,
                    state_source=source, preroll_s=preroll)
        writer.close()
    finally:
        for name, cls in zip(names, saved, strict=True):
            setattr(closed_loop, name, cls)
    skip = round(preroll * closed_loop.CONTROL_RATE_HZ)  # the rest period: no controller
    rows, totals = ticks.rows[skip:], np.array(ticks.totals[skip:], dtype=float)
    out = {k: float(np.median([r[k] for r in rows])) / 1e3 for k in COMPONENTS}
    glue = totals - np.array([sum(r.values()) for r in rows], dtype=float)
    out["glue"] = float(np.median(glue)) / 1e3
    out["tick"] = float(np.median(totals)) / 1e3
    # the means carry what a median hides: the record's flush every 50 rows, the wrench
    # mapper's recomputation while the tilt moves
    out.update({f"{k}_mean": float(np.mean([r[k] for r in rows])) / 1e3 for k in COMPONENTS})
    out["glue_mean"] = float(np.mean(glue)) / 1e3
    out["tick_mean"] = float(np.mean(totals)) / 1e3
    return out


def realtime_factor(params: VehicleParams, mission: Mission, preset: DisturbancePreset,
                    estimator: str, repeats: int = 2) -> float:
    """The best simulated-per-wall-second of ``repeats`` untimed flights."""
    best = 0.0
    for _ in range(repeats):
        source: StateSource | None = None
        preroll = 0.0
        if estimator == "ukf":
            source, preroll = UkfStateSource(params.mass_kg, params.gravity_m_s2), 1.0
        writer = RecordWriter(None)
        res = fly_mission(params, mission, preset, seed=0, sink=writer, duration_s=FLIGHT_S,
                          state_source=source, preroll_s=preroll)
        writer.close()
        best = max(best, res.realtime_factor)
    return best


def _print_breakdown(names: Sequence[str], table: dict[str, dict[str, float]],
                     factors: dict[str, float]) -> None:
    keys = (*COMPONENTS, "glue", "tick")
    print(f"closed loop, {MISSION}, {FLIGHT_S:g} s, us per tick (median / mean)")
    print(f"{'':12}" + "".join(f"{k:>13}" for k in keys) + f"{'realtime':>11}")
    for name in names:
        row = table[name]
        cells = "".join(f"{row[k]:6.1f} /{row[k + '_mean']:5.1f}" for k in keys)
        print(f"{name:12}{cells}{factors[name]:10.1f}x")


def main() -> None:
    params = load_vehicle("fasthex")
    preset = load_disturbances("paper-calibrated")
    model = VehicleModel(params)
    spins = model.spin_from_thrust(model.hover_thrusts(math.radians(30.0))) * 1.01
    sim = FastHexSimulator(params, preset, seed=0)
    sim.command_tilt_rad(math.radians(30.0))
    sim.advance(3.5)
    sim.command_rotor_speeds_hz(list(spins))
    sim.advance(0.1)

    def ours() -> None:
        sim.read_imu()
        sim.poll_mocap()
        sim.advance(PERIOD_S)

    base = NumpyRk4Baseline(model, spins)
    t = _time_us(ours, 5000)
    tb = _time_us(lambda: base.advance(PERIOD_S), 1000)
    med, medb = float(np.median(t)), float(np.median(tb))
    print(f"{'plant, one 2 ms period':34} {'median_us':>10} {'p99_us':>10} {'sim_s/wall_s':>13}")
    print(f"{'  simulator (paper-calibrated)':34} {med:10.1f} {np.percentile(t, 99):10.1f} "
          f"{PERIOD_S * 1e6 / med:12.1f}x")
    print(f"{'  numpy RK4 baseline (no effects)':34} {medb:10.1f} {np.percentile(tb, 99):10.1f} "
          f"{PERIOD_S * 1e6 / medb:12.1f}x")
    print(f"simulator is {medb / med:.1f}x faster than the numpy baseline (same run)")

    mission = Mission(load_mission(MISSION))
    names = ("truth", "ukf")
    table = {n: breakdown(params, mission, preset, n) for n in names}
    factors = {n: realtime_factor(params, mission, preset, n) for n in names}
    _print_breakdown(names, table, factors)


if __name__ == "__main__":
    main()

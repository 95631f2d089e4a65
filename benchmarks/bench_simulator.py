"""Speed of the simulator: simulated seconds per wall-clock second.

Prints (1) the plant alone: median and p99 (microseconds) of one 2 ms control period of physics
(two RK4 steps with the per-propeller wrench, sensors) under the ``paper-calibrated`` preset, and
the same for a baseline measured in the same run: the identical rigid-body RK4 written with
numpy arrays; (2) the whole in-process closed loop (mission, tilt planner, controller, state
noise, physics, flight-record rows) on 20 s of Exp. 1 and Exp. 2b. Target: >= 20x real time.
Run: ``python benchmarks/bench_simulator.py``.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable

import numpy as np
import numpy.typing as npt

from controller.missions import Mission
from controller.model import VehicleModel
from groundstation.configs import load_disturbances, load_mission, load_vehicle
from groundstation.record import RecordWriter
from sim_backend.closed_loop import fly_mission
from sim_backend.simulator import FastHexSimulator

FloatArray = npt.NDArray[np.float64]
PERIOD_S = 0.002


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
        t0 = time.perf_counter_ns()
        fn()
        out[i] = (time.perf_counter_ns() - t0) / 1e3
    return out


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
    for name in ("exp1-hover-tilt-steps", "exp2b-roll-sine"):
        writer = RecordWriter(None)
        res = fly_mission(params, Mission(load_mission(name)), preset, seed=0, sink=writer,
                          duration_s=20.0)
        writer.close()
        print(f"closed loop {name:24} 20 s simulated in {res.wall_time_s:5.2f} s wall: "
              f"{res.realtime_factor:5.1f}x real time")


if __name__ == "__main__":
    main()

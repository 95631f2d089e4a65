"""Cost of one controller tick (position control, Algorithm 1, attitude control, wrench mapper).

Prints median and p99 (microseconds) of ``GeometricController.step`` in three situations:
hover in MDT (30 deg), a 10 cm position error in UDT (the bisection does real work) and the same
error while the tilt ramps (the 6x6 Tikhonov map is recomputed on every tick). The baseline,
measured in the same run, is a straightforward numpy transcription of the same step (3x3
Rodrigues matrices inside the bisection, Tikhonov solve every tick); both give the same spin
rates (checked). Target: median < 100 us. Run: ``python benchmarks/bench_controller.py``.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable

import numpy as np
import numpy.typing as npt

from controller.geometric import GeometricController
from controller.model import LateralBound, VehicleModel
from controller.params import VehicleParams
from controller.reference import IDENTITY_Q, ZERO3, Reference, VehicleState
from controller.wrench import tikhonov_gamma
from groundstation.configs import load_vehicle

FloatArray = npt.NDArray[np.float64]


def _skew(v: FloatArray) -> FloatArray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


class NumpyBaseline:
    """The same control law written the obvious way with numpy arrays."""

    def __init__(self, params: VehicleParams) -> None:
        c = params.controller
        self.model = VehicleModel(params)
        self.bound = LateralBound.for_model(self.model)
        self.kp, self.ki, self.kv = (np.diag(x) for x in (c.kp_pos, c.ki_pos, c.kv_pos))
        self.kr, self.kri, self.kw = (np.diag(x) for x in (c.kr_att, c.ki_att, c.kw_att))
        self.m, self.g = params.mass_kg, params.gravity_m_s2
        self.j = np.diag(params.inertia_diag_kg_m2)
        self.n_it = c.bisection_iterations
        self.k1, self.k2 = c.tikhonov_k1, c.tikhonov_k2_rad
        self.c_f = params.rotors.thrust_coeff_n_per_hz2
        self.w_lim = (params.rotors.min_spin_hz, params.rotors.max_spin_hz)
        self.e_pi = np.zeros(3)
        self.e_ri = np.zeros(3)

    def step(self, p: FloatArray, v: FloatArray, r: FloatArray, w: FloatArray,
             pr: FloatArray, rr: FloatArray, alpha: float, dt: float) -> FloatArray:
        e3 = np.array([0.0, 0.0, 1.0])
        ep = p - pr
        self.e_pi = np.clip(self.e_pi + ep * dt, -3.0, 3.0)
        f_r = self.m * self.g * e3 - self.kp @ ep - self.ki @ self.e_pi - self.kv @ v
        rxy = self.bound.radius_n(alpha)
        fb = r.T @ f_r
        lat = np.linalg.norm(fb[:2])
        if lat > rxy:
            fb[:2] *= rxy / lat
        b3r = rr[:, 2]
        c = np.cross(b3r, f_r)
        theta = 0.0
        if np.linalg.norm(c) > 1e-9 * np.linalg.norm(f_r):
            k = c / np.linalg.norm(c)
            theta_max = math.atan2(np.linalg.norm(c), b3r @ f_r)
            theta = theta_max / 2
            thr = math.sqrt(max(0.0, float(f_r @ f_r) - rxy * rxy))
            kk = _skew(k)
            for i in range(1, self.n_it + 1):
                rot = np.eye(3) + math.sin(theta) * kk + (1 - math.cos(theta)) * kk @ kk
                b3d = rot @ b3r
                theta += (-1 if f_r @ b3d >= thr else 1) * theta_max / 2 / 2**i
            kk_ = _skew(k)
            b3d = (np.eye(3) + math.sin(theta) * kk_ + (1 - math.cos(theta)) * kk_ @ kk_) @ b3r
        else:
            b3d = b3r
        b2d = np.cross(b3d, rr[:, 0])
        b2d /= np.linalg.norm(b2d)
        rd = np.column_stack([np.cross(b2d, b3d), b2d, b3d])
        em = rd.T @ r - r.T @ rd
        e_r = 0.5 * np.array([em[2, 1], em[0, 2], em[1, 0]])
        self.e_ri = np.clip(self.e_ri + e_r * dt, -1.0, 1.0)
        u_tau = np.cross(w, self.j @ w) - self.kr @ e_r - self.kri @ self.e_ri - self.kw @ w
        f = self.model.allocation(alpha)
        mp = np.linalg.solve(f.T @ f + tikhonov_gamma(alpha, self.k1, self.k2) * np.eye(6), f.T)
        u = mp @ np.concatenate([fb, u_tau])
        return np.clip(np.sqrt(np.maximum(u, 0.0) / self.c_f), *self.w_lim)


def _time_us(fn: Callable[[int], object], repeats: int) -> FloatArray:
    out = np.empty(repeats)
    for i in range(repeats):
        t0 = time.perf_counter_ns()
        fn(i)
        out[i] = (time.perf_counter_ns() - t0) / 1e3
    return out


def main() -> None:
    params = load_vehicle("fasthex")
    a30 = math.radians(30.0)
    ref = Reference(0.0, (0.0, 0.0, 1.0), ZERO3, ZERO3, IDENTITY_Q, ZERO3, a30)
    hover = VehicleState((0.0, 0.0, 1.0), ZERO3, IDENTITY_Q, ZERO3)
    off = VehicleState((0.1, 0.0, 1.0), ZERO3, IDENTITY_Q, ZERO3)
    cases: dict[str, tuple[VehicleState, Callable[[int], float]]] = {
        "MDT hover (30 deg)": (hover, lambda i: a30),
        "UDT, 10 cm error (bisection)": (off, lambda i: 0.0),
        "tilt ramp (map recomputed)": (off, lambda i: 0.1 + 1e-3 * i),
    }
    repeats = 20000
    print(f"{'case':32} {'median_us':>10} {'p99_us':>10} {'baseline_med':>13} "
          f"{'baseline_p99':>13} {'speed-up':>9}")
    for name, (state, alpha_of) in cases.items():
        sut = GeometricController(params)
        base = NumpyBaseline(params)
        p, v = np.array(state.pos_w_m), np.zeros(3)
        r, w, pr = np.eye(3), np.zeros(3), np.array(ref.pos_w_m)
        # same numbers from both (first tick, integrators still 0)
        first = sut.step(0.0, state, ref, alpha_of(0)).spin_hz
        theirs = base.step(p, v, r, w, pr, np.eye(3), alpha_of(0), 0.0)
        assert np.allclose(first, theirs, atol=1e-6), (first, theirs)
        def ours(i: int, s: GeometricController = sut, st: VehicleState = state,
                 a: Callable[[int], float] = alpha_of) -> object:
            return s.step(i * 0.002, st, ref, a(i))

        def baseline(i: int, b: NumpyBaseline = base, a: Callable[[int], float] = alpha_of,
                     x: tuple[FloatArray, ...] = (p, v, r, w, pr)) -> object:
            return b.step(x[0], x[1], x[2], x[3], x[4], np.eye(3), a(i), 0.002)

        t = _time_us(ours, repeats)
        tb = _time_us(baseline, repeats // 10)
        med, medb = float(np.median(t)), float(np.median(tb))
        print(f"{name:32} {med:10.1f} {np.percentile(t, 99):10.1f} {medb:13.1f} "
              f"{np.percentile(tb, 99):13.1f} {medb / med:8.1f}x")


if __name__ == "__main__":
    main()

"""Synthetic truth for exercising the estimator without the flying simulator.

Smooth trajectories with analytic first and second derivatives give exact IMU readings (body
rate from the ZYX Euler rates, specific force ``R^T (a + g e3)``); seeded sensor models then add
white noise, constant biases, MoCap noise, latency, dropouts and outliers. An optional
external force (a constant tether pull plus an Ornstein-Uhlenbeck gust) is folded into the
thrust the vehicle must have produced, so the accelerometer and the commanded body force are
consistent with ``m a = R F_thrust + F_ext + m g``. Pure numerics; used by the tests and the
benchmark, and by anyone who wants a known answer.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from .config import TWO_SIDED
from .quaternion import angle_between, quat_exp, quat_from_euler_zyx, quat_mul, quat_to_rot
from .ukf import PoseVerdict, Ukf

FloatArray = npt.NDArray[np.float64]
# value, first and second time derivative at the given times
Signal = Callable[[FloatArray], tuple[FloatArray, FloatArray, FloatArray]]


def const(value: float) -> Signal:
    def signal(t: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        zero = np.zeros_like(t)
        return zero + value, zero, zero
    return signal


def sine(amplitude: float, omega_rad_s: float, phase_rad: float = 0.0,
         offset: float = 0.0) -> Signal:
    """offset + amplitude sin(omega t + phase)."""
    def signal(t: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        arg = omega_rad_s * t + phase_rad
        s, c = np.sin(arg), np.cos(arg)
        return (offset + amplitude * s, amplitude * omega_rad_s * c,
                -amplitude * omega_rad_s ** 2 * s)
    return signal


def ramp_in(inner: Signal, t0_s: float, duration_s: float, base: float = 0.0) -> Signal:
    """base + smoothstep(t) (inner(t) - base): still before t0, all of inner after t0+duration.

    The quintic smoothstep keeps velocity and acceleration continuous at both ends.
    """
    def signal(t: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        tau = np.clip((t - t0_s) / duration_s, 0.0, 1.0)
        inside = (t > t0_s) & (t < t0_s + duration_s)
        s = tau ** 3 * (10.0 - 15.0 * tau + 6.0 * tau ** 2)
        ds = np.where(inside, 30.0 * tau ** 2 * (1.0 - tau) ** 2 / duration_s, 0.0)
        dds = np.where(inside, 60.0 * tau * (1.0 - tau) * (1.0 - 2.0 * tau) / duration_s ** 2,
                       0.0)
        f, df, ddf = inner(t)
        f = f - base
        return base + s * f, ds * f + s * df, dds * f + 2.0 * ds * df + s * ddf
    return signal


@dataclass(frozen=True)
class Trajectory:
    """Position (world, m) and ZYX Euler attitude (rad) as smooth signals."""

    x: Signal = field(default_factory=lambda: const(0.0))
    y: Signal = field(default_factory=lambda: const(0.0))
    z: Signal = field(default_factory=lambda: const(1.0))
    roll: Signal = field(default_factory=lambda: const(0.0))
    pitch: Signal = field(default_factory=lambda: const(0.0))
    yaw: Signal = field(default_factory=lambda: const(0.0))


@dataclass(frozen=True)
class Truth:
    """The true state at times ``t_s`` (N,)."""

    t_s: FloatArray
    pos_w_m: FloatArray        # (N, 3)
    vel_w_m_s: FloatArray      # (N, 3)
    acc_w_m_s2: FloatArray     # (N, 3)
    q_wb: FloatArray           # (N, 4)
    omega_b_rad_s: FloatArray  # (N, 3)
    specific_force_b_m_s2: FloatArray  # (N, 3), what a perfect accelerometer reads


def hover(z_m: float = 1.0) -> Trajectory:
    return Trajectory(z=const(z_m))


def sine_x(amplitude_m: float = 0.6, omega_rad_s: float = 1.667, start_s: float = 0.0,
           ramp_s: float = 0.0, z_m: float = 1.0) -> Trajectory:
    """The paper's Exp. 2a lateral sine (0.6 sin(1.667 t) m), optionally ramped in."""
    x = sine(amplitude_m, omega_rad_s)
    return Trajectory(x=ramp_in(x, start_s, ramp_s) if ramp_s > 0 else x, z=const(z_m))


def roll_sine(amplitude_deg: float = 6.0, freq_hz: float = 0.1, start_s: float = 0.0,
              ramp_s: float = 0.0, z_m: float = 1.0) -> Trajectory:
    """A 6 deg, 0.1 Hz roll oscillation while hovering."""
    r = sine(math.radians(amplitude_deg), 2.0 * math.pi * freq_hz)
    return Trajectory(roll=ramp_in(r, start_s, ramp_s) if ramp_s > 0 else r, z=const(z_m))


def lively(start_s: float = 0.0, ramp_s: float = 0.0) -> Trajectory:
    """3-D motion exciting every axis (Exp. 2a sine in x plus y, z, roll, pitch, yaw)."""
    def maybe(sig: Signal, base: float = 0.0) -> Signal:
        return ramp_in(sig, start_s, ramp_s, base) if ramp_s > 0 else sig
    return Trajectory(
        x=maybe(sine(0.6, 1.667)), y=maybe(sine(0.3, 1.1, 0.5)),
        z=maybe(sine(0.15, 0.9, 1.0, 1.0), 1.0),
        roll=maybe(sine(math.radians(6.0), 2 * math.pi * 0.1)),
        pitch=maybe(sine(math.radians(5.0), 2 * math.pi * 0.13, 0.3)),
        yaw=maybe(sine(math.radians(20.0), 2 * math.pi * 0.05, 0.2)))


def sample_truth(traj: Trajectory, t_s: FloatArray, gravity_m_s2: float = 9.81) -> Truth:
    t = np.asarray(t_s, dtype=np.float64)
    px, py, pz = traj.x(t), traj.y(t), traj.z(t)
    pos = np.stack([px[0], py[0], pz[0]], axis=-1)
    vel = np.stack([px[1], py[1], pz[1]], axis=-1)
    acc = np.stack([px[2], py[2], pz[2]], axis=-1)
    (r, dr, _), (p, dp, _), (y, dy, _) = traj.roll(t), traj.pitch(t), traj.yaw(t)
    q = quat_from_euler_zyx(r, p, y)
    omega = np.stack([dr - dy * np.sin(p),
                      dp * np.cos(r) + dy * np.sin(r) * np.cos(p),
                      -dp * np.sin(r) + dy * np.cos(r) * np.cos(p)], axis=-1)
    rot = quat_to_rot(q)
    f_w = acc + np.array([0.0, 0.0, gravity_m_s2])
    f_b = np.einsum("nji,nj->ni", rot, f_w)
    return Truth(t, pos, vel, acc, q, omega, f_b)


@dataclass(frozen=True)
class ImuModel:
    rate_hz: float = 500.0
    gyro_noise_rad_s_sqrt_hz: float = 2e-3
    accel_noise_m_s2_sqrt_hz: float = 2e-2
    gyro_bias_rad_s: tuple[float, float, float] = (0.0, 0.0, 0.0)
    accel_bias_m_s2: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class MocapModel:
    rate_hz: float = 100.0
    pos_sigma_m: float = 1e-3
    att_sigma_deg: float = 0.2
    latency_min_s: float = 0.0
    latency_max_s: float = 0.0
    dropouts_s: tuple[tuple[float, float], ...] = ()           # (start, end) without frames
    outliers: tuple[tuple[float, tuple[float, float, float]], ...] = ()  # (t, position jump)
    capture_phase_s: float | None = None   # first capture after t0; None: half a period


# The paper's sensor class (ADXRS620 gyro, MXR9500M-class accelerometer, sub-mm MoCap) with
# biases of a few sigma of a typical turn-on spread, and a 5-15 ms MoCap latency.
PAPER_IMU = ImuModel(gyro_noise_rad_s_sqrt_hz=8.7e-4, accel_noise_m_s2_sqrt_hz=2e-3,
                     gyro_bias_rad_s=(0.005, -0.008, 0.006), accel_bias_m_s2=(0.05, -0.04, 0.06))
PAPER_MOCAP = MocapModel(pos_sigma_m=5e-4, att_sigma_deg=0.115, latency_min_s=0.005,
                         latency_max_s=0.015)


@dataclass(frozen=True)
class ExternalForce:
    """A constant world-frame pull plus an Ornstein-Uhlenbeck gust per axis."""

    constant_w_n: tuple[float, float, float] = (0.0, 0.0, 0.0)
    ou_sigma_n: float = 0.0
    ou_tau_s: float = 1.0


@dataclass(frozen=True)
class MocapFrame:
    capture_t_s: float
    arrival_t_s: float
    pos_w_m: FloatArray
    q_wb: FloatArray


@dataclass(frozen=True)
class Scenario:
    """Everything a run needs: IMU samples, MoCap frames (by arrival), truth and force."""

    truth: Truth                     # at the IMU sample times
    gyro_rad_s: FloatArray
    accel_m_s2: FloatArray
    frames: list[MocapFrame]
    force_ext_w_n: FloatArray        # (N, 3) true external force
    force_cmd_b_n: FloatArray        # (N, 3) body force the rotors produced (= commanded)


def make_scenario(traj: Trajectory, duration_s: float, imu: ImuModel, mocap: MocapModel,
                  seed: int, force: ExternalForce | None = None, mass_kg: float = 3.1,
                  gravity_m_s2: float = 9.81, t0_s: float = 0.0) -> Scenario:
    rng = np.random.default_rng(seed)
    n = round(duration_s * imu.rate_hz)
    t = t0_s + np.arange(1, n + 1) / imu.rate_hz
    truth = sample_truth(traj, t, gravity_m_s2)
    root_rate = math.sqrt(TWO_SIDED * imu.rate_hz)   # one-sided densities (estimator.config)
    gyro = (truth.omega_b_rad_s + np.asarray(imu.gyro_bias_rad_s)
            + rng.normal(0.0, imu.gyro_noise_rad_s_sqrt_hz * root_rate, (n, 3)))
    accel_noise = rng.normal(0.0, imu.accel_noise_m_s2_sqrt_hz * root_rate, (n, 3))
    accel = truth.specific_force_b_m_s2 + np.asarray(imu.accel_bias_m_s2) + accel_noise
    f_ext = np.zeros((n, 3))
    if force is not None:
        f_ext += np.asarray(force.constant_w_n)
        if force.ou_sigma_n > 0:
            dt = 1.0 / imu.rate_hz
            phi = math.exp(-dt / force.ou_tau_s)
            kick = force.ou_sigma_n * math.sqrt(1.0 - phi * phi)
            gust = rng.normal(0.0, force.ou_sigma_n, 3)
            for k in range(n):
                gust = phi * gust + kick * rng.normal(0.0, 1.0, 3)
                f_ext[k] += gust
    # thrust the rotors produced: m a = R F + F_ext + m g  =>  F = R^T (m (a + g e3) - F_ext)
    rot = quat_to_rot(truth.q_wb)
    f_cmd = np.einsum("nji,nj->ni", rot, mass_kg * (truth.acc_w_m_s2
                                                     + np.array([0.0, 0.0, gravity_m_s2]))
                      - f_ext)
    frames = _mocap_frames(traj, t0_s, duration_s, mocap, rng, gravity_m_s2)
    return Scenario(truth, gyro, accel, frames, f_ext, f_cmd)


def _mocap_frames(traj: Trajectory, t0_s: float, duration_s: float, mocap: MocapModel,
                  rng: np.random.Generator, gravity_m_s2: float) -> list[MocapFrame]:
    n = math.floor(duration_s * mocap.rate_hz)
    phase = 0.5 / mocap.rate_hz if mocap.capture_phase_s is None else mocap.capture_phase_s
    t_cap = t0_s + phase + np.arange(n, dtype=np.float64) / mocap.rate_hz
    truth = sample_truth(traj, t_cap, gravity_m_s2)
    pos = truth.pos_w_m + rng.normal(0.0, mocap.pos_sigma_m, (n, 3))
    noise = quat_exp(rng.normal(0.0, math.radians(mocap.att_sigma_deg), (n, 3)))
    q = quat_mul(truth.q_wb, noise)
    latency = rng.uniform(mocap.latency_min_s, mocap.latency_max_s, n)
    frames = []
    for k in range(n):
        tc = float(t_cap[k])
        if any(a <= tc < b for a, b in mocap.dropouts_s):
            continue
        p = pos[k].copy()
        for t_out, jump in mocap.outliers:
            if abs(tc - t_out) < 0.5 / mocap.rate_hz:
                p += np.asarray(jump)
        frames.append(MocapFrame(tc, tc + float(latency[k]), p, q[k]))
    # a stream delivers in order: a frame never overtakes the previous one
    arrival = np.maximum.accumulate(np.array([f.arrival_t_s for f in frames], dtype=np.float64))
    return [MocapFrame(f.capture_t_s, float(a), f.pos_w_m, f.q_wb)
            for f, a in zip(frames, arrival, strict=True)]


@dataclass(frozen=True)
class RunLog:
    """Estimates at every IMU tick, next to the truth."""

    t_s: FloatArray
    pos_w_m: FloatArray
    vel_w_m_s: FloatArray
    q_wb: FloatArray
    gyro_bias_rad_s: FloatArray
    accel_bias_m_s2: FloatArray
    pos_sigma_m: FloatArray          # (N,) largest position sigma
    force_ext_w_n: FloatArray
    initialized: npt.NDArray[np.bool_]
    verdicts: list[tuple[float, PoseVerdict]]


def rmse(estimate: FloatArray, truth: FloatArray) -> float:
    """Root mean square of the Euclidean error norm over rows."""
    return float(np.sqrt(np.mean(np.sum((estimate - truth) ** 2, axis=-1))))


def attitude_errors_rad(q_est: FloatArray, q_true: FloatArray) -> FloatArray:
    return angle_between(q_est, q_true)


def run(est: Ukf, sc: Scenario, feed_force: bool = False,
        on_tick: Callable[[int], None] | None = None) -> RunLog:
    """Drive ``est`` tick by tick: predict with the IMU sample, then fuse the poses that have
    arrived by then (the 500 Hz loop's order)."""
    n = len(sc.truth.t_s)
    out = {k: np.full((n, 3), np.nan) for k in ("p", "v", "bg", "ba", "f")}
    q_out = np.full((n, 4), np.nan)
    sig = np.full(n, np.nan)
    init = np.zeros(n, dtype=bool)
    verdicts: list[tuple[float, PoseVerdict]] = []
    frames: Sequence[MocapFrame] = sc.frames
    next_frame = 0
    for k in range(n):
        t = float(sc.truth.t_s[k])
        est.predict(t, sc.gyro_rad_s[k], sc.accel_m_s2[k],
                    sc.force_cmd_b_n[k] if feed_force else None)
        while next_frame < len(frames) and frames[next_frame].arrival_t_s <= t:
            f = frames[next_frame]
            verdicts.append((f.capture_t_s, est.update_pose(f.capture_t_s, f.pos_w_m, f.q_wb)))
            next_frame += 1
        if on_tick is not None:
            on_tick(k)
        if est.initialized:
            e = est.estimate()
            out["p"][k], out["v"][k], q_out[k] = e.pos_w_m, e.vel_w_m_s, e.q_wb
            out["bg"][k], out["ba"][k] = e.gyro_bias_rad_s, e.accel_bias_m_s2
            out["f"][k] = e.force_ext_w_n
            sig[k] = float(np.max(e.pos_sigma_m))
            init[k] = True
    return RunLog(sc.truth.t_s, out["p"], out["v"], q_out, out["bg"], out["ba"], sig, out["f"],
                  init, verdicts)

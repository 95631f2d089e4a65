"""Sensor models: the 500 Hz IMU and the 100 Hz motion capture, seeded.

IMU (paper: ADXRS620 gyros, MXR9500M accelerometer): each sample is the true body rate and
specific force plus a constant bias drawn once per run (sigma ``*_bias_sigma_*``) and white noise
of standard deviation ``density * sqrt(rate / 2)``: the densities are one-sided, as on the
datasheets (rms noise = density * sqrt(bandwidth)), and a sampled white noise is band-limited to
the Nyquist frequency ``rate / 2``. The estimator uses the same convention
(``estimator.config``: an integrated variance of ``density**2 / 2`` per second).

MoCap: a frame is captured every ``1 / mocap_rate_hz`` s of simulated time with Gaussian
position noise and a small random rotation (``mocap_att_noise_rad`` per axis), is lost with
probability ``mocap_dropout_prob``, and becomes available ``mocap_latency_s`` after capture. The
frame keeps its capture time, as a real MoCap timestamps at exposure.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np

from controller.reference import Quat, Vec3, quat_from_axis_angle, quat_mul
from sim_backend.disturbances import DisturbancePreset
from sim_backend.vehicle import ImuReading, PoseReading


class NormalStream:
    """Seeded standard normal numbers handed out one by one from pre-drawn blocks (a numpy
    call per number would cost ~0.5 us each)."""

    def __init__(self, rng: np.random.Generator, block: int = 4096) -> None:
        self._rng = rng
        self._block = block
        self._buf: list[float] = []
        self._i = 0

    def __call__(self) -> float:
        if self._i >= len(self._buf):
            self._buf = self._rng.standard_normal(self._block).tolist()
            self._i = 0
        x = self._buf[self._i]
        self._i += 1
        return x

    def take(self, count: int) -> list[float]:
        """The next ``count`` numbers at once (the same as ``count`` calls)."""
        i, j = self._i, self._i + count
        if j <= len(self._buf):
            self._i = j
            return self._buf[i:j]
        return [self() for _ in range(count)]


class ImuModel:
    """Gyro and accelerometer with constant biases and white noise."""

    def __init__(self, preset: DisturbancePreset, rng: np.random.Generator) -> None:
        self._n = NormalStream(rng)
        self.gyro_bias_rad_s: Vec3 = tuple(  # type: ignore[assignment]
            float(x) for x in rng.normal(0.0, 1.0, 3) * preset.gyro_bias_sigma_rad_s)
        self.accel_bias_m_s2: Vec3 = tuple(  # type: ignore[assignment]
            float(x) for x in rng.normal(0.0, 1.0, 3) * preset.accel_bias_sigma_m_s2)
        self._gyro_density = preset.gyro_noise_density_rad_s_rthz
        self._accel_density = preset.accel_noise_density_m_s2_rthz
        self._set_rate(preset.imu_rate_hz)
        self._period_ns = round(1e9 / preset.imu_rate_hz)
        self._last_t_s: float | None = None

    def _set_rate(self, rate_hz: float) -> None:
        half_rate = math.sqrt(rate_hz / 2.0)
        self.gyro_sigma_rad_s = self._gyro_density * half_rate
        self.accel_sigma_m_s2 = self._accel_density * half_rate

    def sample(self, t_s: float, omega_b_rad_s: Vec3, specific_force_b_m_s2: Vec3
               ) -> ImuReading:
        # the white noise of a sample follows the rate it is taken at (the density is the
        # sensor's): an emulated board asked for 1 kHz by its host samples at 1 kHz whatever
        # the preset's imu_rate_hz (the rate of simulate's loop) says
        last, self._last_t_s = self._last_t_s, t_s
        if last is not None:
            period_ns = round((t_s - last) * 1e9)
            if period_ns > 0 and period_ns != self._period_ns:
                self._period_ns = period_ns
                self._set_rate(1e9 / period_ns)
        gs, as_ = self.gyro_sigma_rad_s, self.accel_sigma_m_s2
        gb, ab = self.gyro_bias_rad_s, self.accel_bias_m_s2
        w, f = omega_b_rad_s, specific_force_b_m_s2
        n0, n1, n2, n3, n4, n5 = self._n.take(6)
        return ImuReading(
            t_s,
            (w[0] + gb[0] + gs * n0, w[1] + gb[1] + gs * n1, w[2] + gb[2] + gs * n2),
            (f[0] + ab[0] + as_ * n3, f[1] + ab[1] + as_ * n4, f[2] + ab[2] + as_ * n5),
        )


class MocapModel:
    """Frames captured at a fixed rate, delayed by the latency, some dropped."""

    def __init__(self, preset: DisturbancePreset, rng: np.random.Generator) -> None:
        self._n = NormalStream(rng)
        self._u = rng
        self.period_s = 1.0 / preset.mocap_rate_hz
        self.latency_s = preset.mocap_latency_s
        self.pos_sigma_m = preset.mocap_pos_noise_m
        self.att_sigma_rad = preset.mocap_att_noise_rad
        self.dropout_prob = preset.mocap_dropout_prob
        self.next_capture_s = 0.0
        self._pending: deque[tuple[float, PoseReading]] = deque()
        self.captured = 0
        self.dropped = 0
        # scheduled faults (sim_backend.scenario): occluded until this time, a reported offset,
        # a frozen (position, attitude)
        self.occluded_until_s = -math.inf
        self.offset_w_m: Vec3 = (0.0, 0.0, 0.0)
        self.frozen: tuple[Vec3, Quat] | None = None

    def maybe_capture(self, t_s: float, pos_w_m: Vec3, q_wb: Quat) -> None:
        """Capture a frame if one is due at ``t_s`` (call after every physics step)."""
        if self.frozen is not None:  # a frozen tracker: the same pose, fresh noise
            pos_w_m, q_wb = self.frozen
        while t_s + 1e-12 >= self.next_capture_s:
            self.next_capture_s += self.period_s
            self.captured += 1
            if self.dropout_prob > 0.0 and self._u.random() < self.dropout_prob:
                self.dropped += 1
                continue
            n, s, a = self._n, self.pos_sigma_m, self.att_sigma_rad
            p = (pos_w_m[0] + s * n(), pos_w_m[1] + s * n(), pos_w_m[2] + s * n())
            q = q_wb
            if a > 0.0:
                rx, ry, rz = a * n(), a * n(), a * n()
                ang = math.sqrt(rx * rx + ry * ry + rz * rz)
                if ang > 0.0:
                    q = quat_mul(q_wb, quat_from_axis_angle((rx / ang, ry / ang, rz / ang), ang))
            # the noise above is drawn for an occluded frame too: a dropout changes nothing else
            if t_s < self.occluded_until_s:
                self.dropped += 1
                continue
            o = self.offset_w_m
            if o != (0.0, 0.0, 0.0):
                p = (p[0] + o[0], p[1] + o[1], p[2] + o[2])
            self._pending.append((t_s + self.latency_s, PoseReading(t_s, p, q)))

    def poll(self, t_s: float) -> list[PoseReading]:
        """Frames that have become available by ``t_s`` (oldest first), each returned once."""
        out = []
        while self._pending and self._pending[0][0] <= t_s + 1e-12:
            out.append(self._pending.popleft()[1])
        return out

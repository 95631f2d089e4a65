"""MoCap checked against the IMU alone: a tracker that goes wrong while the UKF still fuses it.

The UKF fuses every pose its gate lets through, so a tracker that freezes while it still
streams (a stalled server repeating its solution, a rigid body locked onto still markers)
drags the estimate along: its innovations grow only as fast as the vehicle drifts from the
frozen pose, and the filter explains part of the difference away in its biases. This monitor
fuses nothing. It integrates the gyro and the accelerometer alone (less the UKF's biases) and
compares, over ``horizon_s``, what MoCap says changed with what the IMU felt:

- **rotation**: ``c = q_mocap (x) q_gyro^-1`` is the world attitude of the gyro's integration
  frame; it stays constant while the two agree (MoCap's noise and the bias error aside). Its
  change over the horizon, each end averaged over the poses of ``window_s``, is a rotation
  MoCap saw and the gyro did not.
- **velocity change**: MoCap's velocity (the least-squares slope of each end's poses)
  changed by ``dv_mocap``; the accelerometer, rotated into the world by the start's
  ``c`` and plus gravity, gives ``dv_imu`` between the same two instants (the windows' mean
  times, where a slope is the velocity). Their difference is a change of velocity one of the
  two did not see. A corrupted accelerometer sample spoils it (the caller says since when
  the IMU link was clean).

Neither needs the UKF's own position, velocity or attitude, which a wrong MoCap pulls; only
its biases, which move slowly (and which a wrong MoCap pulls too, slowly: a drift of a few
cm/s per second is found late). Measured on the emulated vehicle (lockstep, paper-calibrated
disturbances, 1 s horizon, 0.2 s windows at 100 Hz): in the air, 20 fault-free flights with
the paper's three experiments among them stayed under 0.20 deg and 0.022 m/s (0.35 deg on a
0.5 % corrupted link); a tracker frozen in the hover crossed 0.4 deg or 0.05 m/s a median
0.4-1.1 s after it froze.

Feed it every IMU sample (:meth:`ConsistencyMonitor.add_imu`, an append) and every MoCap pose
(:meth:`ConsistencyMonitor.add_pose`, where the integration runs, up to the capture time).
Python floats but for the windows' statistics, a compiled loop over the poses kept in an array
(:func:`estimator.compiled.window_stats`; interpreted without numba, with the same bits): about
15 us per pose at 500 Hz IMU and 100 Hz MoCap (five samples integrated, one 20-pose window; 29
us with the window in Python), nothing per IMU sample but the append.
"""

from __future__ import annotations

import bisect
import collections
import math
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from . import compiled
from .quaternion import mul_tuple, rotate_tuple

#: the span over which MoCap and the IMU are compared (s)
HORIZON_S = 1.0
#: the poses of this span are averaged at each end of the horizon (20 at 100 Hz: MoCap's
#: velocity from 0.1 s was twice as noisy, 0.041 m/s at most in fault-free flights)...
WINDOW_S = 0.2
#: ... if there are at least this many over 3/4 of the span (a MoCap slower than 25 Hz, a
#: dropout: no comparison)
MIN_WINDOW_POSES = 5
#: a longer gap between two IMU samples loses the integral: the comparison starts afresh
MAX_IMU_GAP_S = 0.1
#: IMU samples kept for poses not yet arrived; beyond this (a long MoCap outage) the oldest
#: are integrated at once
MAX_PENDING_IMU = 4096
#: poses the array holds at first (it doubles when full): 1.4 s at 100 Hz and the 256 kept
#: until the next trim (_trim)
INITIAL_POSES = 512


class Comparison(NamedTuple):
    """MoCap against the IMU over one horizon, ending at the pose captured at ``t_s``."""

    t_s: float
    start_s: float
    """The mean capture time of the horizon's first window."""
    rotation_deg: float
    """The rotation MoCap saw and the gyro did not."""
    velocity_gap_m_s: float
    """|dv_mocap - dv_imu|; NaN when the accelerometer was not clean over the horizon."""


#: a window's statistics: the mean c, the mean time, the mean u, MoCap's velocity. A pose is a
#: row of the monitor's array: t, the position, c = q_mocap (x) q_gyro^-1 and u, the integral
#: of R_gyro (accel - b_a) dt, at the capture time
_WindowStats = tuple[tuple[float, float, float, float], float, tuple[float, float, float],
                     tuple[float, float, float]]


class ConsistencyMonitor:
    """Integrates the IMU on its own and compares it with MoCap over ``horizon_s``."""

    def __init__(self, gravity_m_s2: float, horizon_s: float = HORIZON_S,
                 window_s: float = WINDOW_S) -> None:
        if not 0.0 < window_s < horizon_s:
            raise ValueError("need 0 < window_s < horizon_s")
        self.gravity_m_s2 = gravity_m_s2
        self.horizon_s = horizon_s
        self.window_s = window_s
        self._pending: collections.deque[tuple[float, Sequence[float], Sequence[float]]] = \
            collections.deque()
        self.clear()
        warm_up()

    def clear(self) -> None:
        """Forget everything: the integration and the poses."""
        self._pending.clear()
        self._t_int = math.nan            # time of the last integrated sample
        self._q: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)
        self._u = (0.0, 0.0, 0.0)
        self._bg: tuple[float, float, float] = (0.0, 0.0, 0.0)
        self._ba: tuple[float, float, float] = (0.0, 0.0, 0.0)
        # the poses, one row each (compiled.POSE_WIDTH columns), the first _n in use; their
        # times also in a list (bisect)
        self._poses = np.empty((INITIAL_POSES, compiled.POSE_WIDTH))
        self._n = 0
        self._stats = np.empty(compiled.POSE_WIDTH)  # window_stats' output
        self._times: list[float] = []
        # each pose's window statistics once computed (the window ending at a pose is the
        # horizon's last one, then a horizon later its first one)
        self._windows: list[_WindowStats | None] = []

    def add_imu(self, t_s: float, gyro_rad_s: Sequence[float],
                accel_m_s2: Sequence[float]) -> None:
        """One IMU sample (body frame, specific force), integrated when a pose needs it."""
        pending = self._pending
        pending.append((t_s, gyro_rad_s, accel_m_s2))
        if len(pending) > MAX_PENDING_IMU:
            self._integrate(*pending.popleft())

    def _integrate(self, t: float, g: Sequence[float], a: Sequence[float]) -> None:
        if not t > self._t_int:   # the first sample (the clock starts), or one out of order
            if math.isnan(self._t_int) and math.isfinite(t):
                self._t_int = t
            return
        if not math.isfinite(t):
            return
        if t - self._t_int > MAX_IMU_GAP_S:   # the integral is lost: compare afresh
            self._n = 0
            self._times.clear()
            self._windows.clear()
        else:
            self._q, self._u = self._advance(t - self._t_int, g, a)
        self._t_int = t

    def _advance(self, dt: float, g: Sequence[float], a: Sequence[float]
                 ) -> tuple[tuple[float, float, float, float], tuple[float, float, float]]:
        """The integration state moved by ``dt`` at this sample's rates (its interval ends at
        the sample: the rate it reports is the interval's); unmoved by a non-finite sample.
        Inlined: it runs for every IMU sample."""
        bg, ba = self._bg, self._ba
        if not math.isfinite(dt + g[0] + g[1] + g[2] + a[0] + a[1] + a[2]
                             + bg[0] + bg[1] + bg[2] + ba[0] + ba[1] + ba[2]):
            return self._q, self._u
        w, x, y, z = self._q
        # specific force in the integration frame: f = R(q) (a - b_a)
        fa, fb, fc = a[0] - ba[0], a[1] - ba[1], a[2] - ba[2]
        tx, ty, tz = 2.0 * (y * fc - z * fb), 2.0 * (z * fa - x * fc), 2.0 * (x * fb - y * fa)
        u0, u1, u2 = self._u
        u = (u0 + (fa + w * tx + y * tz - z * ty) * dt, u1 + (fb + w * ty + z * tx - x * tz) * dt,
             u2 + (fc + w * tz + x * ty - y * tx) * dt)
        # q (x) Exp(rotation), normalised
        ra, rb, rc = (g[0] - bg[0]) * dt, (g[1] - bg[1]) * dt, (g[2] - bg[2]) * dt
        angle = math.sqrt(ra * ra + rb * rb + rc * rc)
        if not angle < 100.0:                 # garbage (overflowed): left out
            return self._q, self._u
        if angle > 1e-12:
            k = math.sin(0.5 * angle) / angle
            cw, ra, rb, rc = math.cos(0.5 * angle), ra * k, rb * k, rc * k
        else:
            cw, ra, rb, rc = 1.0, 0.5 * ra, 0.5 * rb, 0.5 * rc
        qw = w * cw - x * ra - y * rb - z * rc
        qx = w * ra + x * cw + y * rc - z * rb
        qy = w * rb - x * rc + y * cw + z * ra
        qz = w * rc + x * rb - y * ra + z * cw
        n = 1.0 / math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
        return (qw * n, qx * n, qy * n, qz * n), u

    def add_pose(self, t_s: float, pos_w_m: Sequence[float], q_wb: Sequence[float],
                 gyro_bias_rad_s: Sequence[float], accel_bias_m_s2: Sequence[float],
                 accel_clean_since_s: float = -math.inf) -> Comparison | None:
        """A MoCap pose captured at ``t_s`` (IMU clock), with the UKF's biases now. Returns
        the comparison over the horizon ending here, or None (too little history yet, a
        window with a dropout, a pose older than the last one). ``accel_clean_since_s``: no
        IMU anomaly since then; the velocity gap is NaN for a horizon starting earlier."""
        self._bg = (float(gyro_bias_rad_s[0]), float(gyro_bias_rad_s[1]),
                    float(gyro_bias_rad_s[2]))
        self._ba = (float(accel_bias_m_s2[0]), float(accel_bias_m_s2[1]),
                    float(accel_bias_m_s2[2]))
        pending = self._pending
        while pending and pending[0][0] <= t_s:
            self._integrate(*pending.popleft())
        if math.isnan(self._t_int) or (self._times and not t_s > self._times[-1]):
            return None
        if not math.isfinite(t_s + pos_w_m[0] + pos_w_m[1] + pos_w_m[2] + q_wb[0] + q_wb[1]
                             + q_wb[2] + q_wb[3]):
            return None
        q, u = self._q, self._u
        if t_s > self._t_int and pending:   # the part of the next sample's interval
            _, g, a = pending[0]
            q, u = self._advance(t_s - self._t_int, g, a)
        qw, qx, qy, qz = q_wb
        c = mul_tuple((qw, qx, qy, qz), (q[0], -q[1], -q[2], -q[3]))
        if self._n == len(self._poses):
            self._poses = np.concatenate((self._poses, np.empty_like(self._poses)))
        self._poses[self._n] = (t_s, pos_w_m[0], pos_w_m[1], pos_w_m[2], *c, *u)
        self._n += 1
        self._times.append(t_s)
        self._windows.append(None)
        self._trim(t_s)
        return self._compare(accel_clean_since_s)

    def _trim(self, t_s: float) -> None:
        keep_from = t_s - self.horizon_s - 2.0 * self.window_s
        n = bisect.bisect_left(self._times, keep_from)
        if n > 256:                          # in blocks: deleting a list's head copies it
            self._poses[:self._n - n] = self._poses[n:self._n]
            self._n -= n
            del self._times[:n]
            del self._windows[:n]

    def _compare(self, clean_since_s: float) -> Comparison | None:
        times = self._times
        i = self._n - 1
        t_i = times[i]
        j = bisect.bisect_right(times, t_i - self.horizon_s) - 1
        if j < 0:
            return None
        wins = self._windows
        wi = wins[i] = self._window(i)
        wj = wins[j] or self._window(j)
        if wi is None or wj is None:
            return None
        ci, ti, ui, vi = wi
        cj, tj, uj, vj = wj
        # the rotation between the two ends' gyro-frame attitudes
        rw, rx, ry, rz = mul_tuple(ci, (cj[0], -cj[1], -cj[2], -cj[3]))
        rot = 2.0 * math.atan2(math.sqrt(rx * rx + ry * ry + rz * rz), abs(rw))
        gap = math.nan
        if tj - 0.5 * self.window_s > clean_since_s:
            dt = ti - tj
            du = rotate_tuple(cj, (ui[0] - uj[0], ui[1] - uj[1], ui[2] - uj[2]))
            dv_imu = (du[0], du[1], du[2] - self.gravity_m_s2 * dt)
            gap = math.sqrt((vi[0] - vj[0] - dv_imu[0]) ** 2 + (vi[1] - vj[1] - dv_imu[1]) ** 2
                            + (vi[2] - vj[2] - dv_imu[2]) ** 2)
        return Comparison(t_i, tj, math.degrees(rot), gap)

    def _window(self, k: int) -> _WindowStats | None:
        """The statistics of the window ending at pose k (None: too few poses in it)."""
        times = self._times
        lo = bisect.bisect_right(times, times[k] - self.window_s + 1e-6)
        # a window cut short (the start of the data, a dropout) has a noisy slope
        if k + 1 - lo < MIN_WINDOW_POSES or times[k] - times[lo] < 0.75 * self.window_s:
            return None
        kernel = compiled.window_stats
        if not compiled.AVAILABLE:   # the same function, interpreted
            kernel = getattr(kernel, "py_func", kernel)
        kernel(self._poses, lo, k + 1, self._stats)
        o = self._stats.tolist()
        return (o[0], o[1], o[2], o[3]), o[4], (o[5], o[6], o[7]), (o[8], o[9], o[10])


def warm_up() -> None:
    """Compile (or load from numba's cache) the window kernel: before a flight, not in it."""
    if compiled.AVAILABLE:
        poses = np.zeros((MIN_WINDOW_POSES, compiled.POSE_WIDTH))
        poses[:, 0] = np.arange(MIN_WINDOW_POSES)
        poses[:, 4] = 1.0
        compiled.window_stats(poses, 0, MIN_WINDOW_POSES, np.empty(compiled.POSE_WIDTH))

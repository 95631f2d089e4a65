"""MoCap poses received over MAVLink (ATT_POS_MOCAP, VISION_POSITION_ESTIMATE) as a
:class:`~drivers.mocap.pose.PoseSource`.

The values are checked before anything is delivered: a non-finite position or angle, a
quaternion that cannot be normalised, or a position farther than :data:`MAX_POSE_RANGE_M` from
the origin (no lab cage is that large; a pose 1 km away is a sender's bug, not a measurement)
is dropped and counted as malformed. Capture time = arrival time on our clock minus the
configured latency (the sender's clock is not comparable to ours).
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable

from drivers.mavlink.frames import (
    Quat,
    Vec3,
    ned_to_world,
    q_from_euler,
    q_ned_to_world,
    q_normalized,
)
from drivers.mocap.pose import MocapStats, PoseSample, StreamMonitor, TrackingStatus

MOCAP_BODY_ID = 0
#: Farthest a MAVLink MoCap position may be from the world origin (m).
MAX_POSE_RANGE_M = 100.0


def pose_in_range(pos_ned_m: Vec3) -> bool:
    """Finite and within :data:`MAX_POSE_RANGE_M` of the origin."""
    return all(math.isfinite(v) for v in pos_ned_m) and \
        math.sqrt(sum(v * v for v in pos_ned_m)) <= MAX_POSE_RANGE_M


def euler_to_q(roll: float, pitch: float, yaw: float) -> Quat | None:
    """The quaternion of finite ZYX Euler angles (rad); None when any is NaN or infinite."""
    if not (math.isfinite(roll) and math.isfinite(pitch) and math.isfinite(yaw)):
        return None
    return q_from_euler(roll, pitch, yaw)


class MavlinkPoseSource:
    """MoCap poses received over MAVLink as a :class:`~drivers.mocap.pose.PoseSource`."""

    def __init__(self, clock_ns: Callable[[], int], latency_s: float) -> None:
        self._clock_ns = clock_ns
        self._latency_s = latency_s
        self._monitor = StreamMonitor(clock_ns)
        self._lock = threading.Lock()
        self._latest: PoseSample | None = None
        self._seq = 0
        self.out_of_range = 0  # poses dropped for their values (also counted as malformed)

    def latest(self) -> PoseSample | None:
        with self._lock:
            return self._latest

    def stats(self) -> MocapStats:
        return self._monitor.snapshot()

    def _refuse(self) -> bool:
        self.out_of_range += 1
        self._monitor.count_malformed()
        return False

    def on_euler_pose(self, pos_ned_m: Vec3, roll: float, pitch: float, yaw: float,
                      source: str) -> bool:
        """A VISION_POSITION_ESTIMATE-style pose; False (and counted) when refused."""
        q = euler_to_q(roll, pitch, yaw)
        if q is None:
            return self._refuse()
        return self.on_pose(pos_ned_m, q, source)

    def on_pose(self, pos_ned_m: Vec3, q_ned_frd: Quat, source: str) -> bool:
        """A pose in NED with the body FRD -> NED quaternion; False (and counted) when its
        values are not physical."""
        rx = self._clock_ns()
        try:
            q = q_ned_to_world(q_normalized(q_ned_frd))
        except (ValueError, OverflowError):
            return self._refuse()
        if not pose_in_range(pos_ned_m):
            return self._refuse()
        self._seq += 1
        sample = PoseSample(
            t_ns=rx - int(self._latency_s * 1e9), rx_t_ns=rx, frame_number=self._seq,
            body_id=MOCAP_BODY_ID, body_name=source, status=TrackingStatus.OK,
            pos_w_m=ned_to_world(pos_ned_m), q_wb=q, latency_s=self._latency_s,
            mean_error_m=math.nan)
        self._monitor.on_frame(self._seq, rx, self._latency_s)
        self._monitor.on_sample(sample)
        with self._lock:
            self._latest = sample
        return True

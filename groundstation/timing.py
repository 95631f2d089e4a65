"""Loop timing: per-tick period, jitter, compute time and deadline misses, plus the scheduler
settings a lab would use for a 500 Hz Python loop.

:class:`LoopTimer` stores every tick's numbers in preallocated arrays (no allocation in the tick)
and summarises them at the end. :func:`apply_realtime_settings` (from
:mod:`drivers.realtime`) tries CPU affinity, SCHED_FIFO for every thread, locked memory and a
frozen garbage collector, and reports which took effect (unprivileged users and containers often
refuse SCHED_FIFO).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from drivers.realtime import apply_realtime_settings, restore_default_settings


@dataclass(frozen=True)
class TimingSummary:
    ticks: int
    deadline_misses: int
    period_p50_ms: float
    period_p99_ms: float
    jitter_p50_ms: float
    jitter_p99_ms: float
    compute_p50_ms: float
    compute_p99_ms: float
    compute_max_ms: float
    latency_p50_ms: float = 0.0  # IMU bytes received -> `w` frame written
    latency_p99_ms: float = 0.0
    compute_mean_ms: float = 0.0
    #: the tick's numerics alone, timed inside the tick: UKF predict (and a pose's update),
    #: the estimate as the loop reads it, the controller (the rest of the compute is I/O,
    #: parsing, the monitor, the state machine and the record)
    numerics_p50_ms: float = 0.0
    numerics_mean_ms: float = 0.0

    @property
    def miss_fraction(self) -> float:
        return self.deadline_misses / self.ticks if self.ticks else 0.0


class LoopTimer:
    """Records tick start/end times (ns, on the loop's clock) into preallocated arrays."""

    def __init__(self, nominal_period_s: float, capacity: int = 500 * 3600) -> None:
        self.nominal_ns = round(nominal_period_s * 1e9)
        self._start = np.zeros(capacity, dtype=np.int64)
        self._compute = np.zeros(capacity, dtype=np.int64)
        self._latency = np.zeros(capacity, dtype=np.int64)
        self._numerics = np.zeros(capacity, dtype=np.int64)
        self._n = 0
        self._capacity = capacity
        self.deadline_misses = 0

    def record(self, start_ns: int, end_ns: int, latency_ns: int = 0,
               numerics_ns: int = 0) -> None:
        """One tick: when the loop took its input (start), when its output was written (end),
        how long after the input's arrival the output went out (``latency_ns``) and how much of
        it the numerics took (``numerics_ns``)."""
        compute = end_ns - start_ns
        if compute > self.nominal_ns:
            self.deadline_misses += 1
        if self._n < self._capacity:
            self._start[self._n] = start_ns
            self._compute[self._n] = compute
            self._latency[self._n] = latency_ns
            self._numerics[self._n] = numerics_ns
        self._n += 1

    @property
    def ticks(self) -> int:
        return self._n

    def compute_ms(self, i: int) -> float:
        """Compute time of tick ``i`` (ms); NaN when that tick was not recorded."""
        return float(self._compute[i]) * 1e-6 if 0 <= i < min(self._n, self._capacity) \
            else math.nan

    def last_compute_s(self) -> float:
        i = min(self._n, self._capacity) - 1
        return float(self._compute[i]) * 1e-9 if i >= 0 else 0.0

    def summary(self) -> TimingSummary:
        n = min(self._n, self._capacity)
        if n < 2:
            return TimingSummary(self._n, self.deadline_misses, *([0.0] * 9))
        numerics = self._numerics[:n] * 1e-6
        period = np.diff(self._start[:n]) * 1e-6
        jitter = np.abs(period - self.nominal_ns * 1e-6)
        compute = self._compute[:n] * 1e-6
        return TimingSummary(
            ticks=self._n,
            deadline_misses=self.deadline_misses,
            period_p50_ms=float(np.percentile(period, 50)),
            period_p99_ms=float(np.percentile(period, 99)),
            jitter_p50_ms=float(np.percentile(jitter, 50)),
            jitter_p99_ms=float(np.percentile(jitter, 99)),
            compute_p50_ms=float(np.percentile(compute, 50)),
            compute_p99_ms=float(np.percentile(compute, 99)),
            compute_max_ms=float(np.max(compute)),
            latency_p50_ms=float(np.percentile(self._latency[:n], 50)) * 1e-6,
            latency_p99_ms=float(np.percentile(self._latency[:n], 99)) * 1e-6,
            compute_mean_ms=float(np.mean(compute)),
            numerics_p50_ms=float(np.percentile(numerics, 50)),
            numerics_mean_ms=float(np.mean(numerics)),
        )


# The scheduler settings live with the device threads they serve (the emulated vehicle uses
# them too); re-exported here for the loop's callers.
__all__ = ["LoopTimer", "TimingSummary", "apply_realtime_settings", "restore_default_settings"]

"""The CPU wake-up latency request (Linux PM QoS, ``/dev/cpu_dma_latency``): held while asked,
released on request, reported (not raised) where the system refuses it.

The kernel keeps the tightest of every open request, and other test workers may fly (and hold
it) at the same time: "released" is judged on this process's own open files, not on the value.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from flight_support import can_hold_cpu_latency as can_request
from flight_support import open_cpu_latency_requests as open_requests

from drivers import realtime
from drivers.realtime import (
    CPU_LATENCY_PATH,
    apply_realtime_settings,
    cpu_latency_us,
    hold_cpu_latency,
    release_cpu_latency,
    restore_default_settings,
)

needs_pm_qos = pytest.mark.skipif(not can_request(),
                                  reason="/dev/cpu_dma_latency absent or not writable (root)")


@pytest.fixture(autouse=True)
def _released() -> object:
    yield
    release_cpu_latency()


@needs_pm_qos
def test_that_a_hold_keeps_the_cpus_awake_until_released() -> None:
    assert open_requests() == 0
    outcome = hold_cpu_latency(0)
    assert outcome == f"wake-up latency held at 0 us ({CPU_LATENCY_PATH})"
    assert open_requests() == 1
    assert cpu_latency_us() == 0  # the tightest request wins: ours
    release_cpu_latency()
    assert open_requests() == 0
    release_cpu_latency()  # twice is harmless
    assert open_requests() == 0


@needs_pm_qos
def test_that_a_second_hold_replaces_the_first() -> None:
    hold_cpu_latency(50)
    hold_cpu_latency(0)
    assert open_requests() == 1
    assert cpu_latency_us() == 0


@needs_pm_qos
def test_that_the_realtime_settings_hold_it_and_their_restore_releases_it() -> None:
    report = apply_realtime_settings(cpu=-1, fifo_priority=0, lock_memory=False,
                                     freeze_gc=False)
    try:
        assert report["cpu idle"].startswith("wake-up latency held at 0 us")
        assert open_requests() == 1
    finally:
        restore_default_settings()
    assert open_requests() == 0
    report = apply_realtime_settings(cpu=-1, fifo_priority=0, lock_memory=False,
                                     freeze_gc=False, cpu_latency=False)
    restore_default_settings()
    assert "cpu idle" not in report


def test_that_a_missing_or_refused_device_is_reported_not_raised(tmp_path: Path) -> None:
    missing = tmp_path / "absent"
    assert hold_cpu_latency(0, missing) == f"unchanged (no {missing}: not Linux, or no PM QoS)"
    assert realtime._cpu_latency_fd is None
    # a path that cannot be opened for writing (a directory stands for any refusal)
    out = hold_cpu_latency(0, tmp_path)
    assert out.startswith(f"unchanged ({tmp_path}: ") and realtime._cpu_latency_fd is None
    assert cpu_latency_us(missing) is None


def test_that_a_nonsense_latency_is_refused() -> None:
    for bad in (-1, 2**31):
        with pytest.raises(ValueError, match="max_us"):
            hold_cpu_latency(bad)

"""The MoCap server on the bench: the configured body streams at a usable rate, with a
plausible latency and finite poses."""

from __future__ import annotations

import math
import time

import pytest

from drivers.mocap.uri import open_pose_source

pytestmark = pytest.mark.hil

MIN_RATE_HZ = 50.0
"""Below this the UKF's position updates are too sparse for the 500 Hz loop (Motive: 100+ Hz)."""
MAX_LATENCY_S = 0.05
"""A MoCap chain takes a few ms; tens of ms means a congested network or a wrong clock."""


def test_that_the_body_streams_at_a_usable_rate_and_latency(mocap_uri: str) -> None:
    # Fixture
    latencies_s: list[float] = []
    with open_pose_source(mocap_uri) as src:
        # Test: 200 frames (2 s at 100 Hz), the latency of each seen (the newest sample,
        # polled faster than the frames come)
        deadline = time.monotonic() + 10.0
        last = sample = None
        seen = valid = 0
        while src.stats().frames_received < 200 and time.monotonic() < deadline:
            s = src.latest()
            if s is not None and s is not last:
                latencies_s.append(s.latency_s)
                last = s
                seen += 1
                if s.valid:     # a real system loses the body for a frame now and then
                    valid += 1
                    sample = s
            time.sleep(0.002)
        got = src.stats().frames_received >= 200
        stats = src.stats()
    # Assert
    assert got, f"fewer than 200 frames in 10 s ({stats.frames_received})"
    assert stats.rate_hz >= MIN_RATE_HZ
    # the typical frame: one frame delayed by a busy host is not a congested chain (the
    # emulated server, in real time on two shared cores, delivers some frames 50 ms late)
    # a poller descheduled on a loaded host sees fewer distinct frames (49 of 200 once in CI):
    # enough for a median is what matters here; the rate above is the server's own
    assert len(latencies_s) >= 20
    median_s = sorted(latencies_s)[len(latencies_s) // 2]
    assert min(latencies_s) >= 0.0 and median_s <= MAX_LATENCY_S, (median_s, max(latencies_s))
    assert stats.malformed_packets == 0 and stats.implausible_samples == 0
    # tracked: nearly every frame valid (the emulated server drops ~1 % of frames, as the
    # paper-calibrated preset says; the test once failed on a last frame that was one)
    assert valid >= 0.9 * seen, (valid, seen)
    assert sample is not None and sample.valid
    assert all(math.isfinite(v) for v in (*sample.pos_w_m, *sample.q_wb))
    assert math.sqrt(sum(q * q for q in sample.q_wb)) == pytest.approx(1.0, abs=1e-3)

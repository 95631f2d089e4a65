"""ClockSync against synthetic clocks whose truth is known: drift, offset, jitter, spikes, gaps,
steps. Errors are against the true host time of the remote instant plus the smallest delay
(the part one-way stamps cannot see)."""

from __future__ import annotations

import math
import random

import pytest

from drivers.clock_sync import ClockSync

PERIOD_NS = 2_000_000  # a 500 Hz board counter
MIN_DELAY_NS = 60_000


def _run(cs: ClockSync, n: int, *, rate: float, offset_ns: int, seed: int = 1,
         spike_p: float = 0.0, start: int = 0, jitter_ns: float = 30_000.0
         ) -> tuple[int, int, int]:
    """Feed n samples; (largest |error| after the first second, newest error, negatives)."""
    rng = random.Random(seed)
    worst = last = late = 0
    for k in range(start, start + n):
        remote = k * PERIOD_NS
        true_host = offset_ns + round(remote * rate)
        delay = MIN_DELAY_NS + int(rng.expovariate(1.0 / jitter_ns))
        if rng.random() < spike_p:
            delay += rng.randint(1_000_000, 40_000_000)
        arrival = true_host + delay
        mapped = cs.update(remote, arrival)
        late += mapped > arrival
        last = mapped - (true_host + MIN_DELAY_NS)
        if k - start > 500:
            worst = max(worst, abs(last))
    return worst, last, late


@pytest.mark.parametrize("drift_ppm", [-12_000.0, -50.0, 0.0, 30.0, 12_000.0])
def test_drift_and_offset_learnt(drift_ppm: float) -> None:
    rate = 1.0 / (1.0 + drift_ppm * 1e-6)  # host s per remote s
    cs = ClockSync()
    worst, _, late = _run(cs, 500 * 60, rate=rate, offset_ns=3_000_000_000)
    assert late == 0
    assert cs.rate_known
    # 30 us of jitter over a 16 s baseline: the rate within a few ppm
    assert cs.drift_ppm == pytest.approx(drift_ppm, abs=3.0)
    assert worst < 500_000  # 0.5 ms from the second second on
    assert abs(cs.offset_ns - 3_000_000_000 - round(cs.last_remote_ns * (rate - 1.0))) < 1e6


def test_delay_spikes_neither_move_the_estimate_nor_step() -> None:
    cs = ClockSync()
    worst, last, late = _run(cs, 500 * 60, rate=1.012, offset_ns=0, spike_p=0.02)
    assert late == 0 and cs.steps == 0
    assert cs.drift_ppm == pytest.approx(-11_857.3, abs=3.0)
    assert abs(last) < 200_000
    assert worst < 600_000


def test_an_hour_keeps_latency_within_a_millisecond() -> None:
    cs = ClockSync()
    rate = 1.0 / (1.0 - 20e-6)
    rng = random.Random(3)
    worst = 0
    for k in range(0, 3600 * 500, 5):  # every 5th sample: an hour of remote time, 360 k calls
        remote = k * PERIOD_NS
        true_host = 7_000_000_000 + round(remote * rate)
        arrival = true_host + MIN_DELAY_NS + int(rng.expovariate(1 / 30_000))
        mapped = cs.update(remote, arrival)
        assert mapped <= arrival
        if k > 5000:
            worst = max(worst, abs(mapped - true_host - MIN_DELAY_NS))
    assert worst < 1_000_000
    assert cs.drift_ppm == pytest.approx(-20.0, abs=3.0)


def test_gap_then_continues() -> None:
    cs = ClockSync()
    _run(cs, 500 * 20, rate=1.012, offset_ns=0)
    # 10 s of silence, then the stream resumes on the same clock
    worst, last, late = _run(cs, 500 * 5, rate=1.012, offset_ns=0, start=500 * 30, seed=2)
    assert late == 0 and cs.steps == 0
    assert worst < 600_000 and abs(last) < 300_000


@pytest.mark.parametrize("step_s", [-2.0, 3.0])
def test_remote_clock_step_is_relearnt(step_s: float) -> None:
    cs = ClockSync()
    _run(cs, 500 * 20, rate=1.012, offset_ns=0)
    # the remote clock is set: the same host instants now carry remote times step_s later
    # (a step forward: host = offset + rate * remote with offset moved back by step_s * rate)
    shifted = -round(step_s * 1e9 * 1.012)
    _worst, last, late = _run(cs, 500 * 20, rate=1.012, offset_ns=shifted,
                             start=500 * 20 + round(step_s * 500), seed=4)
    assert cs.steps == 1
    assert late == 0
    assert abs(last) < 300_000
    assert cs.drift_ppm == pytest.approx(-11_857.3, abs=5.0)


def test_first_sample_maps_to_its_arrival_and_repeats_are_harmless() -> None:
    cs = ClockSync()
    assert cs.update(5, 1_000) == 1_000
    assert not cs.rate_known
    assert cs.update(5, 1_200) <= 1_200  # the same remote instant again, later
    assert cs.update(5, 900) == 900  # an earlier arrival is the better estimate


def test_invalid_settings() -> None:
    with pytest.raises(ValueError):
        ClockSync(block_s=0.0)
    with pytest.raises(ValueError):
        ClockSync(blocks=1)



@pytest.mark.parametrize("stall_ms", [150, 1500])
def test_a_host_stall_is_not_a_step(stall_ms: int) -> None:
    """The reader thread descheduled for a while: the samples of that span arrive late, in one
    burst (longer than the step confirmation: the burst's excess keeps dropping)."""
    cs = ClockSync()
    _run(cs, 500 * 10, rate=1.0, offset_ns=0)
    stall_end = None
    n = stall_ms // 2
    for k in range(500 * 10, 500 * 10 + n):
        remote = k * PERIOD_NS
        stall_end = stall_end or remote + stall_ms * 1_000_000
        mapped = cs.update(remote, stall_end)
        assert mapped <= stall_end
        # still on the envelope (the burst's tail, within a step of it, tilts the line a
        # little until the next blocks)
        assert abs(mapped - remote - MIN_DELAY_NS) < (300_000 if stall_ms < 500 else 3_000_000)
    assert cs.steps == 0
    _, last, late = _run(cs, 500, rate=1.0, offset_ns=0, start=500 * 10 + n)
    assert late == 0 and cs.steps == 0 and abs(last) < 300_000


STARTUPS = [(2, 0.1), (5, 0.1), (10, 0.1), (5, 0.3), (10, 0.3), (20, 0.6), (30, 0.2)]


@pytest.mark.parametrize(("drift_ppm", "startup_ms", "decay_s", "seed"), [
    *((d, ms, tau, seed) for d in (0.0, 200.0, 12_000.0) for ms, tau in STARTUPS
      for seed in (1, 2)),
    # a remote running slow reads as a delay that grows, the start-up as one that shrinks:
    # when the start-up is as large as the drift over the baseline and as slow, a second of
    # data cannot tell them apart (not asserted); short ones are covered
    *((-12_000.0, ms, tau, seed) for ms, tau in STARTUPS[:3] for seed in (1, 2)),
])
def test_a_start_up_delay_that_shrinks_is_inside_the_reported_error_bar(
        drift_ppm: float, startup_ms: int, decay_s: float, seed: int) -> None:
    # A MoCap stream at 100 Hz whose first frames a host still starting up stamps late: an
    # extra delay of startup_ms decaying over decay_s. Over the first second (a preflight) this
    # reads as a fast clock with small fit residuals (seen on a loaded host: +9314 +- 2583 ppm
    # for a server with no drift); the reported error bar must cover the truth (3 sigma), as
    # the preflight prints the drift with it.
    rng = random.Random(seed)
    rate = 1.0 / (1.0 + drift_ppm * 1e-6)
    cs = ClockSync()
    period_ns = 10_000_000
    for k in range(101):
        remote = k * period_ns
        extra = startup_ms * 1e6 * math.exp(-remote * 1e-9 / decay_s)
        arrival = round(remote * rate) + MIN_DELAY_NS + int(rng.expovariate(1 / 30_000.0)) \
            + round(extra)
        cs.update(remote, arrival)
    assert math.isfinite(cs.drift_sigma_ppm)
    assert abs(cs.drift_ppm - drift_ppm) <= 3.0 * cs.drift_sigma_ppm, (
        cs.drift_ppm, cs.drift_sigma_ppm)


def test_the_error_bar_of_a_steady_stream_is_its_jitter_not_inflated() -> None:
    # no start-up trend: after a minute of 30 us jitter the bar is a few ppm and covers the
    # truth (the jackknife agrees with the residuals when the line is the right model)
    cs = ClockSync()
    _run(cs, 500 * 60, rate=1.0 / (1.0 + 30e-6), offset_ns=0)
    assert cs.drift_sigma_ppm < 5.0
    assert abs(cs.drift_ppm - 30.0) <= max(3.0 * cs.drift_sigma_ppm, 1.0)

"""FlightCtrl receive path on a loopback transport with an injected clock."""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterator

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.mikrokopter import (
    FlightCtrl,
    FlightCtrlConfig,
    ImuAxes,
    ImuSample,
    LinkHealth,
    MotorState,
)
from drivers.mikrokopter import framing_tk3 as tk3
from drivers.mikrokopter import messages as mkm
from drivers.mikrokopter.device import _ImuTimeBase
from drivers.transport import LoopTransport

MS = 1_000_000


class FakeClock:
    def __init__(self) -> None:
        self.t_ns = 1_000 * MS

    def __call__(self) -> int:
        return self.t_ns


def _imu(seq: int, gz: float = 0.0) -> bytes:
    return tk3.encode_frame(mkm.ImuMessage(seq & 0xFF, (0.0, 0.0, 9.81), (0.0, 0.0, gz)).encode())


@pytest.fixture
def link() -> Iterator[tuple[FlightCtrl, LoopTransport, FakeClock]]:
    wire = LoopTransport("loop://test", read_timeout_s=0.01)
    clock = FakeClock()
    fc = FlightCtrl(wire, FlightCtrlConfig(imu_axes=ImuAxes(axis=(1, 0, 2), sign=(1, 1, -1))),
                    clock=clock)
    fc.start()
    yield fc, wire, clock
    fc.close()


def _push(fc: FlightCtrl, wire: LoopTransport, clock: FakeClock, frame: bytes, t_ms: float
          ) -> ImuSample | None:
    """Deliver one frame at ``t_ms``; the sample it produced, or None once it was processed."""
    clock.t_ns = 1_000 * MS + round(t_ms * MS)
    before = fc.link_stats().frames
    wire.write(frame)
    for _ in range(2000):
        sample = fc.wait_next(0.005)
        if sample is not None:
            return sample
        if fc.link_stats().frames > before:
            return fc.wait_next(0.0)  # processed without a sample (or one just landed)
    raise AssertionError("the reader never processed the frame")


def test_that_sample_times_are_rebuilt_from_sequence_numbers(
        link: tuple[FlightCtrl, LoopTransport, FakeClock]) -> None:
    fc, wire, clock = link
    # arrival jitter of up to 0.7 ms; the rebuilt times keep the 2 ms grid, give or take the
    # 100 ppm per sample the offset may drift up to follow a slower board clock
    times = [_push(fc, wire, clock, _imu(i), 2.0 * i + (0.7 if i % 2 else 0.0))
             for i in range(10)]
    assert all(s is not None for s in times)
    t = [s.t_ns for s in times if s is not None]
    assert all(abs(b - a - 2 * MS) <= 2 * MS // 10_000 for a, b in itertools.pairwise(t))
    assert t[-1] - t[0] == pytest.approx(18 * MS, abs=2 * MS // 1_000)
    assert [s.seq for s in times if s is not None] == list(range(10))


def test_that_a_short_gap_is_accepted_and_counted_as_missing(
        link: tuple[FlightCtrl, LoopTransport, FakeClock]) -> None:
    fc, wire, clock = link
    _push(fc, wire, clock, _imu(0), 0.0)
    _push(fc, wire, clock, _imu(1), 2.0)
    s = _push(fc, wire, clock, _imu(4), 8.0)  # two samples lost on the wire
    assert s is not None and s.seq == 4
    assert s.t_ns - 1_000 * MS == 8 * MS
    assert fc.link_stats().imu.missing == 2


def test_that_a_corrupted_sequence_number_is_dropped_without_losing_the_stream(
        link: tuple[FlightCtrl, LoopTransport, FakeClock]) -> None:
    fc, wire, clock = link
    for i in range(3):
        _push(fc, wire, clock, _imu(i), 2.0 * i)
    # seq byte hit by noise: 2 -> 0x47, arriving one period later
    assert _push(fc, wire, clock, _imu(0x47), 6.0) is None
    s = _push(fc, wire, clock, _imu(4), 8.0)
    assert s is not None and s.seq == 4
    stats = fc.link_stats()
    assert stats.seq_rejected == 1 and stats.resyncs == 0


def test_that_a_long_outage_resynchronises_on_two_consecutive_samples(
        link: tuple[FlightCtrl, LoopTransport, FakeClock]) -> None:
    fc, wire, clock = link
    _push(fc, wire, clock, _imu(0), 0.0)
    assert _push(fc, wire, clock, _imu(100), 200.0) is None  # 99 lost: suspect
    s = _push(fc, wire, clock, _imu(101), 202.0)
    assert s is not None and s.seq == 101
    assert s.t_ns - 1_000 * MS == 202 * MS
    assert fc.link_stats().resyncs == 1


def test_that_a_sequence_byte_corrupted_ahead_does_not_move_the_clock_a_wrap_ahead(
        link: tuple[FlightCtrl, LoopTransport, FakeClock]) -> None:
    # Fixture: a 0.5 % corrupted link (seed 14, no other fault): sample 84's sequence byte
    # read 86 (one bit), taken as two lost samples; the real 85 was then a suspect, and the
    # real 86 continuing it resynchronised the counter 256 samples ahead (0.512 s: the
    # estimator predicted over half a second at once and the flight ended blind)
    fc, wire, clock = link
    for k in range(84):
        _push(fc, wire, clock, _imu(k), 2.0 * k)
    # Test
    ahead = _push(fc, wire, clock, _imu(86), 2.0 * 84 + 4.0)  # 84, corrupted, late enough
    real = [_push(fc, wire, clock, _imu(k), 2.0 * k + 4.0) for k in (85, 86, 87, 88)]
    # Assert: 85 and 86 dropped (at or behind the counter), 87 and 88 taken as the next
    # samples, two periods after the corrupted one at most
    assert ahead is not None and ahead.seq == 86
    assert real[:2] == [None, None]
    assert real[2] is not None and real[3] is not None
    assert real[2].t_ns - ahead.t_ns == pytest.approx(2 * MS, abs=0.01 * MS)
    assert real[3].t_ns - ahead.t_ns == pytest.approx(4 * MS, abs=0.01 * MS)
    stats = fc.link_stats()
    assert stats.resyncs == 0 and stats.seq_rejected == 2


def test_that_wrong_lengths_and_out_of_range_values_never_reach_the_caller(
        link: tuple[FlightCtrl, LoopTransport, FakeClock]) -> None:
    fc, wire, clock = link
    _push(fc, wire, clock, _imu(0), 0.0)
    short = tk3.encode_frame(mkm.ImuMessage(1, (0, 0, 9.81), (0, 0, 0)).encode()[:-1])
    assert _push(fc, wire, clock, short, 2.0) is None
    assert _push(fc, wire, clock, _imu(1, gz=30.0), 2.0) is None  # beyond the gyro full scale
    stats = fc.link_stats()
    assert (stats.malformed, stats.implausible) == (1, 1)


def test_that_a_lone_imu_jump_is_dropped_and_three_in_a_row_are_taken_as_real(
        link: tuple[FlightCtrl, LoopTransport, FakeClock]) -> None:
    # Fixture: the default step limits (0.25 rad/s, 20 m/s^2 between samples: a corrupted
    # byte of a frame without checksum, not a motion the vehicle can make in 2 ms)
    fc, wire, clock = link
    _push(fc, wire, clock, _imu(0), 0.0)
    # Test: one sample 0.3 rad/s off, then back; then a step that persists
    lone = _push(fc, wire, clock, _imu(1, gz=0.3), 2.0)
    back = _push(fc, wire, clock, _imu(2), 4.0)
    held = [_push(fc, wire, clock, _imu(3 + k, gz=0.3), 6.0 + 2.0 * k) for k in range(4)]
    # Assert: the lone jump dropped; the persisting one dropped three times, then believed
    # (body z is board -z here: the sign of the axes map)
    assert lone is None and back is not None and back.seq == 2
    assert held[:3] == [None, None, None]
    assert held[3] is not None and held[3].gyro_rad_s[2] == pytest.approx(-0.3)
    assert fc.link_stats().implausible == 4


def test_that_a_corrupted_sample_ending_a_run_of_dropped_ones_is_not_taken_as_a_step(
        link: tuple[FlightCtrl, LoopTransport, FakeClock]) -> None:
    # Fixture: a 0.5 % corrupted link once gave this (seed 16 of the corrupted freeze
    # sweep): one sample 0.24 rad/s off (under the 0.25 rad/s limit: taken), so the next good
    # samples jumped 0.26-0.32 rad/s from it and were dropped; after three of them the
    # fourth was taken whatever it read, and that one was corrupted too: 15.3 rad/s
    fc, wire, clock = link
    _push(fc, wire, clock, _imu(0), 0.0)
    # Test
    near = _push(fc, wire, clock, _imu(1, gz=-0.24), 2.0)
    good = [_push(fc, wire, clock, _imu(2 + k, gz=0.02 + 0.03 * k), 4.0 + 2.0 * k)
            for k in range(3)]
    corrupt = _push(fc, wire, clock, _imu(5, gz=15.3), 10.0)
    after = _push(fc, wire, clock, _imu(6, gz=0.09), 12.0)
    # Assert: the good samples are taken at once (near the sample before the corrupted one),
    # the 15.3 rad/s one dropped, no step counted (the loop would re-seed on MoCap for it)
    assert near is not None and all(s is not None for s in good)
    assert corrupt is None and after is not None
    assert after.gyro_rad_s[2] == pytest.approx(-0.09)
    assert fc.link_stats().implausible == 1 and fc.imu_motion_missed == 0


def test_that_a_run_of_dropped_samples_is_a_step_only_if_they_agree(
        link: tuple[FlightCtrl, LoopTransport, FakeClock]) -> None:
    # Fixture: a real step (an impact): three samples 2 rad/s off, near each other
    fc, wire, clock = link
    _push(fc, wire, clock, _imu(0), 0.0)
    # Test: three dropped, then a corrupted one far from them, then the step once more
    run = [_push(fc, wire, clock, _imu(1 + k, gz=2.0 + 0.1 * k), 2.0 + 2.0 * k)
           for k in range(3)]
    corrupt = _push(fc, wire, clock, _imu(4, gz=-9.0), 8.0)
    again = [_push(fc, wire, clock, _imu(5 + k, gz=2.2), 10.0 + 2.0 * k) for k in range(4)]
    # Assert: the corrupted one does not end the run as a step (it starts one of its own,
    # which the step's next sample breaks); the step is taken once three of its samples in a
    # row are dropped again (a fourth near them), counted as motion the IMU missed
    assert run == [None, None, None] and corrupt is None
    assert again[:3] == [None, None, None]
    assert again[3] is not None and again[3].gyro_rad_s[2] == pytest.approx(-2.2)
    assert fc.link_stats().implausible == 7 and fc.imu_motion_missed == 1


def test_that_an_accelerometer_at_the_frames_limit_is_kept_and_counted_as_an_anomaly(
        link: tuple[FlightCtrl, LoopTransport, FakeClock]) -> None:
    # Fixture: a hard touchdown reads more than the I frame's s16 of mm/s^2 can carry
    fc, wire, clock = link
    _push(fc, wire, clock, _imu(0), 0.0)
    before = fc.imu_anomalies
    # Test: an impact ramping to the limit (each step within the 20 m/s^2 a sample may
    # change by), held there, then down to g and resting
    ramp = [(0.0, 0.0, 25.0), (0.0, 0.0, 40.0), (0.0, 0.0, 60.0), (0.0, 0.0, 60.0),
            (0.0, 0.0, 45.0), (0.0, 0.0, 28.0), *[(0.0, 0.0, 9.81)] * 5]
    got = [_push(fc, wire, clock, tk3.encode_frame(mkm.ImuMessage(1 + k, a, (0.0, 0.0, 0.0))
                                                   .encode()), 2.0 + 2.0 * k)
           for k, a in enumerate(ramp)]
    lim = mkm.IMU_ACCEL_WIRE_LIMIT_M_S2
    # Assert: the impact's first sample jumps far beyond the resting IMU's steps: held at the
    # value before (a spike hold), so the next one, 23 m/s^2 from that value, is implausible,
    # and so are the two after it; the fourth at the limit is a real step, taken (the IMU
    # missed motion). The first sample down is held the same way and the way down to g is a
    # step again. The sample taken at the limit is counted saturated and each step as motion
    # missed: the loop knows the IMU missed part of that motion
    assert [None if s is None else abs(s.accel_m_s2[2]) for s in got] == [
        pytest.approx(9.81), None, None, None, pytest.approx(lim), pytest.approx(lim),
        None, None, None, pytest.approx(9.81), pytest.approx(9.81)]
    stats = fc.link_stats()
    assert stats.accel_saturated == 1 and stats.accel_spikes_held == 2
    assert stats.implausible == 6 and fc.imu_motion_missed == 3
    assert fc.imu_anomalies - before == 9


def _accel(seq: int, az: float) -> bytes:
    return tk3.encode_frame(mkm.ImuMessage(seq & 0xFF, (0.0, 0.0, az), (0.0, 0.0, 0.0)).encode())


def _accel_z(fc: FlightCtrl, wire: LoopTransport, clock: FakeClock, az_m_s2: list[float],
             first_seq: int = 0) -> list[float]:
    """Body z of the samples the loop gets for board z readings ``az_m_s2`` (the fixture's
    axes map turns board z to body -z)."""
    got = [_push(fc, wire, clock, _accel(first_seq + k, az), 2.0 * (first_seq + k))
           for k, az in enumerate(az_m_s2)]
    assert all(s is not None for s in got)
    return [-s.accel_m_s2[2] for s in got if s is not None]


def test_that_a_lone_accelerometer_spike_under_the_step_limit_is_held_for_one_sample(
        link: tuple[FlightCtrl, LoopTransport, FakeClock]) -> None:
    # Fixture: a resting IMU (0.05 m/s^2 steps), then a corrupted byte of a frame without
    # checksum: z 6 m/s^2 off for one sample, under the 20 m/s^2 implausible-step limit (a
    # 0.012 m/s kick to an integrated velocity)
    fc, wire, clock = link
    rest = [9.81 + (0.05 if k % 2 else 0.0) for k in range(40)]
    # Test
    got = _accel_z(fc, wire, clock, [*rest, 15.81, 9.86, 9.81])
    # Assert: the spike reads as the value before it, the next sample as itself; held once,
    # an anomaly for the loop, not a receive error (the sample was delivered)
    assert got[40:] == [pytest.approx(9.86), pytest.approx(9.86), pytest.approx(9.81)]
    stats = fc.link_stats()
    assert stats.accel_spikes_held == 1 and stats.implausible == 0
    assert fc.imu_anomalies == 1 and fc.rx_errors == 0


def test_that_a_held_spike_is_not_the_reference_of_the_next_implausible_step_check(
        link: tuple[FlightCtrl, LoopTransport, FakeClock]) -> None:
    # Fixture: a 0.5 % corrupted link once sent this (seed 19, no other fault): z 5.9 m/s^2
    # off (under the 20 m/s^2 implausible-step limit: held), then 25.6 m/s^2 off, 19.7 from
    # the held reading; taken, it kicked the estimate's velocity by 0.15 m/s
    fc, wire, clock = link
    rest = [9.81 + (0.05 if k % 2 else 0.0) for k in range(40)]
    got = _accel_z(fc, wire, clock, rest)
    # Test
    spike = _push(fc, wire, clock, _accel(40, 9.81 - 5.9), 80.0)
    worse = _push(fc, wire, clock, _accel(41, 9.81 - 25.6), 82.0)
    after = _push(fc, wire, clock, _accel(42, 9.81), 84.0)
    # Assert: the first held, the second dropped as implausible (25.6 m/s^2 from the
    # reading before the spike), the next taken
    assert got[-1] == pytest.approx(9.86)
    assert spike is not None and -spike.accel_m_s2[2] == pytest.approx(9.86)
    assert worse is None
    assert after is not None and -after.accel_m_s2[2] == pytest.approx(9.81)
    stats = fc.link_stats()
    assert stats.accel_spikes_held == 1 and stats.implausible == 1


def test_that_a_real_accelerometer_step_is_taken_one_sample_late(
        link: tuple[FlightCtrl, LoopTransport, FakeClock]) -> None:
    # Fixture: a resting IMU, then a step of 6 m/s^2 that stays
    fc, wire, clock = link
    rest = [9.81 + (0.05 if k % 2 else 0.0) for k in range(40)]
    # Test
    got = _accel_z(fc, wire, clock, [*rest, 15.81, 15.81, 15.86, 15.81])
    # Assert: held for its first sample only
    assert got[40:] == [pytest.approx(9.86), pytest.approx(15.81), pytest.approx(15.86),
                        pytest.approx(15.81)]
    assert fc.link_stats().accel_spikes_held == 1


def test_that_the_spike_hold_widens_to_a_vibrating_airframe(
        link: tuple[FlightCtrl, LoopTransport, FakeClock]) -> None:
    # Fixture: vibration at 80 Hz, 4 m/s^2 amplitude, sampled at 500 Hz: steps up to 2.4
    # m/s^2, above the 1 m/s^2 floor. The limit follows the typical step (10 times its
    # average), so only the first of them may be held, never the vibration once learnt
    fc, wire, clock = link
    vib = [9.81 + 4.0 * math.sin(2.0 * math.pi * 80.0 * 0.002 * k) for k in range(600)]
    # Test
    got = _accel_z(fc, wire, clock, vib)
    # Assert: the last 400 samples (0.8 s) untouched; few held while it learnt
    assert got[200:] == [pytest.approx(v, abs=0.001) for v in vib[200:]]
    assert fc.link_stats().accel_spikes_held < 60


def test_that_the_spike_hold_can_be_turned_off() -> None:
    wire = LoopTransport("loop://test", read_timeout_s=0.01)
    clock = FakeClock()
    fc = FlightCtrl(wire, FlightCtrlConfig(imu_axes=ImuAxes(axis=(1, 0, 2), sign=(1, 1, -1)),
                                           accel_spike_factor=0.0), clock=clock)
    fc.start()
    try:
        got = _accel_z(fc, wire, clock, [9.81] * 10 + [15.81, 9.81])
        assert got[10] == pytest.approx(15.81) and fc.link_stats().accel_spikes_held == 0
    finally:
        fc.close()


@settings(max_examples=40, deadline=None)
@given(st.lists(st.floats(-30.0, 30.0), min_size=2, max_size=30))
def test_that_the_spike_hold_gives_a_reading_or_the_one_before(az_m_s2: list[float]) -> None:
    # Property: whatever the readings (each within the full scale, steps within the
    # implausible-step limit or not), every delivered value is the sample's own reading or
    # the value delivered before it, never two held in a row
    wire = LoopTransport("loop://test", read_timeout_s=0.01)
    clock = FakeClock()
    fc = FlightCtrl(wire, FlightCtrlConfig(imu_axes=ImuAxes(axis=(1, 0, 2), sign=(1, 1, -1))),
                    clock=clock)
    fc.start()
    try:
        out: list[tuple[float, float]] = []   # (reading, delivered)
        for k, az in enumerate(az_m_s2):
            s = _push(fc, wire, clock, _accel(k, az), 2.0 * k)
            if s is not None:
                # the reading as the wire carries it (mm/s^2, rounded half to even: not
                # round(az, 3), which reads 0.0005 as 0.001 where the wire has 0)
                out.append((round(az * 1e3) * 1e-3, -s.accel_m_s2[2]))
        for (_, before), (own, now), in itertools.pairwise(out):
            assert now == pytest.approx(own, abs=1e-9) or now == before
        held = [now != pytest.approx(own, abs=1e-9) for own, now in out]
        assert not any(a and b for a, b in itertools.pairwise(held))
        assert fc.link_stats().accel_spikes_held == sum(held)
    finally:
        fc.close()


def test_that_the_imu_axes_map_board_to_body(
        link: tuple[FlightCtrl, LoopTransport, FakeClock]) -> None:
    fc, wire, clock = link
    frame = tk3.encode_frame(mkm.ImuMessage(0, (1.0, 2.0, 3.0), (0.1, 0.2, 0.3)).encode())
    s = _push(fc, wire, clock, frame, 0.0)
    assert s is not None
    assert s.accel_m_s2 == (2.0, 1.0, -3.0)
    assert s.gyro_rad_s == (0.2, 0.1, -0.3)


def test_that_the_loop_gets_the_newest_sample_and_stale_ones_are_counted(
        link: tuple[FlightCtrl, LoopTransport, FakeClock]) -> None:
    fc, wire, clock = link
    _push(fc, wire, clock, _imu(0), 0.0)
    wire.write(b"".join(_imu(i) for i in range(1, 6)))  # the loop was busy for 5 samples
    newest = None
    for _ in range(100):
        s = fc.wait_next(0.05)
        newest = s or newest
        if newest is not None and newest.seq == 5:
            break
    assert newest is not None and newest.seq == 5
    assert fc.wait_next(0.01) is None  # nothing is queued behind it
    assert fc.link_stats().imu_overwritten >= 1


def test_that_motor_frames_become_typed_states(
        link: tuple[FlightCtrl, LoopTransport, FakeClock]) -> None:
    fc, wire, _ = link
    frames = [mkm.MotorMessage(0, 1, False, True, False, 5000, 400, 1.5),
              mkm.MotorMessage(0, 2, True, False, False, 0, 0, 0.0),
              mkm.MotorMessage(0, 3, False, False, True, 32767, 100, 0.3)]
    wire.write(b"".join(tk3.encode_frame(f.encode()) for f in frames))
    snap = None
    for _ in range(100):
        snap = fc.wait_motor_update(0.05)
        if snap is not None and snap.motors[2] is not None:
            break
    assert snap is not None
    m1, m2, m3 = snap.motors[:3]
    assert m1 is not None and m1.state == MotorState.SPINNING and m1.speed_hz == 100.0
    assert m1.current_a == 1.5
    assert m2 is not None and m2.state == MotorState.EMERGENCY
    assert m3 is not None and m3.state == MotorState.STARTING
    assert snap.any_emergency and not snap.all_spinning


def test_that_spin_rates_are_sent_as_one_w_frame_with_the_configured_directions() -> None:
    wire = LoopTransport("loop://w")
    fc = FlightCtrl(wire, FlightCtrlConfig(spin_directions=(1, -1, 1, -1, 1, -1)))
    fc.send_rotor_speeds_hz([100.0, 100.0, 80.0, 80.0, 60.0, 60.0])
    assert wire.read(100) == bytes.fromhex("5e 77 13 88 ec 78 18 6a e7 96 20 8d df 73 24")
    with pytest.raises(ValueError, match="expected 6 spin rates"):
        fc.send_rotor_speeds_hz([50.0] * 5)
    with pytest.raises(ValueError):
        fc.send_rotor_speeds_hz([50.0] * 5 + [float("nan")])
    fc.close()


@settings(max_examples=60, deadline=None)
@given(st.binary(max_size=300))
def test_that_random_bytes_never_stop_the_reader_nor_hide_the_next_valid_samples(
        noise: bytes) -> None:
    wire = LoopTransport("loop://noise", read_timeout_s=0.01)
    fc = FlightCtrl(wire).start()
    try:
        marker = (0.123, -0.456, 0.789)
        frames = b"".join(tk3.encode_frame(mkm.ImuMessage(s, (0.0, 0.0, 9.81), marker).encode())
                          for s in (10, 11, 12))
        wire.write(noise)
        wire.write(frames)
        seen = None
        for _ in range(400):
            s = fc.wait_next(0.01)
            if s is not None and s.gyro_rad_s == marker:
                seen = s
                break
        assert seen is not None, fc.link_stats()
        assert seen.seq % 256 in (10, 11, 12)
    finally:
        fc.close()


def test_that_health_reports_stale_and_low_rate_imu_streams() -> None:
    # Fixture: on a loopback the '?' comes back as an empty identity, accepted here
    wire = LoopTransport("loop://health", read_timeout_s=0.01)
    clock = FakeClock()
    fc = FlightCtrl(wire, FlightCtrlConfig(firmware_ids=("",), identify_attempts=1),
                    clock=clock)
    try:
        fc.connect()
        while wire.read(4096):  # drop the echoed rate commands
            pass
        # Test + Assert: 500 Hz for 0.6 s is healthy
        for i in range(300):
            _push(fc, wire, clock, _imu(i), 2.0 * i)
        assert fc.health() == LinkHealth.OK
        assert fc.link_stats().imu.measured_rate_hz == pytest.approx(500.0, rel=0.01)
        clock.t_ns += 20 * MS  # 20 ms without a sample
        assert fc.health() == LinkHealth.STALE
        # 300 Hz (one sample in three lost, 60 % of the set rate) is too slow
        t0 = 598.0 + 20.0
        for k in range(1, 200):
            _push(fc, wire, clock, _imu(299 + 3 * k), t0 + 6.0 * k)
        stats = fc.link_stats()
        assert stats.health == LinkHealth.RATE_LOW
        assert stats.imu.missing >= 2 * 198
    finally:
        fc.close()


def test_that_a_frame_with_its_start_byte_corrupted_counts_as_a_receive_error(
        link: tuple[FlightCtrl, LoopTransport, FakeClock]) -> None:
    # Fixture: one good sample read, the error counter as the loop sees it
    fc, wire, clock = link
    assert _push(fc, wire, clock, _imu(0), 0.0) is not None
    before = fc.rx_errors
    # Test: the next frame arrives with its '^' changed: its bytes are outside any frame
    clock.t_ns = 1_000 * MS + 2 * MS
    wire.write(b"\x00" + _imu(1)[1:])
    for _ in range(200):
        if fc.rx_errors != before:
            break
        fc.wait_next(0.005)
    # Assert: a receive error (a lockstep loop then knows the sample is lost, at once), and
    # the next good frame still reads
    assert fc.rx_errors > before
    sample = _push(fc, wire, clock, _imu(2), 4.0)
    assert sample is not None and sample.seq == 2


def _window_stats_by_brute_force(arrivals: list[int], first_ns: int | None, window_ns: int,
                                 now_ns: int) -> tuple[float, float, float]:
    """(rate, age, largest interval) from every arrival of the window, one pass each."""
    arr = [t for t in arrivals[-8192:] if t >= now_ns - window_ns]
    span = window_ns if first_ns is None else min(window_ns, max(now_ns - first_ns, 1))
    gaps = [b - a for a, b in itertools.pairwise(arr)]
    return (len(arr) * 1e9 / span if arr else 0.0,
            (now_ns - arr[-1]) / 1e9 if arr else float("inf"),
            max(gaps) / 1e9 if gaps else float("inf"))


@settings(max_examples=300)
@given(st.lists(st.tuples(st.integers(0, 50_000_000), st.booleans()), max_size=300),
       st.integers(1_000_000, 200_000_000))
def test_that_the_rate_meter_keeps_the_largest_interval_of_its_window(
        steps: list[tuple[int, bool]], window_ns: int) -> None:
    # Fixture: arrivals at random intervals (repeats included), stats asked now and then
    from drivers.mikrokopter.device import _RateMeter
    meter, seen, t, now = _RateMeter(window_ns), [], 0, 0
    for dt, ask in steps:
        t += dt
        meter.add(t)
        seen.append(t)
        if ask:
            # Test (the host clock never runs back)
            now = max(now, t + dt // 2)
            got = meter.stats("imu", 500.0, now)
            # Assert: the same figures as a pass over the whole window
            rate, age, largest = _window_stats_by_brute_force(seen, seen[0], window_ns, now)
            assert (got.measured_rate_hz, got.age_s, got.max_interval_s) == \
                (pytest.approx(rate), pytest.approx(age), pytest.approx(largest))


@settings(max_examples=300, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 60), st.sampled_from(["lost", "ahead", "any"]),
                          st.integers(0, 255)), max_size=12),
       st.integers(0, 255))
def test_that_lost_samples_and_corrupted_sequence_bytes_never_move_the_imu_clock_far(
        faults: list[tuple[int, str, int]], first_seq: int) -> None:
    # Property: a 500 Hz stream whose samples are lost or have their sequence byte corrupted
    # (up to 16 ahead, or into any value), each fault at least two samples after the last:
    # every sample the time base accepts gets a counter at most 16 ahead of its true one (a
    # corrupted byte may pass as a gap of lost samples) and never behind, in increasing
    # order. A resync on the real samples after a byte corrupted ahead once moved it a whole
    # wrap (256) ahead.
    period_ns = 2_000_000
    tb = _ImuTimeBase(period_ns)
    plan: dict[int, tuple[str, int]] = {}
    k = 3                                    # the stream starts clean
    for skip, kind, value in faults:
        k += 2 + skip
        plan[k] = (kind, value)
    last = None
    arrival_ns = 0
    for k in range(max(plan, default=0) + 40):
        kind, value = plan.get(k, ("ok", 0))
        if kind == "lost":
            continue
        # "ahead": read up to 16 ahead (a low bit flipped), after a host stall as long (so
        # that it passes for that many lost samples), the samples after it in a burst
        ahead = value % 17 if kind == "ahead" else 0
        seq = (first_seq + k + ahead) & 0xFF if kind != "any" else value
        arrival_ns = max(arrival_ns, 1_000_000_000 + (k + ahead) * period_ns)
        got = tb.accept(seq, arrival_ns)
        if got is None:
            continue
        count = got[0] - first_seq
        assert 0 <= count - k <= 16, (k, seq, count)
        assert last is None or count > last
        last = count
    assert last is not None and last == k   # back in step by the end

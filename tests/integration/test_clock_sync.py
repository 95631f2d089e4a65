"""One time base, end to end on real ptys and UDP sockets, in real time: an emulated board
whose sample clock runs 1.2 % slow (494 Hz for a set 500 Hz) and a NatNet server whose clock
is 3 s ahead of ours, read by the real drivers for 20 s.

Asserted on what the drivers compute, against what the emulators know (no wall-clock timing
asserts): no sample is stamped later than its arrival (no negative age), the measured board
rate and drift, the server's offset, and every sample time and MoCap latency within 1 ms of
the emulators' truth once the clock sync has its first rate (after 2 s of samples). The
span is ``FASTHEX_CLOCK_SYNC_S`` (default 20: two quiet runs here learnt the drift to 1.2 and
1.8 ppm, error bars 1.6 and 1.8 ppm, MoCap drift 0.0 and +0.1 ppm, every sample time within
0.29 ms; 30 s once gave 1.4 and 2.2 ppm: a longer run adds nothing the 20 ppm bounds can see,
and the test runs alone, the whole suite waiting on it).
"""

from __future__ import annotations

import math
import os
import re
import threading
import time
from pathlib import Path

import pytest
from flight_support import SHORT_MISSION

from controller.missions import Mission
from drivers.mikrokopter import FlightCtrl
from drivers.mocap.natnet_client import NatNetClient, NatNetConfig
from drivers.mocap.vrpn_client import VrpnClient, VrpnConfig
from groundstation.configs import load_mission, load_vehicle
from groundstation.loop import DRIFT_SHOWN_SIGMA_PPM
from groundstation.session import FlightSession
from groundstation.session_config import load_session
from sim_backend.emulators.flightctrl import EmulatedFlightCtrl, FlightCtrlEmulatorConfig
from sim_backend.emulators.natnet import NatNetEmulatorConfig, NatNetServer
from sim_backend.emulators.vrpn import VrpnEmulatorConfig, VrpnServer
from sim_backend.vehicle import BenchVehicle

BOARD_PPM = -12_000.0  # the board's crystal 1.2 % slow
MOCAP_OFFSET_S = 3.0
MOCAP_LATENCY_S = 0.004  # mid-exposure -> transmit, as the server stamps it
RUN_S = float(os.environ.get("FASTHEX_CLOCK_SYNC_S", "20"))
SETTLE_S = 2.0


def test_slow_board_and_offset_mocap_server_over_twenty_seconds() -> None:
    vehicle = BenchVehicle(seed=3)
    emu = EmulatedFlightCtrl(vehicle, lock=threading.Lock(), config=FlightCtrlEmulatorConfig(
        record_truth=True, board_clock_error_ppm=BOARD_PPM))
    server = NatNetServer(vehicle, NatNetEmulatorConfig(
        command_port=0, latency_s=MOCAP_LATENCY_S, server_clock_offset_s=MOCAP_OFFSET_S),
        lock=threading.Lock())
    emu.start()
    server.start(realtime=True)
    fc = FlightCtrl.open(f"pty://{emu.path}")
    client = NatNetClient(NatNetConfig(command_port=server.command_port))
    imu_seen = imu_checked = poses_checked = 0
    worst_imu_err_ns = worst_lat_err_ns = 0
    negative_ages = 0
    slips_seen = excluded = 0
    quiet_since_ns = 0
    try:
        fc.connect()
        client.start()
        first_ns: int | None = None
        last_frame = -1
        while True:
            s = fc.wait_next(10.0)  # generous: a loaded host may starve the emulator
            assert s is not None, "the IMU stream stopped"
            now_ns = time.monotonic_ns()
            imu_seen += 1
            negative_ages += s.t_ns > s.arrival_t_ns or s.t_ns > now_ns
            first_ns = first_ns or s.arrival_t_ns
            settled = s.arrival_t_ns - first_ns > SETTLE_S * 1e9
            if imu_seen % 50 == 0:
                slips = emu.stats().stream_slips
                if slips != slips_seen:
                    # the emulator fell behind and skipped sample periods: its counter then no
                    # longer counts its clock (a real board's does), so no truth for a second
                    slips_seen, quiet_since_ns = slips, s.arrival_t_ns
                    excluded += 1
            if settled and imu_seen % 50 == 0 and s.arrival_t_ns - quiet_since_ns > 1e9:
                # the emulator's own record of when it sent the sample (its clock -> ours)
                # (seq counts every sample the board sent, as the driver's unwrapped counter)
                truth = emu.sent_imu[s.seq] if s.seq < len(emu.sent_imu) else None
                if truth is not None and truth.seq == s.seq:
                    err = s.t_ns - _emu_host_ns(emu, truth.t_ns)
                    worst_imu_err_ns = max(worst_imu_err_ns, abs(err))
                    imu_checked += 1
            with client._cond:  # the newest frame and its times, as the client saw them
                frame, times = client._last_frame, client._last_frame_times
            if frame is not None and frame.frame_number != last_frame:
                last_frame = frame.frame_number
                rx_ns, t_ns, latency_s = times
                negative_ages += t_ns > rx_ns
                if settled:
                    # the server's timestamp field is its capture time on the emulator's
                    # clock (the 3 s offset is in the high-resolution stamps only)
                    true_capture_ns = round((server._t0_wall + frame.timestamp_s) * 1e9)
                    true_latency_ns = rx_ns - true_capture_ns
                    worst_lat_err_ns = max(worst_lat_err_ns,
                                           abs(round(latency_s * 1e9) - true_latency_ns))
                    poses_checked += 1
            if s.arrival_t_ns - first_ns > RUN_S * 1e9:
                break
        stats = fc.link_stats()
        mstats = client.stats()
        print(f"steps {fc._timebase.sync.steps}, resyncs {stats.resyncs}, seq rejected "
              f"{stats.seq_rejected}, missing {stats.imu.missing}, emulator {emu.stats()}")
    finally:
        fc.close()
        client.close()
        server.close()
        emu.stop()
    clk = stats.imu_clock
    print(f"board: {clk.rate_hz:.2f} Hz, offset {clk.offset_s:+.6f} s, drift "
          f"{clk.drift_ppm:+.1f} +- {clk.drift_sigma_ppm:.1f} ppm; IMU time error max "
          f"{worst_imu_err_ns / 1e3:.0f} us over "
          f"{imu_checked} checks; MoCap offset {mstats.clock_offset_s:+.6f} s, drift "
          f"{mstats.clock_drift_ppm:+.2f} ppm, latency error max {worst_lat_err_ns / 1e3:.0f} "
          f"us over {poses_checked} frames; {excluded} spans after emulator slips not checked")
    assert negative_ages == 0
    assert clk.known
    # within its own error bar (a loaded host scatters the block minima: 2-15 ppm seen)
    assert abs(clk.drift_ppm - BOARD_PPM) <= max(20.0, 3.0 * clk.drift_sigma_ppm)
    assert clk.rate_hz == pytest.approx(500.0 * (1 + BOARD_PPM * 1e-6), abs=0.05)
    assert imu_checked > RUN_S * 5 and worst_imu_err_ns < 1_000_000
    # the server's clock: 3 s ahead of the emulator's, which started with the test
    assert mstats.clock_offset_s == pytest.approx(server._t0_wall - MOCAP_OFFSET_S, abs=0.005)
    assert math.isfinite(mstats.clock_drift_ppm) and abs(mstats.clock_drift_ppm) < 20.0
    assert poses_checked > RUN_S * 50 and worst_lat_err_ns < 1_000_000


def _emu_host_ns(emu: EmulatedFlightCtrl, sim_ns: int) -> int:
    """Host (monotonic) time of the realtime emulator's simulated instant."""
    return round(emu._wall0 * 1e9) + sim_ns - emu._sim0_ns



SESSION = """\
schema: fasthex.session
version: 1
name: clock-errors
vehicle: fasthex
mission: short-hover.yaml
backend:
  kind: emulated
  clock: realtime
  seed: 3
  board_clock_ppm: -12000
  mocap_clock_offset_s: 3.0
safety:
  geofence_min_m: [-2.0, -2.0, -0.5]
  geofence_max_m: [2.0, 2.0, 2.5]
  mocap_timeout_s: 1.0
  imu_timeout_s: 0.5
telemetry:
  rerun: "off"
"""


def test_the_preflight_reports_the_board_and_mocap_clocks(tmp_path: Path) -> None:
    """A session on the emulated backend in real time, with the two clock errors as session
    keys: the preflight's IMU and MoCap lines carry the measured rate, offset and drift."""
    (tmp_path / "short-hover.yaml").write_text(SHORT_MISSION)
    (tmp_path / "clock.yaml").write_text(SESSION)
    session = FlightSession(load_session(tmp_path / "clock.yaml"), load_vehicle("fasthex"),
                            Mission(load_mission(tmp_path / "short-hover.yaml")),
                            record_path=tmp_path / "clock.fhr", echo_events=False,
                            # the preflight is all it needs: it passes at its first check
                            # (1.0 s); the land request at 1.9 s disarms before the take-off
                            scripted_requests=((1.9, "land"),))
    outcome = session.run()
    checks = {name: (ok, value) for name, ok, value in outcome.preflight}
    imu_ok, imu = checks["flight-ctrl streaming IMU at 80-125 % of the set rate"]
    mocap_ok, mocap = checks["MoCap sees the body at >= 80 % of its rate"]
    print(imu, "|", mocap)
    assert imu_ok and mocap_ok
    board = re.search(r"board clock ([0-9.]+) Hz, offset ([-+0-9.]+) s, (?:drift ([-+0-9]+) "
                      r"(?:\+- ([0-9]+) ppm|ppm \(first estimate\))|drift not measured yet "
                      r"\(\+- ([0-9]+) ppm\))", imu)
    assert board is not None, imu
    # After ~1 s of preflight the estimate stands on a few host-stamped blocks; on a loaded host
    # their minima scatter (CI runs read 495 and 496 Hz for 494, one with a 76620 ppm error
    # bar). The preflight must report the truth within the error bar it prints (3 sigma), and
    # no looser than 0.2 % where the bar is tighter; the 20 s test holds 20 ppm.
    # an error bar above DRIFT_SHOWN_SIGMA_PPM prints no value ("not measured yet")
    if board.group(5) is not None:
        assert float(board.group(5)) > DRIFT_SHOWN_SIGMA_PPM, imu
    else:
        rate_hz, drift_ppm = float(board.group(1)), float(board.group(3))
        bar_ppm = max(2000.0, 3.0 * float(board.group(4))) if board.group(4) else 2000.0
        assert abs(drift_ppm - BOARD_PPM) <= bar_ppm, imu
        # the printed rate is the printed drift applied to the set 500 Hz (to the 0.1 Hz)
        assert rate_hz == pytest.approx(500.0 * (1 + drift_ppm * 1e-6), abs=0.051)
    server = re.search(r"server clock offset ([-+0-9.]+) s, (?:drift ([-+0-9]+) "
                       r"(?:\+- ([0-9]+) ppm|ppm \(first estimate\))|drift not measured yet "
                       r"\(\+- ([0-9]+) ppm\))", mocap)
    assert server is not None, mocap
    if server.group(4) is not None:
        assert float(server.group(4)) > DRIFT_SHOWN_SIGMA_PPM, mocap
    # the server's clock has no rate error. After ~1 s the estimate stands on a few blocks, and
    # the MoCap stream's first frames arrive late (start-up), which reads as a fast clock: seen
    # here +7000..+17000 ppm with error bars of 2400..6400 ppm. The preflight must report it
    # with that error bar; the 20 s test holds the tight bounds (20 ppm).
    if server.group(3) is not None:  # else reported as a first estimate, without a bar
        assert abs(float(server.group(2))) <= 1000.0 + 3.0 * float(server.group(3))
    age = re.search(r"newest pose (-?[0-9]+) ms old", mocap)
    assert age is not None and int(age.group(1)) >= 0
    # The loop's first sample is a fresh one: nothing holds the interpreter once the IMU
    # streams (a full GC collection and the controller's warm-up after it used to: the
    # driver's thread took no sample for 73-194 ms, the summary's "longest IMU gap" at 0.00 s)
    counters = outcome.result.counters
    assert counters["imu_gap_max_at_ms"] > 0 or counters["imu_gap_max_us"] < 30_000, counters


def test_vrpn_server_clock_offset_and_drift_are_learnt() -> None:
    """VRPN stamps are absolute: a server clock 3 s ahead and 200 ppm fast, over 10 s (the
    emulator's wall clock is ours, so the truth is known): no sample after its arrival, the
    offset and drift learnt, latency = the configured smallest one plus what is above it."""
    cfg = VrpnEmulatorConfig(port=0, rate_hz=200.0, latency_s=0.004,
                             server_clock_offset_s=MOCAP_OFFSET_S, server_clock_drift_ppm=200.0)
    server = VrpnServer(BenchVehicle(seed=3), cfg, wall_clock=lambda: time.monotonic_ns() * 1e-9)
    late = n = 0
    latencies_s: list[float] = []
    with server, VrpnClient(VrpnConfig(port=server.port, latency_s=0.004)) as client:
        t_end = time.monotonic() + 10.0
        last = None
        while time.monotonic() < t_end:
            assert client.wait_frames(1, 2.0)
            s = client.latest()
            if s is None or s is last:
                continue
            last = s
            n += 1
            late += s.t_ns > s.rx_t_ns
            latencies_s.append(s.latency_s)
        stats = client.stats()
    print(f"VRPN: {n} reports, offset {stats.clock_offset_s:+.6f} s, drift "
          f"{stats.clock_drift_ppm:+.1f} +- {stats.clock_drift_sigma_ppm:.1f} ppm, latency "
          f"median {sorted(latencies_s)[len(latencies_s) // 2] * 1e3:.3f} ms")
    assert n > 1000 and late == 0
    assert min(latencies_s) >= 0.004
    latencies_s.sort()
    assert latencies_s[len(latencies_s) // 2] < 0.005  # the median: within 1 ms of the 4 ms
    # host - server at the end: -3 s, minus the drift accumulated since the server started
    # (200 ppm of ~10 s = 2 ms), plus the smallest delay (4 ms and the transport)
    assert stats.clock_offset_s == pytest.approx(-MOCAP_OFFSET_S - 0.002 + 0.004, abs=0.002)
    assert stats.clock_drift_ppm == pytest.approx(200.0, abs=30.0)

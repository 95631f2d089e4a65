"""The Flight-Ctrl on the bench: identity, the IMU stream's rate and values, motor spin-up and
the watchdog stop (propellers off), and the board left quiet on close."""

from __future__ import annotations

import math
import time

import pytest

from drivers.mikrokopter.device import FlightCtrl, FlightCtrlConfig, MotorState, probe

pytestmark = pytest.mark.hil

IMU_RATE_HZ = 500.0
G_M_S2 = 9.81
WATCHDOG_S = 0.25
"""The BL-Ctrl's command timeout (the emulator's; a real board's is of this order)."""


def test_that_the_board_identifies_as_tk3_and_can_fly(flight_ctrl_uri: str) -> None:
    ident = probe(flight_ctrl_uri)
    assert ident.protocol == "tk3"
    assert ident.accepted, f"firmware {ident.firmware_id!r} is not an accepted tk3 id"


def test_that_the_imu_streams_at_the_rate_asked_with_valid_samples(
        flight_ctrl_uri: str) -> None:
    # Fixture
    with FlightCtrl.open(flight_ctrl_uri, FlightCtrlConfig(imu_rate_hz=IMU_RATE_HZ)) as fc:
        fc.connect()
        before = fc.link_stats()
        samples = []
        t0 = time.monotonic()
        while time.monotonic() - t0 < 2.0:  # 2 s of samples, ~1000
            s = fc.wait_next(0.1)
            if s is not None:
                samples.append(s)
        stats = fc.link_stats()
        elapsed_s = time.monotonic() - t0
        # one more take settles the overwritten count of what arrived up to ``stats``
        last = fc.wait_next(0.0)
        taken = len(samples) + (last is not None)
        overwritten = fc.link_stats().imu_overwritten - before.imu_overwritten
    # Assert: the board streamed at the rate asked, within what the link check tolerates
    # (80 %). Counted where the driver decodes the frames, not where this thread took them: on a
    # loaded host the test thread is late and the mailbox keeps only the newest sample.
    # The board's rate over the whole 2 s (the samples decoded over the time between the two
    # stats calls): within 5 %. The driver's own estimate counts host arrivals over its 0.5 s
    # window, so a host stall that straddles the window's start (samples queued, then read at
    # once) shows more than the board sent (534 Hz seen on a loaded CI host, 27 ms gap): it is
    # held to the limits the link check and the preflight apply (80 %, 125 %).
    received = stats.imu.received - before.imu.received
    assert received == pytest.approx(IMU_RATE_HZ * elapsed_s, rel=0.05)
    assert 0.8 * IMU_RATE_HZ <= stats.imu.measured_rate_hz <= 1.25 * IMU_RATE_HZ
    # nothing lost: every sample decoded was taken or counted overwritten (more may have
    # arrived after ``stats``, so the count can only exceed what was received)
    assert taken + overwritten >= received
    assert len(samples) >= 100  # enough to check the values below
    for s in samples:
        a, w = s.accel_m_s2, s.gyro_rad_s
        assert all(math.isfinite(v) for v in (*a, *w))
        # at rest: the accelerometer reads g (a tilted bench too), the gyro reads little
        assert math.sqrt(a[0] ** 2 + a[1] ** 2 + a[2] ** 2) == pytest.approx(G_M_S2, abs=1.5)
        assert max(abs(v) for v in w) < 0.2
    assert stats.implausible == 0 and stats.malformed == 0


@pytest.mark.usefixtures("props_off")
def test_that_the_motors_spin_up_and_the_watchdog_stops_them(flight_ctrl_uri: str) -> None:
    # Fixture
    with FlightCtrl.open(flight_ctrl_uri, FlightCtrlConfig(imu_rate_hz=IMU_RATE_HZ,
                                                           motor_rate_hz=50.0)) as fc:
        fc.connect()
        # Test: the loop's start sequence (g, then w at idle) until every motor spins
        started = fc.start_motors(timeout_s=10.0, idle_spin_hz=20.0)
        for _ in range(250):  # 0.5 s more at idle, as the loop's spin-up does: speeds settle
            fc.wait_next(0.05)
            fc.send_rotor_speeds_hz([20.0] * 6)
        speeds = fc.motors().speeds_hz
        # then silence: no w for ten watchdog periods
        t_quiet = time.monotonic()
        stopped = None
        while time.monotonic() - t_quiet < 10 * WATCHDOG_S:
            snap = fc.wait_motor_update(0.1)
            if snap is not None and not any(
                    m is not None and m.state is MotorState.SPINNING for m in snap.motors):
                stopped = time.monotonic() - t_quiet
                break
    # Assert: all six spun at the idle speed, and stopped by themselves within the watchdog
    assert started.all_spinning
    assert speeds == pytest.approx((20.0,) * 6, abs=2.0)
    assert stopped is not None, "the motors kept spinning without commands"
    assert stopped < 4 * WATCHDOG_S


def test_that_close_leaves_the_board_quiet(flight_ctrl_uri: str) -> None:
    # Fixture: a client that streams, then closes
    with FlightCtrl.open(flight_ctrl_uri, FlightCtrlConfig(imu_rate_hz=IMU_RATE_HZ)) as fc:
        fc.connect()
        assert fc.wait_next(1.0) is not None
    # Test: a new client that asks for nothing
    with FlightCtrl.open(flight_ctrl_uri) as quiet:
        quiet.start()
        sample = quiet.wait_next(0.5)  # listening for a stream that should not come
        stats = quiet.link_stats()
    # Assert: no IMU or motor frame arrived (the close switched every stream off)
    assert sample is None
    assert stats.imu.received == 0 and stats.motor.received == 0

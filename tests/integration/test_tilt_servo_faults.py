"""Faults between TiltServo and the emulated MX-28T: no reply, corrupt reply, late reply and
an unplugged port. The driver reports them, keeps the last tilt, never blocks the caller and
comes back by itself."""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Literal

import pytest

from drivers.dynamixel import (
    Reg,
    ServoCommError,
    ServoHealth,
    ServoState,
    TiltServo,
    TiltServoConfig,
)
from sim_backend.emulators.dynamixel_p1 import EmulatedMX28, Fault
from sim_backend.vehicle import BenchVehicle

DEG = math.pi / 180.0
WAIT_S = 20.0


@pytest.fixture
def rig(tmp_path: Path) -> Iterator[tuple[EmulatedMX28, TiltServo]]:
    vehicle = BenchVehicle(max_tilt_rate_rad_s=100 * DEG)
    emu = EmulatedMX28(vehicle, lock=threading.Lock(), link_path=tmp_path / "tilt-servo",
                       drive_clock=True)
    with emu, TiltServo(TiltServoConfig(uri=f"pty://{emu.path}?id=1")) as servo:
        # Move to a tilt that is not zero, so "kept the last tilt" means something.
        servo.wait_for(lambda s: s.ok, WAIT_S)
        servo.set_tilt(5 * DEG)
        servo.wait_for(lambda s: abs(s.tilt_rad - 5 * DEG) < 0.01 * DEG and not s.moving,
                       WAIT_S)
        yield emu, servo


def assert_kept_last_tilt(state: ServoState) -> None:
    assert state.tilt_rad == pytest.approx(5 * DEG, abs=0.01 * DEG)


def test_that_a_silent_servo_is_no_reply_keeps_the_last_tilt_and_recovers(
        rig: tuple[EmulatedMX28, TiltServo]) -> None:
    emu, servo = rig
    emu.set_fault(Fault.SILENT)
    state = servo.wait_for(lambda s: s.health is ServoHealth.NO_REPLY, WAIT_S)
    assert_kept_last_tilt(state)
    assert state.timeouts >= 1
    for _ in range(1000):
        servo.set_tilt(6 * DEG)  # a mailbox write: returns whatever the servo does
    emu.set_fault(Fault.NONE)
    state = servo.wait_for(lambda s: s.ok and abs(s.tilt_rad - 6 * DEG) < 0.01 * DEG, WAIT_S)
    assert state.seq > 0


def test_that_a_garbled_reply_is_corrupt_reply_and_recovers(
        rig: tuple[EmulatedMX28, TiltServo]) -> None:
    emu, servo = rig
    emu.set_fault(Fault.GARBLE)
    state = servo.wait_for(lambda s: s.health is ServoHealth.CORRUPT_REPLY, WAIT_S)
    assert_kept_last_tilt(state)
    assert state.corrupt_replies >= 1
    emu.set_fault(Fault.NONE)
    servo.wait_for(lambda s: s.ok, WAIT_S)


def test_that_late_replies_are_faults_and_never_answer_the_next_request(
        rig: tuple[EmulatedMX28, TiltServo]) -> None:
    emu, servo = rig
    # Every reply 80 ms late: after the SDK's 34 ms timeout, before the driver's 100 ms resync.
    emu.set_fault(Fault.LATE, late_s=0.08)
    state = servo.wait_for(lambda s: s.health is ServoHealth.NO_REPLY, WAIT_S)
    assert_kept_last_tilt(state)
    servo.wait_for(lambda s: s.timeouts >= 5, WAIT_S)
    emu.set_fault(Fault.NONE)
    state = servo.wait_for(lambda s: s.ok, WAIT_S)
    # Test: a stale late reply would be taken as the next answer; every reading after the
    # recovery must be the servo's true state.
    for _ in range(20):
        last_seq = state.seq
        state = servo.wait_for(lambda s, n=last_seq: s.seq > n, WAIT_S)
        assert state.servo_position_steps == emu.register(Reg.PRESENT_POSITION)
        assert state.voltage_v == pytest.approx(12.0) and state.temperature_c == 25.0


def test_that_an_unplugged_port_is_disconnected_and_reconnects_when_it_comes_back(
        rig: tuple[EmulatedMX28, TiltServo]) -> None:
    emu, servo = rig
    emu.unplug()
    state = servo.wait_for(lambda s: s.health is ServoHealth.DISCONNECTED, WAIT_S)
    assert_kept_last_tilt(state)
    with pytest.raises(ServoCommError, match="not connected"):
        servo.home(at_tilt_rad=0.0, timeout_s=WAIT_S)
    servo.set_tilt(7 * DEG)
    emu.replug()
    state = servo.wait_for(lambda s: s.ok and abs(s.tilt_rad - 7 * DEG) < 0.01 * DEG, WAIT_S)
    assert state.reconnects == 2
    assert servo.probe(timeout_s=WAIT_S).is_mx28_p1


def test_that_a_measurement_older_than_100_ms_is_stale_whatever_the_worker_said(
        rig: tuple[EmulatedMX28, TiltServo]) -> None:
    _, servo = rig
    state = servo.latest()
    assert servo.latest(now_s=state.t_s + 0.05).health is ServoHealth.OK
    stale = servo.latest(now_s=state.t_s + 0.15)
    assert stale.health is ServoHealth.STALE
    assert stale.age_s == pytest.approx(0.15)
    assert_kept_last_tilt(stale)


def test_that_a_wrong_baud_in_the_uri_is_no_reply_not_a_crash(tmp_path: Path) -> None:
    vehicle = BenchVehicle()
    with EmulatedMX28(vehicle, lock=threading.Lock(), link_path=tmp_path / "servo",
                      drive_clock=True) as emu, \
            TiltServo(TiltServoConfig(uri=f"serial://{emu.path}?baud=57600&id=1")) as servo:
        state = servo.wait_for(lambda s: s.health is ServoHealth.NO_REPLY, WAIT_S)
        assert math.isnan(state.tilt_rad) and state.timeouts >= 1


def test_that_a_power_cycle_during_a_silence_is_caught_by_the_led_marker(
        rig: tuple[EmulatedMX28, TiltServo]) -> None:
    emu, servo = rig
    assert emu.register(Reg.LED) == 1
    emu.set_fault(Fault.SILENT)
    servo.wait_for(lambda s: s.health is ServoHealth.NO_REPLY, WAIT_S)
    emu.power_cycle()  # at 5 deg = 1138 steps: no jump in the turn count to see
    emu.set_fault(Fault.NONE)
    state = servo.wait_for(lambda s: s.health is ServoHealth.HOMING_REQUIRED, WAIT_S)
    assert not state.homed
    servo.wait_for(lambda s: emu.register(Reg.TORQUE_ENABLE) == 1, WAIT_S)  # holding again


def _cycle_or_error(servo: TiltServo) -> ServoState | ServoCommError:
    try:
        return servo.sync_cycle(WAIT_S)
    except ServoCommError as exc:
        return exc


def _first_cycle(servo: TiltServo) -> ServoState:
    """The first cycle on request: "not connected" until the servo is configured (the servo
    process has started its SDK, or the inline worker has connected)."""
    deadline = time.monotonic() + WAIT_S
    first = _cycle_or_error(servo)
    while not isinstance(first, ServoState) and time.monotonic() < deadline:
        time.sleep(0.05)  # bounded: the servo process starts its SDK (inline: no wait)
        first = _cycle_or_error(servo)
    assert isinstance(first, ServoState) and first.ok
    return first


@pytest.mark.parametrize("isolation", ["process", "inline"])
@pytest.mark.parametrize("retries", [2, 0])
def test_that_a_lockstep_cycle_of_a_healthy_servo_is_asked_again_before_a_lost_reply_is_a_fault(
        tmp_path: Path, retries: int, isolation: Literal["process", "inline"]) -> None:
    """Lockstep cycles (``serve: on_request``) with ``late_reply_retries``: a servo that answered
    its last cycle is asked again after a lost reply (an emulated servo starved by a loaded
    host is late, not faulty); one already in fault is not (its retries cost one timeout)."""
    # Fixture: a servo cycled on request, as a lockstep flight does
    emu = EmulatedMX28(BenchVehicle(max_tilt_rate_rad_s=100 * DEG), lock=threading.Lock(),
                       link_path=tmp_path / "tilt-servo", drive_clock=True)
    cfg = TiltServoConfig(uri=f"pty://{emu.path}?id=1", serve="on_request",
                          rate_limit_goal=False, late_reply_retries=retries)
    with emu, TiltServo(cfg, isolation) as servo:
        first = _first_cycle(servo)
        # Test 1: one reply lost
        emu.set_fault(Fault.SILENT, replies=1)
        one_lost = _cycle_or_error(servo)
        if retries == 0:  # the control: without retries that is a fault
            assert isinstance(one_lost, ServoCommError)
            servo.wait_for(lambda s: s.health is ServoHealth.NO_REPLY, WAIT_S)
            return
        assert isinstance(one_lost, ServoState) and one_lost.ok
        assert one_lost.seq == first.seq + 1 and one_lost.timeouts == 1
        # Test 2: more lost replies in a row than retries: the cycle fails, NO_REPLY
        emu.set_fault(Fault.SILENT, replies=retries + 1)
        assert isinstance(_cycle_or_error(servo), ServoCommError)
        faulted = servo.wait_for(lambda s: s.health is ServoHealth.NO_REPLY, WAIT_S)
        assert faulted.timeouts == 1 + retries + 1
        # Test 3: in fault, one lost reply is one failed cycle (no retry)
        emu.set_fault(Fault.SILENT, replies=1)
        assert isinstance(_cycle_or_error(servo), ServoCommError)
        servo.wait_for(lambda s: s.timeouts == faulted.timeouts + 1, WAIT_S)
        # Test 4: it answers again: back to OK, and retried again when next needed
        assert _cycle_or_error(servo).ok  # type: ignore[union-attr]
        emu.set_fault(Fault.SILENT, replies=1)
        again = _cycle_or_error(servo)
        assert isinstance(again, ServoState) and again.ok


@pytest.mark.parametrize("isolation", ["process", "inline"])
def test_that_a_lockstep_cycle_read_late_is_this_cycles_measurement_not_stale(
        tmp_path: Path, isolation: Literal["process", "inline"]) -> None:
    """A lockstep loop descheduled between the servo process's answer and its own read (100 ms
    and more on a loaded host) still has this cycle's measurement: fresh, not STALE. What it
    reads later, outside a cycle, ages on the wall clock as before."""
    emu = EmulatedMX28(BenchVehicle(max_tilt_rate_rad_s=100 * DEG), lock=threading.Lock(),
                       link_path=tmp_path / "tilt-servo", drive_clock=True)
    cfg = TiltServoConfig(uri=f"pty://{emu.path}?id=1", serve="on_request",
                          rate_limit_goal=False)
    with emu, TiltServo(cfg, isolation) as servo:
        first = _first_cycle(servo)
        # Test: the cycle is answered at once; the loop reads it 0.3 s later (a descheduled
        # process: the sleep stands for the host, not for a timing assumption)
        servo.begin_cycle()
        time.sleep(3 * cfg.stale_after_s)
        state = servo.finish_cycle(WAIT_S)
        # Assert
        assert state.health is ServoHealth.OK and state.seq == first.seq + 1
        assert state.age_s == 0.0
        # outside a cycle it ages on the wall clock (inline, the measurement is stamped when
        # its reply is taken: the finish above)
        time.sleep(3 * cfg.stale_after_s)
        assert servo.latest().health is ServoHealth.STALE


def test_that_an_inline_servo_unplugged_is_disconnected_then_configured_again(
        tmp_path: Path) -> None:
    """The inline servo (a lockstep flight's: the SDK in the loop's thread) meets an unplugged
    port as the servo process does: the cycle fails, the health says DISCONNECTED with the
    last tilt kept, requests answer "not connected", and once the port is back (and the
    reconnect period has passed) the next cycle configures it again and measures."""
    emu = EmulatedMX28(BenchVehicle(max_tilt_rate_rad_s=100 * DEG), lock=threading.Lock(),
                       link_path=tmp_path / "tilt-servo", drive_clock=True)
    cfg = TiltServoConfig(uri=f"pty://{emu.path}?id=1", serve="on_request",
                          rate_limit_goal=False, late_reply_retries=2)
    with emu, TiltServo(cfg, "inline") as servo:
        first = _first_cycle(servo)
        assert first.reconnects == 1
        # Test 1: unplugged
        emu.unplug()
        assert isinstance(_cycle_or_error(servo), ServoCommError)
        lost = servo.latest()
        assert lost.health is ServoHealth.DISCONNECTED
        assert lost.tilt_rad == first.tilt_rad  # the last measurement is kept
        with pytest.raises(ServoCommError, match="not connected"):
            servo.home(at_tilt_rad=0.0, timeout_s=WAIT_S)
        # Test 2: back; cycles answer "not connected" until the reconnect is due, then measure
        emu.replug()
        back = _first_cycle(servo)
        assert back.reconnects == 2 and back.seq > first.seq
        assert servo.probe(timeout_s=WAIT_S).is_mx28_p1


def test_that_an_inline_servo_is_served_on_request_only(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="on request only"):
        TiltServo(TiltServoConfig(uri=f"pty://{tmp_path}/x?id=1"), "inline")


def test_that_an_inline_cycle_waits_for_its_replies_no_longer_than_asked(tmp_path: Path) -> None:
    """A lockstep loop asks a servo already in fault briefly (0.3 s, not the SDK's 0.5 s
    timeout of a lockstep servo): inline, begin_cycle's timeout caps each reply's wait of that
    cycle, and the next cycle waits as configured again."""
    emu = EmulatedMX28(BenchVehicle(max_tilt_rate_rad_s=100 * DEG), lock=threading.Lock(),
                       link_path=tmp_path / "tilt-servo", drive_clock=True)
    cfg = TiltServoConfig(uri=f"pty://{emu.path}?id=1", serve="on_request",
                          rate_limit_goal=False, sdk_latency_timer_ms=250.0)
    with emu, TiltServo(cfg, "inline") as servo:
        _first_cycle(servo)
        link = servo._inline.link  # type: ignore[union-attr]
        # Test 1: capped at 50 ms: the READ's reply wait (SDK: its bytes' time + 2 x timer + 2)
        servo.begin_cycle(0.05)
        capped_ms = link.port.packet_timeout
        assert servo.finish_cycle(WAIT_S).ok
        # Test 2: no cap: the configured 2 x 250 + 2 ms
        servo.begin_cycle()
        uncapped_ms = link.port.packet_timeout
        assert servo.finish_cycle(WAIT_S).ok
        # Test 3: a silent servo asked with the cap fails, and the cap ends with the cycle
        emu.set_fault(Fault.SILENT, replies=1)
        servo.begin_cycle(0.05)
        with pytest.raises(ServoCommError):
            servo.finish_cycle(WAIT_S)
        assert link.sdk.port_handler.LATENCY_TIMER == 250.0
    assert 50.0 <= capped_ms < 51.0
    assert 502.0 <= uncapped_ms < 503.0


def test_that_a_crashed_servo_process_is_stale_and_stopping_it_returns(
        rig: tuple[EmulatedMX28, TiltServo]) -> None:
    # Fixture: the servo process killed (a crash, the OOM killer), most likely asleep between
    # two cycles in its wait for the stop flag: with a multiprocessing.Event, stop()'s set()
    # then waited for ever for it to wake (drivers.shared_flag)
    import os
    import signal

    _, servo = rig
    runner = servo._runner
    assert runner is not None and runner.pid is not None
    os.kill(runner.pid, signal.SIGKILL)
    runner.join(WAIT_S)
    # Test / Assert: the measurement goes stale, the last tilt kept; stopping returns at once
    state = servo.wait_for(lambda s: not s.ok, WAIT_S)
    assert state.health is ServoHealth.STALE
    assert_kept_last_tilt(state)
    stopper = threading.Thread(target=servo.stop, daemon=True)
    t0 = time.monotonic()
    stopper.start()
    stopper.join(WAIT_S)
    assert not stopper.is_alive() and time.monotonic() - t0 < 1.0

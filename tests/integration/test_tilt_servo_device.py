"""TiltServo (dynamixel-sdk in its own process) against the emulated MX-28T over a pty."""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Literal

import pytest

from drivers.dynamixel import (
    ErrorBit,
    Mode,
    Reg,
    ServoCommError,
    ServoError,
    ServoHealth,
    TiltServo,
    TiltServoConfig,
)
from sim_backend.emulators.dynamixel_p1 import EmulatedMX28
from sim_backend.vehicle import BenchVehicle

DEG = math.pi / 180.0
TILT_STEP_RAD = 2 * math.pi / 4096 * 0.05  # one servo step seen at the tilt
WAIT_S = 20.0  # generous: the machine may be loaded


def make_emulator(tmp_path: Path, **kwargs: object) -> EmulatedMX28:
    vehicle = BenchVehicle(max_tilt_rate_rad_s=100 * DEG)  # the servo is the only limit
    return EmulatedMX28(vehicle, lock=threading.Lock(), link_path=tmp_path / "tilt-servo",
                        drive_clock=True, **kwargs)  # type: ignore[arg-type]


@pytest.fixture
def emulator(tmp_path: Path) -> Iterator[EmulatedMX28]:
    with make_emulator(tmp_path) as emu:
        yield emu


def config_for(emu: EmulatedMX28, **changes: object) -> TiltServoConfig:
    return TiltServoConfig(uri=f"serial://{emu.path}?baud=1000000&id=1", **changes)  # type: ignore[arg-type]


def test_that_the_servo_is_identified_then_set_to_multi_turn_at_the_tilt_rate(
        emulator: EmulatedMX28) -> None:
    # Fixture: a factory-fresh servo (joint mode, 500 us return delay).
    servo = TiltServo(config_for(emulator))
    before = servo.probe()
    assert (before.model_number, before.mode, before.return_delay_us) == (29, Mode.JOINT, 500)
    # Test
    with servo:
        state = servo.wait_for(lambda s: s.ok, WAIT_S)
        identity = servo.probe()
    # Assert
    assert identity.is_mx28_p1 and identity.mode is Mode.MULTI_TURN
    assert identity.firmware_version == 41 and identity.return_delay_us == 0
    assert emulator.register(Reg.MOVING_SPEED) == 292  # 9.99 deg/s of tilt
    assert state.voltage_v == pytest.approx(12.0) and state.temperature_c == 25.0
    assert state.tilt_rad == pytest.approx(0.0, abs=TILT_STEP_RAD)


def test_that_stopping_turns_the_torque_off(emulator: EmulatedMX28) -> None:
    servo = TiltServo(config_for(emulator)).start()
    servo.wait_for(lambda s: s.ok, WAIT_S)
    assert emulator.register(Reg.TORQUE_ENABLE) == 1
    servo.stop()
    assert emulator.register(Reg.TORQUE_ENABLE) == 0
    assert servo.latest().health is ServoHealth.STOPPED


def max_rate_over_windows(log: list[tuple[float, float]], window_s: float) -> float:
    """Largest |d tilt| / dt over pairs of samples at least ``window_s`` apart."""
    worst, j = 0.0, 0
    for i in range(len(log)):
        while j < len(log) and log[j][0] - log[i][0] < window_s:
            j += 1
        if j == len(log):
            break
        worst = max(worst, abs(log[j][1] - log[i][1]) / (log[j][0] - log[i][0]))
    return worst


def test_that_a_0_35_0_deg_profile_respects_10_deg_s_and_is_read_back(
        emulator: EmulatedMX28) -> None:
    with TiltServo(config_for(emulator)) as servo:
        servo.wait_for(lambda s: s.ok, WAIT_S)
        # Test: up, then down.
        servo.set_tilt(35 * DEG)
        top = servo.wait_for(lambda s: s.tilt_rad >= 35 * DEG - TILT_STEP_RAD and not s.moving,
                             WAIT_S)
        top_steps = emulator.register(Reg.PRESENT_POSITION)
        servo.set_tilt(0.0)
        bottom = servo.wait_for(lambda s: s.tilt_rad <= TILT_STEP_RAD and not s.moving, WAIT_S)
        bottom_steps = emulator.register(Reg.PRESENT_POSITION)
    # Assert: positions read back exactly (35 deg x 20 = 7964 steps).
    assert top_steps == top.servo_position_steps == 7964
    assert bottom_steps == bottom.servo_position_steps == 0
    assert top.tilt_rad == pytest.approx(35 * DEG, abs=TILT_STEP_RAD)
    # The tilt never moved faster than 10 deg/s on the vehicle's clock. Slack: one physics
    # step (<= 0.1 s) of lag between the servo's trajectory and the bench's tilt.
    log = list(emulator.tilt_log)
    window_s = 1.0
    assert max_rate_over_windows(log, window_s) <= 10 * DEG * (window_s + 0.1) / window_s
    # ... and did get close to it (the profile is not trivially slow; a loaded machine may
    # stall the emulator's clock, hence the margin).
    assert max_rate_over_windows(log, window_s) >= 5 * DEG
    assert max(t for _, t in log) == pytest.approx(35 * DEG, abs=TILT_STEP_RAD)


@pytest.mark.parametrize("bit", list(ErrorBit)[1:])
def test_that_every_status_error_bit_is_surfaced_as_typed_health(
        emulator: EmulatedMX28, bit: ErrorBit) -> None:
    with TiltServo(config_for(emulator)) as servo:
        servo.wait_for(lambda s: s.ok, WAIT_S)
        emulator.force_error_bits(bit)
        state = servo.wait_for(lambda s: s.health is ServoHealth.SERVO_ERROR, WAIT_S)
        assert state.errors == bit
        emulator.force_error_bits(ErrorBit.NONE)
        servo.wait_for(lambda s: s.ok, WAIT_S)


def test_that_modelled_faults_reach_the_health_with_their_bits(emulator: EmulatedMX28) -> None:
    with TiltServo(config_for(emulator)) as servo:
        servo.wait_for(lambda s: s.ok, WAIT_S)
        emulator.set_supply_voltage(17.0)
        state = servo.wait_for(lambda s: bool(s.errors & ErrorBit.VOLTAGE), WAIT_S)
        assert state.voltage_v == pytest.approx(17.0)
        emulator.set_supply_voltage(12.0)
        emulator.set_temperature(85.0)
        state = servo.wait_for(lambda s: bool(s.errors & ErrorBit.OVERHEATING), WAIT_S)
        assert state.temperature_c > 80.0
        emulator.set_temperature(25.0)
        emulator.set_external_load(-1.2)  # beyond the stall torque: above any torque limit
        state = servo.wait_for(lambda s: bool(s.errors & ErrorBit.OVERLOAD), WAIT_S)
        assert state.load_fraction <= 0.0  # CW load (or none once the shutdown cut the torque)
        # Once the fault clears, the driver turns the torque back on (Shutdown cut it).
        emulator.set_external_load(0.0)
        servo.wait_for(lambda s: s.ok and emulator.register(Reg.TORQUE_ENABLE) == 1, WAIT_S)


def test_that_a_protocol_2_firmware_servo_is_refused(tmp_path: Path) -> None:
    with make_emulator(tmp_path, model_number=30) as emu, \
            TiltServo(config_for(emu)) as servo:
        state = servo.wait_for(lambda s: s.health is ServoHealth.WRONG_MODEL, WAIT_S)
        assert emu.register(Reg.TORQUE_ENABLE) == 0 and emu.mode() is Mode.JOINT
        assert math.isnan(state.tilt_rad)


def test_that_homing_sets_the_zero_and_goals_wait_for_it(tmp_path: Path) -> None:
    # Fixture: the mechanism was assembled with tilt 0 at Present Position 1234.
    with make_emulator(tmp_path, zero_offset_steps=1234) as emu, \
            TiltServo(config_for(emu, assume_homed=False)) as servo:
        servo.wait_for(lambda s: s.health is ServoHealth.HOMING_REQUIRED, WAIT_S)
        servo.set_tilt(10 * DEG)  # ignored until homed
        # Test
        zero = servo.home(at_tilt_rad=0.0)
        state = servo.wait_for(lambda s: s.ok and abs(s.tilt_rad - 10 * DEG) < TILT_STEP_RAD
                               and not s.moving, WAIT_S)
    # Assert
    assert zero == 1234
    assert state.servo_position_steps == 1234 + 2276  # 10 deg x 20 = 200 deg = 2275.6 steps
    assert max(t for _, t in emu.tilt_log) == pytest.approx(10 * DEG, abs=TILT_STEP_RAD)


def test_that_a_power_cycle_is_detected_and_asks_for_homing(emulator: EmulatedMX28) -> None:
    with TiltServo(config_for(emulator)) as servo:
        servo.wait_for(lambda s: s.ok, WAIT_S)
        servo.set_tilt(30 * DEG)
        servo.wait_for(lambda s: s.tilt_rad > 25 * DEG, WAIT_S)
        emulator.power_cycle()
        state = servo.wait_for(lambda s: s.health is ServoHealth.HOMING_REQUIRED, WAIT_S)
        assert not state.homed
        # Configured again and holding where it is (the worm held the tilt).
        servo.wait_for(lambda s: emulator.register(Reg.TORQUE_ENABLE) == 1, WAIT_S)


def test_that_in_lockstep_the_servo_follows_the_simulated_clock(tmp_path: Path) -> None:
    # Fixture: nobody advances the vehicle but this test (as the lockstep backend would).
    vehicle = BenchVehicle(max_tilt_rate_rad_s=100 * DEG)
    lock = threading.Lock()
    with EmulatedMX28(vehicle, lock=lock, link_path=tmp_path / "servo") as emu, \
            TiltServo(config_for(emu, rate_limit_goal=False)) as servo:
        servo.wait_for(lambda s: s.ok, WAIT_S)
        servo.set_tilt(35 * DEG)
        servo.wait_for(lambda s: emu.register(Reg.GOAL_POSITION) == 7964, WAIT_S)
        with lock:
            frozen = vehicle.tilt_rad()
        # Test: 1.5 s of simulated time, in 2 ms physics steps, as fast as the CPU goes.
        for _ in range(750):
            with lock:
                vehicle.advance(0.002)
            emu.step()
        with lock:
            tilt = vehicle.tilt_rad()
    # Assert: the wall time the driver took did not move the tilt; 1.5 s of simulated time at
    # Moving Speed 292 (9.99 deg/s of tilt) did, to within one physics step.
    assert frozen == 0.0
    assert tilt / DEG == pytest.approx(1.5 * 292 * 0.114 * 6 * 0.05, abs=0.03)


@pytest.mark.parametrize("isolation", ["process", "inline"])
def test_that_an_on_request_servo_runs_one_cycle_per_begin_finish_pair(
        emulator: EmulatedMX28, isolation: Literal["process", "inline"]) -> None:
    # Fixture: a lockstep-style servo, serviced only when asked, with the lockstep sessions'
    # late-reply retries (a loaded CI host once lost the emulator's reply to the goal write);
    # in the servo process, or inline (the SDK in this thread, as a lockstep flight runs it)
    servo = TiltServo(config_for(emulator, serve="on_request", rate_limit_goal=False,
                                 late_reply_retries=2), isolation).start()
    try:
        deadline = time.monotonic() + WAIT_S
        while True:  # the servo process answers "not connected" until it has configured it
            try:
                first = servo.sync_cycle(WAIT_S)
                break
            except ServoCommError:
                assert time.monotonic() < deadline, "the servo never connected"
        # Test: a goal set before the pair is written by it, and measured by it
        servo.set_tilt(10 * DEG)
        servo.begin_cycle()
        state = servo.finish_cycle(WAIT_S)
        # Assert: exactly one more cycle, carrying the new goal
        assert state.seq == first.seq + 1
        assert state.goal_tilt_rad == pytest.approx(10 * DEG, abs=TILT_STEP_RAD)
        assert servo.latest().seq == state.seq  # nothing runs unasked
        with pytest.raises(ServoError, match="no service cycle pending"):
            servo.finish_cycle(WAIT_S)
    finally:
        servo.stop()

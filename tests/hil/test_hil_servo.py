"""The tilt servo on the bench: identity, read-only status, homing, moves at the rate limit,
the range limits, and the torque left off."""

from __future__ import annotations

import math

import pytest

from controller.params import VehicleParams
from drivers.dynamixel import Mode, TiltServo, TiltServoConfig
from drivers.dynamixel.device import probe_servo, read_servo, tilt_to_steps
from groundstation.cli import main

pytestmark = pytest.mark.hil

WAIT_S = 30.0


def _servo(uri: str, vehicle: VehicleParams, zero_steps: int = 0) -> TiltServo:
    t = vehicle.tilt
    return TiltServo(TiltServoConfig(uri=uri, gear_ratio=t.worm_ratio,
                                     zero_offset_steps=zero_steps, max_tilt_deg=t.max_tilt_deg,
                                     max_tilt_rate_deg_s=t.max_rate_deg_s))


def test_that_the_servo_is_an_mx28_with_protocol_1(servo_uri: str) -> None:
    ident = probe_servo(servo_uri)
    assert ident.is_mx28_p1, f"model {ident.model_number}"
    assert ident.firmware_version > 0


def test_that_status_reads_without_changing_the_servo(servo_uri: str) -> None:
    # Test: two reads around a `servo status`
    before = read_servo(servo_uri)
    assert main(["servo", "status", "--uri", servo_uri]) == 0
    after = read_servo(servo_uri)
    # Assert: what status could have written is unchanged (goal, torque, LED, mode, delay)
    assert after.goal_position_steps == before.goal_position_steps
    assert after.torque_enabled == before.torque_enabled and after.led_on == before.led_on
    assert after.identity.mode is before.identity.mode
    assert after.identity.return_delay_us == before.identity.return_delay_us


def test_that_the_servo_homes_moves_at_the_rate_limit_and_comes_back(
        servo_uri: str, hil_vehicle: VehicleParams) -> None:
    t = hil_vehicle.tilt
    step_deg = min(5.0, t.max_tilt_deg)
    with _servo(servo_uri, hil_vehicle) as servo:
        servo.wait_for(lambda s: s.health.name in ("OK", "HOMING_REQUIRED"), WAIT_S)
        # Test: the present position is tilt 0 (the mechanism on its jig), then a step and back
        zero = servo.home(0.0)
        servo.wait_for(lambda s: s.ok, WAIT_S)
        servo.set_tilt(math.radians(step_deg))
        there = servo.wait_for(lambda s: abs(math.degrees(s.tilt_rad) - step_deg) < 0.2
                               and not s.moving, WAIT_S)
        servo.set_tilt(0.0)
        back = servo.wait_for(lambda s: abs(math.degrees(s.tilt_rad)) < 0.2 and not s.moving,
                              WAIT_S)
        # the tilt rate never beyond the configured limit (+ the servo's speed quantisation)
        ident = servo.probe()
    # Assert: one servo step is 360/4096 deg at the servo, times the worm ratio at the tilt
    step_tilt_deg = 360.0 / 4096 * t.worm_ratio
    assert math.degrees(there.tilt_rad) == pytest.approx(step_deg, abs=2 * step_tilt_deg + 0.2)
    assert math.degrees(back.tilt_rad) == pytest.approx(0.0, abs=2 * step_tilt_deg + 0.2)
    assert there.servo_position_steps == pytest.approx(
        tilt_to_steps(math.radians(step_deg), t.worm_ratio, zero), abs=3)
    assert ident.mode is Mode.MULTI_TURN
    # the documented rest state once stopped: torque off (the worm drive holds the tilt)
    assert not read_servo(servo_uri).torque_enabled


def test_that_the_range_limits_hold(servo_uri: str, hil_vehicle: VehicleParams,
                                    capsys: pytest.CaptureFixture[str]) -> None:
    t = hil_vehicle.tilt
    # Test: the CLI refuses a goal beyond the range before touching the servo
    before = read_servo(servo_uri)
    code = main(["servo", "move", str(t.max_tilt_deg + 10.0), "--uri", servo_uri])
    err = capsys.readouterr().err
    after = read_servo(servo_uri)
    # Assert
    assert code == 2 and f"within [0, {t.max_tilt_deg:g}] deg" in err
    assert after.goal_position_steps == before.goal_position_steps
    # and the driver clamps any goal it is handed to [0, max tilt]
    with _servo(servo_uri, hil_vehicle) as servo:
        servo.set_tilt(math.radians(t.max_tilt_deg + 10.0))
        assert servo._mailbox.goal[0] == pytest.approx(math.radians(t.max_tilt_deg))
        servo.set_tilt(math.radians(-5.0))
        assert servo._mailbox.goal[0] == 0.0

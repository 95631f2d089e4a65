"""A Present Position no MX-28 can report (beyond the multi-turn range) is dropped and counted
by TiltServo: the last good tilt is kept, and the servo comes back when the readings do."""

from __future__ import annotations

import math
import threading
from pathlib import Path

import pytest

from drivers.dynamixel import Reg, ServoHealth, TiltServo, TiltServoConfig
from sim_backend.emulators.dynamixel_p1 import EmulatedMX28
from sim_backend.vehicle import BenchVehicle

DEG = math.pi / 180.0
WAIT_S = 20.0


class _LyingMX28(EmulatedMX28):
    """The real emulated servo, with a Present Position register that can be made to lie."""

    lie_steps: int | None = None

    def _refresh_present(self, real: float) -> None:
        super()._refresh_present(real)
        if self.lie_steps is not None:
            self._write_reg(Reg.PRESENT_POSITION, self.lie_steps)


def test_that_a_present_position_beyond_the_multi_turn_range_is_dropped(tmp_path: Path) -> None:
    # Fixture
    vehicle = BenchVehicle(max_tilt_rate_rad_s=100 * DEG)
    emu = _LyingMX28(vehicle, lock=threading.Lock(), link_path=tmp_path / "tilt-servo",
                     drive_clock=True)
    with emu, TiltServo(TiltServoConfig(uri=f"pty://{emu.path}?id=1")) as servo:
        servo.wait_for(lambda s: s.ok, WAIT_S)
        servo.set_tilt(5 * DEG)
        good = servo.wait_for(lambda s: abs(s.tilt_rad - 5 * DEG) < 0.01 * DEG
                              and not s.moving, WAIT_S)
        # Test: 30000 steps, past +28672 (raw 0x7530 on the wire)
        emu.lie_steps = 30000
        lied = servo.wait_for(lambda s: s.implausible_readings >= 3, WAIT_S)
        emu.lie_steps = None
        back = servo.wait_for(lambda s: s.ok and s.seq > lied.seq, WAIT_S)
    # Assert
    assert lied.tilt_rad == pytest.approx(good.tilt_rad, abs=1e-12)
    assert lied.servo_position_steps == good.servo_position_steps
    assert back.tilt_rad == pytest.approx(5 * DEG, abs=0.01 * DEG)
    assert back.health is ServoHealth.OK

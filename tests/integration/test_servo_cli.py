"""``fasthex servo`` against the emulated MX-28T of a session (the real SDK over a pty)."""

from __future__ import annotations

import math
import re
import threading
from pathlib import Path

import pytest

from drivers.dynamixel import Reg
from drivers.dynamixel.control_table import MX28_P1, Access
from groundstation.cli import main
from sim_backend.emulators.dynamixel_p1 import EmulatedMX28
from sim_backend.vehicle import BenchVehicle


def test_that_servo_status_identifies_the_emulated_mx28(capsys: pytest.CaptureFixture[str]
                                                        ) -> None:
    assert main(["servo", "status"]) == 0
    out = capsys.readouterr().out
    # a fresh emulated servo, read as it is: joint mode until a flight or a move configures it
    assert "model 29 firmware 41 id 1 mode joint" in out
    assert "tilt 0.00 deg" in out and "torque off" in out


def test_that_servo_move_reaches_the_goal_tilt(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["servo", "move", "3"]) == 0
    out = capsys.readouterr().out
    assert "reached 3.0" in out or "reached 2.9" in out
    assert "tilt 3.0" in out or "tilt 2.9" in out


def test_that_servo_move_without_a_goal_is_a_user_error(capsys: pytest.CaptureFixture[str]
                                                        ) -> None:
    assert main(["servo", "move"]) == 2
    assert "needs the goal tilt in degrees" in capsys.readouterr().err


# ------------------------------------------------------- read-only status, range, torque at rest

def _mx28(tmp_path: Path, tilt_rate_deg_s: float = 100.0) -> EmulatedMX28:
    vehicle = BenchVehicle(max_tilt_rate_rad_s=math.radians(tilt_rate_deg_s))
    return EmulatedMX28(vehicle, lock=threading.Lock(), link_path=tmp_path / "tilt-servo",
                        drive_clock=True, zero_offset_steps=1024)


def _control_table(emu: EmulatedMX28) -> dict[str, int]:
    """Every writable entry, EEPROM and RAM (the read-only ones are measurements that move by
    themselves: Present *, Realtime Tick)."""
    return {r.reg.name: emu.register(r.reg) for r in MX28_P1 if r.access is Access.RW}


def test_that_servo_status_writes_nothing_to_the_servo(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # Fixture: a factory-fresh servo (joint mode, 500 us return delay, torque off)
    with _mx28(tmp_path) as emu:
        before = _control_table(emu)
        instructions = emu.instructions
        # Test
        code = main(["servo", "status", "--uri", f"serial://{emu.path}?baud=1000000&id=1",
                     "--zero-steps", "1024"])
        after = _control_table(emu)
        # Assert: it asked (PING and READs) but every writable register is as it was
        assert code == 0
        assert len(before) == 25
        assert emu.instructions - instructions >= 5
        assert after == before
    out = capsys.readouterr().out
    assert "model 29 firmware 41 id 1 mode joint" in out  # reported, not "fixed"
    assert "torque off" in out and "not configured since power-up" in out


class _MissingEveryThirdReply(EmulatedMX28):
    """An MX-28 whose every third reply never arrives (a loaded host: the SDK's ~34 ms wait
    for a status packet ran out; seen beside the test suite on 2 cores). The SDK's PING is
    two requests (the PING, then a READ of the model number)."""

    replies_dropped = 0
    _replies_made = 0

    def _schedule(self, reply: bytes | None) -> None:
        if reply is not None:
            self._replies_made += 1
            if self._replies_made % 3 == 0:
                self.replies_dropped += 1
                return
        super()._schedule(reply)


def test_that_servo_status_asks_again_when_a_reply_is_lost(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # Fixture: a servo that misses every third reply: the PING is answered, the first READ
    # is not (before, only the PING was asked again: `servo status` failed with "read
    # RETURN_DELAY_TIME: There is no status packet!")
    vehicle = BenchVehicle(max_tilt_rate_rad_s=math.radians(100.0))
    with _MissingEveryThirdReply(vehicle, lock=threading.Lock(),
                                 link_path=tmp_path / "tilt-servo", drive_clock=True,
                                 zero_offset_steps=1024) as emu:
        # Test
        code = main(["servo", "status", "--uri", f"serial://{emu.path}?baud=1000000&id=1",
                     "--zero-steps", "1024"])
        # Assert: each lost reply asked again, the servo identified as it is
        assert code == 0
        assert emu.replies_dropped >= 4
    out = capsys.readouterr().out
    assert "model 29 firmware 41 id 1 mode joint" in out and "tilt 0.00 deg" in out


def test_that_a_move_outside_the_tilt_range_is_an_error(
        capsys: pytest.CaptureFixture[str]) -> None:
    for deg in ("80", "-1", "nan"):
        # Test: refused before anything is opened or started
        code = main(["servo", "move", deg])
        err = capsys.readouterr().err
        # Assert: one line naming the range of the session's vehicle (fasthex: 0..35 deg)
        assert code == 2
        assert err.count("\n") == 1
        assert "within [0, 35] deg" in err


def test_that_move_and_home_leave_the_torque_off(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # Fixture
    with _mx28(tmp_path) as emu:
        uri = f"serial://{emu.path}?baud=1000000&id=1"
        # Test
        moved = main(["servo", "move", "2", "--uri", uri, "--zero-steps", "1024"])
        torque_after_move = emu.register(Reg.TORQUE_ENABLE)
        tilt_steps = emu.register(Reg.PRESENT_POSITION)
        homed = main(["servo", "home", "--uri", uri, "--zero-steps", "1024"])
        torque_after_home = emu.register(Reg.TORQUE_ENABLE)
    # Assert: 2 deg of tilt = 40 deg at the servo (20:1) = 455 steps above the zero
    assert moved == 0 and homed == 0
    assert torque_after_move == 0 and torque_after_home == 0
    assert tilt_steps - 1024 == pytest.approx(2 / 0.05 * 4096 / 360, abs=3)
    assert capsys.readouterr().out.count("torque off (the worm drive holds the tilt)") == 2


# ------------------------------------------------------------- the session's servo zero offset

_HW_SESSION = """\
schema: fasthex.session
version: 1
name: bench-servo-zero
vehicle: fasthex
mission: exp1-hover-tilt-steps
backend:
  kind: hardware
  flight_ctrl_uri: serial:///dev/ttyUSB0?baud=500000
  servo_uri: serial://{servo}?baud=1000000&id=1
  mocap_uri: natnet://192.0.2.10?local=192.0.2.20&body=fasthex
{zero}"""


def test_that_the_sessions_servo_zero_offset_is_the_tilt_zero_of_status_and_move(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # Fixture: a servo whose tilt 0 is at Present Position 1024, named by two hardware
    # sessions, one with the zero written down (as `servo home` prints it), one without
    with _mx28(tmp_path) as emu:
        with_zero = tmp_path / "with-zero.yaml"
        with_zero.write_text(_HW_SESSION.format(servo=emu.path,
                                                zero="  servo_zero_offset_steps: 1024\n"))
        without = tmp_path / "without.yaml"
        without.write_text(_HW_SESSION.format(servo=emu.path, zero=""))
        # Test
        status_with = main(["servo", "status", "--session", str(with_zero)])
        out_with = capsys.readouterr().out
        status_without = main(["servo", "status", "--session", str(without)])
        out_without = capsys.readouterr().out
        moved = main(["servo", "move", "2", "--session", str(with_zero)])
        tilt_steps = emu.register(Reg.PRESENT_POSITION)
    # Assert: with the zero the mechanism reads 0 deg; without it, 1024 steps above the
    # encoder's zero = 1024 x 360/4096 deg at the servo x 0.05 (20:1 worm) = 4.50 deg
    assert status_with == status_without == moved == 0
    assert "tilt 0.00 deg" in out_with
    assert "tilt 4.50 deg" in out_without
    # 2 deg of tilt lands 455 steps above the session's zero, not above the encoder's
    assert tilt_steps - 1024 == pytest.approx(2 / 0.05 * 4096 / 360, abs=3)


def test_that_a_servo_zero_that_puts_the_tilt_range_past_the_encoder_is_a_config_error(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # Fixture: 35 deg of tilt is 700 deg at the servo = 7964 steps: a zero at 28000 overflows
    session = tmp_path / "s.yaml"
    session.write_text(_HW_SESSION.format(servo="/dev/null",
                                          zero="  servo_zero_offset_steps: 28000\n"))
    # Test
    code = main(["servo", "status", "--session", str(session)])
    err = capsys.readouterr().err
    # Assert: one FILE:LINE: KEY: expectation line, the line of the key
    assert code == 2
    assert err.count("\n") == 1
    assert f"{session}:11: backend.servo_zero_offset_steps:" in err
    assert "beyond the servo's multi-turn range" in err
    assert "expected a zero of at most 20708" in err


def test_that_home_prints_the_tilt_from_the_new_zero_and_the_errors_by_name(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # Fixture: the session says zero 0; the mechanism sits on its jig at Present Position 1024
    with _mx28(tmp_path) as emu:
        session = tmp_path / "s.yaml"
        session.write_text(_HW_SESSION.format(servo=emu.path,
                                              zero="  servo_zero_offset_steps: 0\n"))
        # Test
        code = main(["servo", "home", "--session", str(session)])
    out = capsys.readouterr().out
    # Assert: the new zero, the one it replaces, and the state read with the new zero (the
    # jig is tilt 0), not the 4.50 deg of the old one; the error byte in words
    assert code == 0
    assert "tilt 0.00 deg (goal 0.00), servo 1024 steps" in out, out
    assert "errors none" in out and "ErrorBit" not in out, out
    assert ("zero offset: 1024 steps (Present Position at tilt 0; was 0); put it in the "
            "session as backend.servo_zero_offset_steps") in out


def test_that_a_move_that_times_out_says_the_last_state_in_degrees(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # Fixture: a mechanism at 0.2 deg/s, far slower than the vehicle's 10 deg/s the command
    # allows for (the move's deadline: 5 s + 3 deg at 10 deg/s)
    with _mx28(tmp_path, tilt_rate_deg_s=0.2) as emu:
        uri = f"serial://{emu.path}?baud=1000000&id=1"
        # Test
        code = main(["servo", "move", "3", "--uri", uri, "--zero-steps", "1024"])
    err = capsys.readouterr().err
    # Assert: one readable line: the tilt short of the goal, in degrees, moving, no errors
    assert code == 2 and err.count("\n") == 1, err
    assert "ServoState(" not in err and "ErrorBit" not in err, err
    match = re.search(r"tilt not reached: .*: timed out after 5\.3 s; last state: tilt "
                      r"(\d+\.\d\d) deg \(goal 3\.00 deg\), moving, health OK, errors none, "
                      r"read \d+ ms ago$", err.strip())
    assert match is not None, err
    assert 0.5 < float(match.group(1)) < 2.0

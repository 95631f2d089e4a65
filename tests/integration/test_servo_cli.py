"""``fasthex servo`` against the emulated MX-28T of a session (the real SDK over a pty)."""

from __future__ import annotations

import pytest

from groundstation.cli import main


def test_that_servo_status_identifies_the_emulated_mx28(capsys: pytest.CaptureFixture[str]
                                                        ) -> None:
    assert main(["servo", "status"]) == 0
    out = capsys.readouterr().out
    assert "model 29 firmware 41 id 1 mode multi_turn" in out
    assert "tilt 0.00 deg" in out and "health OK" in out


def test_that_servo_move_reaches_the_goal_tilt(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["servo", "move", "3"]) == 0
    out = capsys.readouterr().out
    assert "reached 3.0" in out or "reached 2.9" in out
    assert "tilt 3.0" in out or "tilt 2.9" in out


def test_that_servo_move_without_a_goal_is_a_user_error(capsys: pytest.CaptureFixture[str]
                                                        ) -> None:
    assert main(["servo", "move"]) == 2
    assert "needs the goal tilt in degrees" in capsys.readouterr().err

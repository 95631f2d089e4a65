"""Ctrl-C on `fasthex fly`: the first SIGINT lands, a second one cuts the motors; the session
ends with its report and the record is complete."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from flight_support import SESSION, SHORT_MISSION

from groundstation.record import read_record
from groundstation.signals import REPEAT_WINDOW_S


def _rows(path: Path) -> int:
    try:
        return len(read_record(path).rows)
    except (OSError, ValueError):
        return 0


def _start(tmp_path: Path, name: str, clock: str = "lockstep"
           ) -> tuple[subprocess.Popen[str], Path]:
    (tmp_path / "short-hover.yaml").write_text(
        SHORT_MISSION.replace("duration_s: 4.0", "duration_s: 60.0"))
    session = tmp_path / f"{name}.yaml"
    session.write_text(SESSION.format(seed=2, faults="", corrupt=0.0, zmax=2.5,
                                      servo_action="hold").replace("clock: lockstep",
                                                                   f"clock: {clock}"))
    record = tmp_path / f"{name}.fhr"
    proc = subprocess.Popen([sys.executable, "-m", "groundstation", "fly", str(session),
                             "--record", str(record), "--quiet", "--rerun", "off"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120.0
    while _rows(record) < 3000 and time.monotonic() < deadline:  # airborne (6 s of ticks)
        time.sleep(0.05)  # polling the record another process writes, bounded
    assert _rows(record) >= 3000
    return proc, record


def test_that_one_ctrl_c_lands_the_vehicle(tmp_path: Path) -> None:
    proc, record = _start(tmp_path, "land")
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 1, err  # the flight did not end as planned: exit code 1
    events = Path(str(record) + ".events.txt").read_text()
    assert "operator stop: landing" in events
    assert "LANDING -> DISARMED: touchdown" in events
    assert "session ended: operator: land" in out
    assert read_record(record).rows["pos_w_m"][-1][2] < 0.15


@pytest.mark.exclusive  # a realtime flight: a loaded host's IMU gap would cut it
def test_that_a_second_ctrl_c_cuts_the_motors(tmp_path: Path) -> None:
    # realtime: a person's second press comes after the repeat window (0.1 s: the same signal
    # within it is the same request) and while the landing (3 s) still runs; a lockstep flight
    # flies 0.5 s in ~55 ms of wall time and lands in ~0.35 s
    proc, record = _start(tmp_path, "cut", clock="realtime")
    proc.send_signal(signal.SIGINT)
    sent = time.monotonic()
    n = _rows(record)
    deadline = time.monotonic() + 60.0
    while _rows(record) < n + 250 and time.monotonic() < deadline:  # 0.5 s later
        time.sleep(0.05)
    time.sleep(max(0.0, sent + 3 * REPEAT_WINDOW_S - time.monotonic()))  # past the window
    proc.send_signal(signal.SIGINT)
    proc.communicate(timeout=120)
    events = Path(str(record) + ".events.txt").read_text()
    assert "operator stop: motors cut" in events, events
    assert "-> CUT: operator: second stop request" in events

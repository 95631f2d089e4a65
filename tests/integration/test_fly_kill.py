"""The ground station is killed (kill -9) in flight: the emulated board's watchdog stops the
motors, as the real BL-Ctrls do, and the flight record is readable up to the kill."""

from __future__ import annotations

import json
import multiprocessing as mp
import os
import signal
import time
from pathlib import Path

from flight_support import fly_long_hover_in_this_process

from groundstation.record import read_record


def _wait_for(predicate: object, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():  # type: ignore[operator]
            return True
        time.sleep(0.05)  # polling a file another process writes; bounded by the deadline
    return False


def test_that_kill_9_of_the_ground_station_stops_the_motors_and_keeps_the_record(
        tmp_path: Path) -> None:
    # Fixture: a flight in its own process, hovering for a minute
    record = tmp_path / "killed.fhr"
    proc = mp.get_context("spawn").Process(target=fly_long_hover_in_this_process,
                                           args=(str(tmp_path),))
    proc.start()

    def rows_written() -> int:
        try:
            return len(read_record(record).rows)
        except (OSError, ValueError):
            return 0

    try:
        # airborne: 6 s of ticks recorded (takeoff ends at 4.5 s)
        assert _wait_for(lambda: rows_written() >= 3000, 120.0)
        # Test
        assert proc.pid is not None
        os.kill(proc.pid, signal.SIGKILL)
        proc.join(timeout=10)
        before = rows_written()
        # Assert: the emulator noticed, waited for its watchdog, and left a note
        note_path = tmp_path / "dev" / "emulator-exit.json"
        assert _wait_for(note_path.exists, 30.0)
        note = json.loads(note_path.read_text())
        assert note["motors_stopped"] is True
        assert note["watchdog_trips"] >= 1
        # the record is readable, and the telemetry process wrote out what the ring held
        assert _wait_for(lambda: rows_written() >= before, 10.0)
        rows = read_record(record).rows
        assert len(rows) >= 3000
        assert rows["pos_w_m"][-1][2] > 0.5  # it was flying when killed
    finally:
        if proc.is_alive():
            proc.kill()

"""The ground station is killed (kill -9 of its whole process group) in flight: the emulated
board's watchdog stops the motors, as the real BL-Ctrls do, and the flight record loses at most
the last 100 ms (the telemetry process writes the ring out every 50 ms).

The loss is measured, not assumed: the emulated vehicle (in a session of its own, so the kill
does not reach it) logs the true state at every IMU sample it sends and ends that log when the
ground station is gone, so the log's last row is the last tick the ground station could have
flown. The flight runs on the realtime clock, the one a crash-loss budget is about (in lockstep
the simulated time runs several times faster than the wall clock the telemetry writer sleeps
on); a realtime session does not ask for the truth log, so this test turns it on. The record's
clock (host time since the first sample) and the emulator's simulated clock are put on one
time base by the takeoff: the instant the climb passes its midpoint, in the record's estimate
and in the truth (the estimate follows the truth to a few mm, ~10 ms at the climb's 0.5 m/s).
"""

from __future__ import annotations

import contextlib
import json
import multiprocessing as mp
import os
import signal
import time
from pathlib import Path

import numpy as np
from process_targets import START_Z_M, TAKEOFF_HEIGHT_M, fly_long_hover_in_own_group

from groundstation.record import read_record
from sim_backend.backend import TruthLog

#: the documented crash loss of the flight record
MAX_LOSS_S = 0.1
#: the kill comes this long after a telemetry write was seen: a writer that writes every 50 ms
#: has written twice more since; one that writes every 300 ms has not
KILL_AFTER_WRITE_S = 0.15


def _wait_for(predicate: object, timeout_s: float, poll_s: float = 0.05) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():  # type: ignore[operator]
            return True
        time.sleep(poll_s)  # polling files another process writes; bounded by the deadline
    return False


def _crossing_s(t_s: np.ndarray, z_m: np.ndarray, level_m: float) -> float:
    """The first time ``z`` rises through ``level`` (linear between the two samples)."""
    i = int(np.argmax(z_m >= level_m))
    assert i > 0 and z_m[i] >= level_m > z_m[i - 1]
    return float(t_s[i - 1] + (level_m - z_m[i - 1]) / (z_m[i] - z_m[i - 1])
                 * (t_s[i] - t_s[i - 1]))


def test_that_kill_9_of_the_ground_station_loses_at_most_100_ms_and_stops_the_motors(
        tmp_path: Path) -> None:
    # Fixture: a realtime flight in its own process group, hovering for a minute
    record = tmp_path / "killed.fhr"
    proc = mp.get_context("spawn").Process(target=fly_long_hover_in_own_group,
                                           args=(str(tmp_path),))
    proc.start()
    assert proc.pid is not None

    def size() -> int:
        try:
            return record.stat().st_size
        except OSError:
            return 0

    def rows_written() -> int:
        try:
            return len(read_record(record).rows)
        except (OSError, ValueError):
            return 0

    try:
        # airborne and hovering: 6 s of ticks recorded (the takeoff ends at ~4.5 s)
        assert _wait_for(lambda: rows_written() >= 3000, 120.0)
        # Test: kill -9 the whole group a fixed time after a write of the telemetry process
        before = size()
        assert _wait_for(lambda: size() != before, 5.0, poll_s=0.002)
        time.sleep(KILL_AFTER_WRITE_S)  # the phase of the kill against the writer's period
        os.killpg(proc.pid, signal.SIGKILL)
        proc.join(timeout=10)
        # Assert: the emulator noticed, waited for its watchdog, and left a note
        note_path = tmp_path / "dev" / "emulator-exit.json"
        assert _wait_for(note_path.exists, 30.0)
        note = json.loads(note_path.read_text())
        assert note["motors_stopped"] is True
        assert note["watchdog_trips"] >= 1
        # the record against the truth, on one time base (the takeoff's midpoint)
        rows = read_record(record).rows
        truth = TruthLog.read(tmp_path / "dev" / "truth.f64")
        assert rows["pos_w_m"][-1][2] > 0.5  # it was flying when killed
        mid_m = START_Z_M + TAKEOFF_HEIGHT_M / 2
        offset_s = (_crossing_s(truth[:, 0], truth[:, 3], mid_m)
                    - _crossing_s(rows["t_s"], rows["est_pos_w_m"][:, 2], mid_m))
        last_tick_s = float(truth[-1, 0])  # the last sample the ground station could take
        lost_s = last_tick_s - (float(rows["t_s"][-1]) + offset_s)
        assert -0.02 < lost_s <= MAX_LOSS_S, f"the record ends {lost_s * 1e3:.0f} ms early"
    finally:
        if proc.is_alive():
            os.killpg(proc.pid, signal.SIGKILL)


def _children(pid: int) -> dict[int, str]:
    """The processes whose parent is ``pid``: pid -> command line."""
    found: dict[int, str] = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat") as f:
                ppid = int(f.read().rsplit(")", 1)[1].split()[1])
            if ppid == pid:
                with open(f"/proc/{entry}/cmdline", "rb") as f:
                    found[int(entry)] = f.read().replace(b"\0", b" ").decode(errors="replace")
        except (OSError, IndexError, ValueError):
            continue
    return found


def _running(pid: int) -> bool:
    """Alive, not a zombie waiting to be reaped."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def test_that_kill_9_of_the_ground_station_in_its_start_up_leaves_no_telemetry_process(
        tmp_path: Path) -> None:
    """The telemetry process starts first in a session and imports for a second or so. A
    ground station killed meanwhile (kill -9, the OOM killer) is dead before its child can
    note its parent's pid: the child, given the session's pid, still sees it gone and exits
    (reading its parent's pid itself, it took its new parent for the session and waited for
    the flight forever)."""
    from flight_support import fly_long_hover_in_this_process

    # Fixture: a lockstep session in its own process
    proc = mp.get_context("spawn").Process(target=fly_long_hover_in_this_process,
                                           args=(str(tmp_path),))
    proc.start()
    assert proc.pid is not None
    telemetry: list[int] = []
    try:
        def telemetry_started() -> bool:
            telemetry[:] = [p for p, cmd in _children(proc.pid).items()  # type: ignore[arg-type]
                            if "spawn_main" in cmd]
            return bool(telemetry)

        assert _wait_for(telemetry_started, 60.0, poll_s=0.005)
        # Test: the ground station alone killed, its telemetry child still importing
        os.kill(proc.pid, signal.SIGKILL)
        proc.join(timeout=10)
        # Assert: the telemetry process ends of itself, and there is no record
        assert _wait_for(lambda: not _running(telemetry[0]), 30.0)
        assert not (tmp_path / "killed.fhr").exists()
    finally:
        if proc.is_alive():
            os.kill(proc.pid, signal.SIGKILL)
        for pid in telemetry:
            with contextlib.suppress(OSError):
                os.kill(pid, signal.SIGKILL)


def test_that_kill_9_of_the_ground_station_leaves_no_temporary_folder(tmp_path: Path) -> None:
    """The session's temporary folder (the emulator's links, its truth log) cannot be removed
    by a ground station killed with SIGKILL: the emulator, orphaned, removes it once its
    watchdog has stopped the motors."""
    from flight_support import fly_long_hover_in_a_temporary_folder

    # Fixture: a lockstep session hovering for a minute, its folder under tmp_path/t
    proc = mp.get_context("spawn").Process(target=fly_long_hover_in_a_temporary_folder,
                                           args=(str(tmp_path),))
    proc.start()
    assert proc.pid is not None

    def folders() -> list[str]:
        return [p.name for p in (tmp_path / "t").glob("fasthex-*")]

    def rows_written() -> int:
        try:
            return len(read_record(tmp_path / "killed.fhr").rows)
        except (OSError, ValueError):
            return 0

    try:
        assert _wait_for(lambda: rows_written() >= 3000, 120.0)  # airborne
        assert len(folders()) == 1
        # Test
        os.kill(proc.pid, signal.SIGKILL)
        proc.join(timeout=10)
        # Assert: gone once the emulator's watchdog wait (at most 10 s) is over
        assert _wait_for(lambda: not folders(), 30.0), folders()
    finally:
        if proc.is_alive():
            os.kill(proc.pid, signal.SIGKILL)

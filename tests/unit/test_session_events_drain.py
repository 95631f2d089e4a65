"""The telemetry process writes every event the session sent before it stopped: a
multiprocessing queue hands another process the producer's last items only once the
producer's feeder thread has written them to the pipe, so a non-blocking read at the end
found the queue empty and the flight's last transitions missing from the events file under
load. The session ends its events with END_OF_EVENTS; the telemetry drains up to it."""

from __future__ import annotations

import collections
import os
import queue
from pathlib import Path
from typing import Any

from groundstation.session import END_OF_EVENTS, _telemetry_run


class _LaggingQueue:
    """The events queue as the telemetry process sees it: ``late`` items are still in the
    session's feeder thread (a non-blocking read misses them, a blocking one waits for them)."""

    def __init__(self, ready: list[str], late: list[str]) -> None:
        self.ready = collections.deque(ready)
        self.late = collections.deque(late)
        self.waits = 0

    def get_nowait(self) -> str:
        if self.ready:
            return self.ready.popleft()
        raise queue.Empty

    def get(self, timeout: float) -> str:
        if not self.ready and self.late:
            self.waits += 1
            self.ready.extend(self.late)
            self.late.clear()
        return self.get_nowait()


class _NoRows:
    def drain(self) -> list[Any]:
        return []


class _Writer:
    closed = False

    def append_block(self, rows: Any) -> None:
        raise AssertionError("no rows were queued")

    def close(self) -> None:
        self.closed = True


class _Set:
    def is_set(self) -> bool:
        return True


def test_the_last_events_still_under_way_are_written(tmp_path: Path) -> None:
    events_path = tmp_path / "flight.fhr.events.txt"
    q = _LaggingQueue(["9.500 s MISSION -> LANDING: mission complete"],
                      ["13.206 s LANDING -> DISARMED: touchdown",
                       "session ended: mission complete", END_OF_EVENTS])
    writer = _Writer()
    _telemetry_run(_NoRows(), writer, q, str(events_path), _Set(), os.getppid(), None, None)  # type: ignore[arg-type]
    assert events_path.read_text().splitlines() == [
        "9.500 s MISSION -> LANDING: mission complete",
        "13.206 s LANDING -> DISARMED: touchdown",
        "session ended: mission complete"]
    assert q.waits == 1 and writer.closed


def test_a_session_that_died_leaves_no_end_marker_and_the_drain_still_ends(
        tmp_path: Path) -> None:
    events_path = tmp_path / "flight.fhr.events.txt"
    q = _LaggingQueue([], ["5.000 s MISSION -> LANDING: operator: land"])
    # the parent is not who the process was started by: the session died (kill -9)
    _telemetry_run(_NoRows(), _Writer(), q, str(events_path), _Set(), -1, None, None)  # type: ignore[arg-type]
    assert events_path.read_text() == "5.000 s MISSION -> LANDING: operator: land\n"

"""The frame clock every emulated MoCap server shares: a frame is captured every period and
sent ``latency_s`` after its capture, on the emulator's time (the wall clock in real time, the
simulated clock in lockstep). Callers hold their own lock around it."""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from typing import Generic, TypeVar

T = TypeVar("T")

#: a server that has not been called for this long (s) restarts its schedule at the present
#: instead of capturing every missed frame in one burst
STARVED_S = 0.25
_EPS_S = 1e-12


class CaptureSchedule(Generic[T]):
    """Captures due by a time, and the captured frames whose send time has come."""

    def __init__(self, period_s: float) -> None:
        self.period_s = period_s
        self._next_capture_s: float | None = None
        self._pending: deque[tuple[float, T]] = deque()

    def due(self, now_s: float, latency_s: float, capture: Callable[[], T | None]
            ) -> tuple[int, list[T]]:
        """Call ``capture`` for every frame due by ``now_s`` (a None result is a frame lost
        before sending) -> (frames captured, frames to send now, oldest first). The first call
        starts the schedule at ``now_s``."""
        if self._next_capture_s is None or now_s - self._next_capture_s > STARVED_S:
            self._next_capture_s = now_s
        captured = 0
        while self._next_capture_s <= now_s + _EPS_S:
            frame = capture()
            captured += 1
            if frame is not None:
                self._pending.append((now_s + latency_s, frame))
            self._next_capture_s += self.period_s
        send = []
        while self._pending and self._pending[0][0] <= now_s + _EPS_S:
            send.append(self._pending.popleft()[1])
        return captured, send

    def next_event_s(self) -> float:
        """Emulator time of the next capture or send (0 before the first call)."""
        nxt = self._next_capture_s if self._next_capture_s is not None else 0.0
        return min(nxt, self._pending[0][0]) if self._pending else nxt

"""The frame clock every emulated MoCap server shares: a frame is captured every period and
sent ``latency_s`` after its capture, on the emulator's time (the wall clock in real time, the
simulated clock in lockstep). Callers hold their own lock around it.

A lockstep server may defer its captures (``due(..., defer=True)``): a frame sent after a
latency is not needed on the wire at its capture time, so its capture (noise, packet encoding)
can run after the emulated board's reply went out, while the ground station computes. The
owner of the vehicle runs the deferred captures (:meth:`CaptureSchedule.capture_deferred`)
before the vehicle moves on, so each frame still holds the pose at its capture time."""

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
        #: captures due but deferred: (send time, capture), in capture order
        self._deferred: list[tuple[float, Callable[[], T | None]]] = []

    def due(self, now_s: float, latency_s: float, capture: Callable[[], T | None],
            defer: bool = False) -> tuple[int, list[T]]:
        """Call ``capture`` for every frame due by ``now_s`` (a None result is a frame lost
        before sending) -> (frames captured, frames to send now, oldest first). The first call
        starts the schedule at ``now_s``.

        ``defer``: when the frame goes out after a latency (> 0), ``capture`` is only noted and
        runs at :meth:`capture_deferred`, which must come before the vehicle moves on (it is
        run here first if it did not). Not counted as captured until then."""
        captured = self.capture_deferred()
        if self._next_capture_s is None or now_s - self._next_capture_s > STARVED_S:
            self._next_capture_s = now_s
        while self._next_capture_s <= now_s + _EPS_S:
            self._deferred.append((now_s + latency_s, capture))
            self._next_capture_s += self.period_s
        if not (defer and latency_s > _EPS_S):  # the frame is due now, or deferral not asked
            captured += self.capture_deferred()
        send = []
        while self._pending and self._pending[0][0] <= now_s + _EPS_S:
            send.append(self._pending.popleft()[1])
        return captured, send

    def capture_deferred(self) -> int:
        """Run the deferred captures (see :meth:`due`); returns how many ran."""
        if not self._deferred:
            return 0
        todo, self._deferred = self._deferred, []
        for send_s, capture in todo:
            frame = capture()
            if frame is not None:
                self._pending.append((send_s, frame))
        return len(todo)

    def next_event_s(self) -> float:
        """Emulator time of the next capture or send (0 before the first call)."""
        nxt = self._next_capture_s if self._next_capture_s is not None else 0.0
        if self._deferred:
            nxt = min(nxt, self._deferred[0][0])
        return min(nxt, self._pending[0][0]) if self._pending else nxt

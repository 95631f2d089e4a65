"""One policy for every way an operator (or the system) asks a session to stop.

SIGINT (Ctrl-C: the terminal sends it to the whole foreground process group), SIGTERM
(``timeout``, systemd, ``kill``) and SIGHUP (the terminal closed) all mean the same thing: the
first one lands the vehicle, a second one cuts the motors. The same signal again within
``REPEAT_WINDOW_S`` is the same request, not a second one: GNU ``timeout`` sends its signal to
the command and then to the command's process group, so the command gets it twice within
microseconds (a landing would otherwise become a cut 2 ms later); no operator presses Ctrl-C
twice that fast. SIGKILL cannot be caught: then the Flight-Ctrl's own watchdog stops the motors.

The handlers do the least a signal handler may: they count, remember the signal number and
append to a deque (an atomic operation that takes no lock), and the C-level wake-up byte of
:func:`signal.set_wakeup_fd` lets a thread blocked in :meth:`StopSignals.wait` see the signal at
once. They never take a lock: a handler runs on the main thread between two bytecodes, possibly
while that thread holds the very lock (``threading.Event.set`` would deadlock there).

The children of a session are arranged so that these signals reach only the ground station's
own process: the emulated vehicle runs in a session of its own, and the telemetry and servo
processes ignore them (the ground station stops them in order after the flight).

Job control would freeze a flight: Ctrl-Z (SIGTSTP, to the whole foreground group) stops the
process that commands the motors every tick, and the Flight-Ctrl's watchdog then stops them in
the air (seen: a realtime flight suspended at 0.8 m for 3.6 s fell, and ended "IMU stream lost"
on ``fg``). A flight session therefore refuses to be suspended (``flight``): Ctrl-Z is an
event for the operator, not a stop, and the children that the terminal stopped with it are
continued at once (they ignore it too once they run; the window is their start-up). SIGTTIN and
SIGTTOU, which stop a background job touching the terminal, are ignored: its writes then go
through. Ctrl-\\ (SIGQUIT, to the whole group) would kill the ground station and its children
by default, in the air, with the record cut short: in a flight it is one more stop signal,
landing first and cutting second, as Ctrl-C.
"""

from __future__ import annotations

import collections
import contextlib
import math
import os
import select
import signal
import time
from collections.abc import Callable, Iterator
from types import FrameType
from typing import Any

#: the signals that ask a session to stop (land first, then cut)
STOP_SIGNALS: tuple[signal.Signals, ...] = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
#: a flight's stop signals: also Ctrl-\ (its default action kills every process of the job)
FLIGHT_STOP_SIGNALS: tuple[signal.Signals, ...] = (*STOP_SIGNALS, signal.SIGQUIT)
#: job control: suspend (Ctrl-Z), and the stops of a background job at the terminal
JOB_CONTROL_SIGNALS: tuple[signal.Signals, ...] = (signal.SIGTSTP, signal.SIGTTIN,
                                                   signal.SIGTTOU)
#: the same stop signal again within this many seconds is one request (``timeout`` sends two)
REPEAT_WINDOW_S = 0.1
#: what a refused Ctrl-Z puts in the loop's request queue (the loop tells the operator)
SUSPEND_REFUSED = "suspend"


def ignore_stop_signals(*, flight: bool = False) -> None:
    """For a session's child processes: the ground station ends them, not the terminal;
    ``flight``: nor does Ctrl-\\ or Ctrl-Z reach them (a flight session's children).

    A child started inside :func:`stop_signals_blocked` has had them blocked since its first
    instruction (a signal mask survives ``exec``); once ignored they are unblocked, and any that
    arrived meanwhile are discarded."""
    for sig in (FLIGHT_STOP_SIGNALS + JOB_CONTROL_SIGNALS) if flight else STOP_SIGNALS:
        with contextlib.suppress(OSError, ValueError):
            signal.signal(sig, signal.SIG_IGN)
    with contextlib.suppress(OSError, ValueError):
        signal.pthread_sigmask(signal.SIG_UNBLOCK, STOP_SIGNALS)


@contextlib.contextmanager
def stop_signals_blocked(*, flight: bool = False) -> Iterator[None]:
    """Start child processes inside this block: they inherit a mask that holds the stop
    signals back until they ignore them (a spawned interpreter takes a second or more to get
    there, and a Ctrl-C in that window would kill it). The parent only defers them: a signal
    that arrives meanwhile is delivered to its handler when the block ends. The block ends
    with the mask it found, so that a block inside another one leaves them held.

    ``flight``: Ctrl-\\ and job control too, for a child that never unblocks them (a
    flight's Ctrl-\\ must not kill it, nor Ctrl-Z stop it)."""
    held = (FLIGHT_STOP_SIGNALS + JOB_CONTROL_SIGNALS) if flight else STOP_SIGNALS
    previous = signal.pthread_sigmask(signal.SIG_BLOCK, held)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)


class _Requests:
    """Which stop signals are requests: all but the same signal again within
    ``REPEAT_WINDOW_S`` of the request it repeats (the window runs from the request, not from
    each repeat)."""

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self._clock = clock
        self.last: int | None = None   # the signal of the newest request
        self._last_at_s = -math.inf

    def is_repeat(self, signum: int) -> bool:
        now = self._clock()
        if signum == self.last and now - self._last_at_s < REPEAT_WINDOW_S:
            return True
        self.last, self._last_at_s = signum, now
        return False


@contextlib.contextmanager
def stop_signals_interrupt() -> Iterator[None]:
    """Within: SIGTERM and SIGHUP raise ``KeyboardInterrupt`` in the main thread, as Ctrl-C
    does, so that a batch command (``sweep``, ``tune``) stops the same way whatever stopped it;
    the same signal again within ``REPEAT_WINDOW_S`` is the same stop (``timeout`` sends two),
    not a second interrupt in the middle of the first one's clean-up. The previous handlers
    are restored on the way out, except for the signal of a stop taken: the caller is ending
    (it returns once the interrupt is handled), and that signal is ignored from then on, so
    that a repeat arriving after the clean-up cannot kill the exit (SIGKILL still does)."""
    previous = {sig: signal.getsignal(sig) for sig in (signal.SIGTERM, signal.SIGHUP)}
    stops = _Requests()

    def interrupt(signum: int, frame: FrameType | None) -> None:
        if not stops.is_repeat(signum):
            raise KeyboardInterrupt

    for sig in previous:
        signal.signal(sig, interrupt)
    try:
        yield
    finally:
        for sig, handler in previous.items():
            # a stop was taken: the command is ending, and the repeat of its signal may come
            # after the clean-up (a command that stops fast), even during the interpreter's
            # exit, when Python has put back the default action: ignored from here on
            signal.signal(sig, signal.SIG_IGN if stops.last == sig else handler)


class StopSignals:
    """Installs the stop handlers on the main thread; a context manager restores the old ones.

    ``requests`` is the deque the flight loop takes operator requests from: each signal
    appends ``"stop"`` (the state machine lands on the first and cuts on the second), except
    the same signal repeated within ``REPEAT_WINDOW_S`` (counted, not a new request).

    ``flight``: SIGQUIT (Ctrl-\\) is a stop signal too; Ctrl-Z appends ``SUSPEND_REFUSED``
    instead of stopping the process, and continues the process group (children the terminal
    stopped with it); SIGTTIN and SIGTTOU are ignored (see the module doc)."""

    def __init__(self, requests: collections.deque[Any] | None = None,
                 clock: Callable[[], float] = time.monotonic, *,
                 flight: bool = False) -> None:
        self.requests: collections.deque[Any] = (requests if requests is not None
                                                 else collections.deque())
        self.count = 0
        #: the signal numbers received, in order (a fixed-size ring would do; a list of a
        #: few ints is all a session ever sees)
        self.received: list[int] = []
        self.repeats = 0  # signals taken as a repeat of the one before (REPEAT_WINDOW_S)
        self._requests = _Requests(clock)
        self.hangup = False  # SIGHUP: the terminal is gone, stop writing to it
        self.flight = flight
        self.suspends_refused = 0  # Ctrl-Z presses (SIGTSTP) taken as an event, not a stop
        self._previous: dict[int, Any] = {}
        self._rfd = self._wfd = -1
        self._previous_wakeup = -1

    # -- handlers ------------------------------------------------------------------------
    def _handler(self, signum: int, frame: FrameType | None) -> None:
        repeat = self._requests.is_repeat(signum)
        self.count += 1
        self.received.append(signum)
        if signum == signal.SIGHUP:
            self.hangup = True
        if repeat:
            self.repeats += 1
        else:
            self.requests.append("stop")

    def _suspend_handler(self, signum: int, frame: FrameType | None) -> None:
        self.suspends_refused += 1
        self.requests.append(SUSPEND_REFUSED)
        with contextlib.suppress(OSError):  # the children the terminal stopped with us
            os.killpg(os.getpgrp(), signal.SIGCONT)

    def install(self) -> StopSignals:
        self._rfd, self._wfd = os.pipe()
        os.set_blocking(self._rfd, False)
        os.set_blocking(self._wfd, False)
        self._previous_wakeup = signal.set_wakeup_fd(self._wfd, warn_on_full_buffer=False)
        for sig in FLIGHT_STOP_SIGNALS if self.flight else STOP_SIGNALS:
            self._previous[sig] = signal.signal(sig, self._handler)
        if self.flight:
            self._previous[signal.SIGTSTP] = signal.signal(signal.SIGTSTP,
                                                           self._suspend_handler)
            for sig in (signal.SIGTTIN, signal.SIGTTOU):
                self._previous[sig] = signal.signal(sig, signal.SIG_IGN)
        return self

    def restore(self) -> None:
        for sig, handler in self._previous.items():
            with contextlib.suppress(OSError, ValueError, TypeError):
                signal.signal(sig, handler)
        self._previous.clear()
        if self._wfd >= 0:
            with contextlib.suppress(ValueError):
                signal.set_wakeup_fd(self._previous_wakeup)
            for fd in (self._rfd, self._wfd):
                with contextlib.suppress(OSError):
                    os.close(fd)
            self._rfd = self._wfd = -1

    def __enter__(self) -> StopSignals:
        return self.install()

    def __exit__(self, *exc: object) -> None:
        self.restore()

    # -- queries -------------------------------------------------------------------------
    def wait(self, timeout_s: float) -> bool:
        """Block up to ``timeout_s`` or until a signal arrives; True if any was received."""
        if self.count:
            return True
        if self._rfd >= 0:
            with contextlib.suppress(InterruptedError, OSError):
                ready, _, _ = select.select([self._rfd], [], [], timeout_s)
                if ready:
                    with contextlib.suppress(BlockingIOError, OSError):
                        os.read(self._rfd, 512)
        return self.count > 0

    @property
    def names(self) -> list[str]:
        return [signal.Signals(s).name for s in self.received]

    def describe(self) -> str:
        """``"SIGTERM"``, ``"SIGINT, SIGINT"``: what was received, for the end reason."""
        return ", ".join(self.names)

"""The stop-signal policy (groundstation.signals): the first stop signal lands, a second cuts,
and the same signal repeated at once (GNU ``timeout`` sends it to the command and then to its
process group) is one request. Real signals sent to this process; the handler's clock is the
test's, so no assertion depends on how fast this host runs."""

from __future__ import annotations

import os
import signal
import subprocess
import sys

from groundstation.signals import REPEAT_WINDOW_S, StopSignals


class Clock:
    def __init__(self) -> None:
        self.t_s = 1000.0

    def __call__(self) -> float:
        return self.t_s


def test_that_the_same_signal_twice_at_once_is_one_stop_request() -> None:
    # Fixture
    clock = Clock()
    with StopSignals(clock=clock) as signals:
        # Test: what `timeout` does: the command, then its process group (here: both us)
        os.kill(os.getpid(), signal.SIGTERM)
        clock.t_s += 0.001
        os.kill(os.getpid(), signal.SIGTERM)
        # Assert: one request (land), the repeat counted
        assert list(signals.requests) == ["stop"]
        assert signals.count == 2 and signals.repeats == 1
        assert signals.describe() == "SIGTERM, SIGTERM"


def test_that_the_same_signal_after_the_window_is_a_second_request() -> None:
    clock = Clock()
    with StopSignals(clock=clock) as signals:
        os.kill(os.getpid(), signal.SIGINT)
        clock.t_s += REPEAT_WINDOW_S  # the operator presses Ctrl-C again
        os.kill(os.getpid(), signal.SIGINT)
        assert list(signals.requests) == ["stop", "stop"]  # land, then cut
        assert signals.repeats == 0


def test_that_different_signals_at_once_are_two_requests() -> None:
    # Ctrl-C and a SIGTERM from elsewhere are two requests, however close
    with StopSignals(clock=Clock()) as signals:
        os.kill(os.getpid(), signal.SIGINT)
        os.kill(os.getpid(), signal.SIGTERM)
        assert list(signals.requests) == ["stop", "stop"]


def test_that_repeats_do_not_stretch_the_window() -> None:
    # a signal every 0.6 windows: the third is 1.2 windows after the request, a new one
    clock = Clock()
    with StopSignals(clock=clock) as signals:
        for _ in range(3):
            os.kill(os.getpid(), signal.SIGHUP)
            clock.t_s += 0.6 * REPEAT_WINDOW_S
        assert list(signals.requests) == ["stop", "stop"]
        assert signals.repeats == 1


REFUSE_SUSPEND_CHILD = r"""
import os, signal
from groundstation.signals import StopSignals
TOUCHED = (signal.SIGTSTP, signal.SIGTTOU, signal.SIGTTIN, signal.SIGQUIT)
before = [signal.getsignal(x) for x in TOUCHED]  # a shell's `&` leaves SIGQUIT ignored
with StopSignals(flight=True) as s:
    ignored = [signal.getsignal(x) is signal.SIG_IGN for x in (signal.SIGTTIN, signal.SIGTTOU)]
    os.kill(os.getpid(), signal.SIGTSTP)  # Ctrl-Z: a process that obeyed would stop here
    os.kill(os.getpid(), signal.SIGTTOU)  # a background job's write to the terminal
    print(list(s.requests), s.suspends_refused, s.count, ignored)
    os.kill(os.getpid(), signal.SIGQUIT)  # Ctrl-\: by default a core dump
    print(list(s.requests), s.count, s.describe())
print([signal.getsignal(x) for x in TOUCHED] == before)
"""


def test_that_a_flight_refuses_ctrl_z_tells_the_loop_and_lands_on_ctrl_backslash() -> None:
    # In a child: a test process that failed to refuse would stop, not fail (the parent's
    # timeout then fails the test)
    out = subprocess.run([sys.executable, "-c", REFUSE_SUSPEND_CHILD], capture_output=True,
                         text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    # one event for the loop, not a stop request (count), the terminal stops ignored; all
    # put back afterwards
    assert out.stdout.splitlines() == ["['suspend'] 1 0 [True, True]",
                                       "['suspend', 'stop'] 1 SIGQUIT", "True"]


def test_that_ctrl_z_and_ctrl_backslash_are_left_alone_unless_a_flight_asks() -> None:
    before = signal.getsignal(signal.SIGTSTP), signal.getsignal(signal.SIGQUIT)
    with StopSignals():
        assert (signal.getsignal(signal.SIGTSTP), signal.getsignal(signal.SIGQUIT)) == before

"""The cross-process flag that replaces multiprocessing.Event where a process may die: setting
it never waits on anyone (drivers/shared_flag.py).

Real processes (spawn, as the session and the servo use), killed with SIGKILL while asleep in
the flag's wait.
"""

from __future__ import annotations

import multiprocessing as mp
import time

import pytest
from process_targets import set_flag_after_its_waiter_died, set_flag_later

from drivers.shared_flag import POLL_S, SharedFlag

CTX = mp.get_context("spawn")


@pytest.mark.parametrize(("kind", "returns"), [("flag", True), ("event", False)])
def test_that_setting_the_flag_never_waits_on_a_waiter_that_died(kind: str,
                                                                 returns: bool) -> None:
    # Fixture: a process waits on the flag and is killed in its wait (a session killed in
    # start-up, a servo process that crashed)
    ours, theirs = CTX.Pipe()
    prober = CTX.Process(target=set_flag_after_its_waiter_died, args=(kind, theirs))
    prober.start()
    try:
        # Test
        assert ours.poll(60.0) and ours.recv() == "dead"
        done = ours.poll(3.0)
        # Assert: the flag's set() returns at once; multiprocessing.Event's waits for ever for
        # the dead waiter to wake (the hang the flag is for: this case shows the fixture makes it)
        assert done is returns
    finally:
        prober.kill()
        prober.join()


def test_that_a_flag_set_in_another_process_is_seen_and_waited_for() -> None:
    flag = SharedFlag(CTX)
    assert not flag.is_set()
    # a wait without the flag lasts its timeout, give or take a poll
    t0 = time.monotonic()
    assert flag.wait(0.05) is False
    assert 0.05 <= time.monotonic() - t0 < 0.05 + 0.1
    # set by a child: the wait returns True soon after
    child = CTX.Process(target=set_flag_later, args=(flag, 0.2))
    child.start()
    assert flag.wait(60.0) is True
    child.join()
    assert flag.is_set() and flag.wait(0.0) is True and flag.wait() is True
    flag.clear()
    assert not flag.is_set() and flag.wait(0.0) is False
    assert POLL_S <= 0.01  # a stop is seen within 10 ms

"""A one-way flag shared between processes that no process can hang on, whoever dies.

``multiprocessing.Event`` is a condition variable: its ``set()`` wakes every process asleep in
``wait()`` and then waits, without a timeout, until each has woken and said so. A process that
died asleep in ``wait()`` (killed, crashed, out of memory) never says so, and ``set()`` blocks
for ever, holding the Event's lock, in a C call that no signal handler of ours ends. Seen: a
telemetry process left behind for good by a session killed during its start-up (the session had
died waiting for it); the same would hang a ground station that stops a servo process after that
process crashed, or a session whose telemetry process died before the session's ``go``.

:class:`SharedFlag` is one byte of shared memory and no lock: ``set()`` is a store, ``is_set()``
a load, ``wait()`` polls (at most :data:`POLL_S` late). It goes to a child as a
``Process`` argument, as an Event does.
"""

from __future__ import annotations

import ctypes
import time
from typing import Any

#: the longest ``wait`` sleeps between two looks at the flag
POLL_S = 0.005


class SharedFlag:
    """Set once (or cleared again) by any process; read and waited for by any other."""

    def __init__(self, ctx: Any) -> None:
        """``ctx``: a multiprocessing context (the flag's memory is made with it)."""
        self._value = ctx.RawValue(ctypes.c_bool, False)

    def set(self) -> None:
        self._value.value = True

    def clear(self) -> None:
        self._value.value = False

    def is_set(self) -> bool:
        return bool(self._value.value)

    def wait(self, timeout: float | None = None) -> bool:
        """True once the flag is set, False after ``timeout`` seconds (None: no limit)."""
        if self._value.value:
            return True
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            if deadline is None:
                time.sleep(POLL_S)
            else:
                left = deadline - time.monotonic()
                if left <= 0.0:
                    return bool(self._value.value)
                time.sleep(min(POLL_S, left))
            if self._value.value:
                return True

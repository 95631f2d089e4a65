"""Scheduler settings for the processes that serve a 500 Hz loop: the ground station and a
realtime emulated vehicle.

Linux lets a process (root, or a user with ``CAP_SYS_NICE`` / an ``rtprio`` limit) pin itself to
a CPU, run its threads under ``SCHED_FIFO`` (a CPU hog at normal priority can then no longer
delay an IMU sample by tens of milliseconds), lock its memory (no page fault in a tick) and freeze
the garbage collector. Each setting is tried on its own; a refused one is reported and the
process goes on without it: nothing here raises.

``SCHED_FIFO`` is applied to every thread that exists when it is called (on Linux the policy is
per thread; threads created later inherit it from their creator). It is safe for threads that
block on I/O, as every device thread here does; the kernel's real-time throttling keeps 5 % of
each CPU for everyone else.
"""

from __future__ import annotations

import contextlib
import ctypes
import gc
import os
import sys
from pathlib import Path

__all__ = ["apply_realtime_settings", "lock_memory", "restore_default_settings", "settings_line"]

_MCL_CURRENT, _MCL_FUTURE = 1, 2


def _thread_ids() -> list[int]:
    try:
        return sorted(int(t) for t in os.listdir("/proc/self/task"))
    except OSError:
        return [0]  # not Linux: the calling thread only


def apply_realtime_settings(*, cpu: int | None = None, fifo_priority: int = 50,
                            lock_memory: bool = True, freeze_gc: bool = True) -> dict[str, str]:
    """Try the settings of a real-time process; returns ``{setting: outcome}``.

    ``cpu``: the CPU to pin to (default the last one this process may use; ``-1`` leaves the
    affinity alone). ``fifo_priority`` 0 leaves the scheduler alone."""
    report: dict[str, str] = {}
    if cpu == -1:
        report["affinity"] = "unchanged"
    elif hasattr(os, "sched_setaffinity"):
        try:
            cpus = sorted(os.sched_getaffinity(0))
            target = cpu if cpu is not None else cpus[-1]
            for tid in _thread_ids():
                with contextlib.suppress(ProcessLookupError):
                    os.sched_setaffinity(tid, {target})
            report["affinity"] = f"pinned to CPU {target}"
        except OSError as exc:
            report["affinity"] = f"refused ({exc.strerror})"
    else:
        report["affinity"] = "not supported on this OS"
    if hasattr(os, "sched_setscheduler") and fifo_priority > 0:
        try:
            for tid in _thread_ids():
                with contextlib.suppress(ProcessLookupError):
                    os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(fifo_priority))
            report["scheduler"] = f"SCHED_FIFO priority {fifo_priority}"
        except OSError as exc:
            report["scheduler"] = (f"SCHED_FIFO refused ({exc.strerror}; needs root, "
                                   "CAP_SYS_NICE or an rtprio limit); SCHED_OTHER")
    else:
        report["scheduler"] = "SCHED_OTHER"
    if lock_memory:
        report["memory"] = _mlockall()
    if freeze_gc:
        gc.collect()
        gc.freeze()
        gc.disable()
        report["gc"] = "collected, frozen and disabled"
    return report


def lock_memory() -> str:
    """Lock every present and future page of the process in RAM (no page fault in a tick).
    Call it before the device threads start: ``mlockall`` holds the process's memory map for
    tens to hundreds of milliseconds, and every thread that touches a new page waits."""
    return _mlockall()


def _mlockall() -> str:
    if not sys.platform.startswith("linux"):
        return "not locked (not Linux)"
    try:
        libc = ctypes.CDLL("libc.so.6", use_errno=True)
    except OSError:
        return "not locked (no libc)"
    if libc.mlockall(_MCL_CURRENT | _MCL_FUTURE) != 0:
        err = ctypes.get_errno()
        return f"not locked ({os.strerror(err)}; needs root or a memlock limit)"
    return "locked (mlockall)"


def restore_default_settings() -> None:
    """Undo :func:`apply_realtime_settings`: GC on, SCHED_OTHER, memory unlocked."""
    gc.enable()
    gc.unfreeze()
    if hasattr(os, "sched_setscheduler"):
        for tid in _thread_ids():
            with contextlib.suppress(OSError):
                os.sched_setscheduler(tid, os.SCHED_OTHER, os.sched_param(0))
    if sys.platform.startswith("linux") and Path("/proc/self").exists():
        with contextlib.suppress(OSError, AttributeError):
            ctypes.CDLL("libc.so.6", use_errno=True).munlockall()


def settings_line(report: dict[str, str]) -> str:
    """One line for the operator: what took effect and what did not."""
    return "; ".join(f"{k}: {v}" for k, v in report.items())

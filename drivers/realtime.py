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

The CPU wake-up latency (Linux PM QoS, ``/dev/cpu_dma_latency``): a tick blocks on its serial
port between samples, and a CPU left idle meanwhile drops into an idle state (``hlt``; on a
virtual machine the host deschedules the virtual CPU) that costs a slow wake-up and leaves the
caches cold, so the tick that follows computes two to three times slower than the same code run
back to back. Writing 0 to that device and keeping it open holds every CPU in its shallowest
idle state (polling) while the request is open, as ``cyclictest`` and the ``latency-performance``
tuned profile do; the kernel drops the request when the file closes, also when the process
dies. Measured on a 2-CPU virtual machine: a lockstep flight 3.3-3.9x -> 5.1-6.1x real time,
tick compute p50 168-193 -> 116-139 us (``benchmarks/bench_speed.py`` measures it each run).
The cost: idle CPUs spin instead of sleeping while a flight runs; with no CPU ever idle (three
lockstep flights at once on two CPUs) it cannot help, and those flights took 5-10 % longer.
"""

from __future__ import annotations

import contextlib
import ctypes
import gc
import os
import struct
import sys
from pathlib import Path

__all__ = ["CPU_LATENCY_PATH", "apply_realtime_settings", "cpu_latency_us", "freeze_start_up_heap",
           "hold_cpu_latency", "lock_memory", "release_cpu_latency", "restore_default_settings",
           "settings_line"]

#: the PM QoS request file of the CPU wake-up latency (us, a native 32-bit integer)
CPU_LATENCY_PATH = Path("/dev/cpu_dma_latency")
#: the open request, if any: the kernel holds it as long as the file stays open
_cpu_latency_fd: int | None = None

_MCL_CURRENT, _MCL_FUTURE = 1, 2


def _thread_ids() -> list[int]:
    try:
        return sorted(int(t) for t in os.listdir("/proc/self/task"))
    except OSError:
        return [0]  # not Linux: the calling thread only


def hold_cpu_latency(max_us: int = 0, path: Path = CPU_LATENCY_PATH) -> str:
    """Ask the kernel to keep every CPU's wake-up latency at or below ``max_us`` (0: the CPUs
    poll when idle) until :func:`release_cpu_latency` or the end of the process. Returns the
    outcome for the operator: a system that refuses it is reported, not raised (a ``max_us``
    outside 0..2e9 is a programming error: ValueError). A second call replaces the first."""
    global _cpu_latency_fd
    if not 0 <= max_us <= 2_000_000_000:
        raise ValueError(f"max_us must be in 0..2000000000, got {max_us}")
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CLOEXEC)
    except FileNotFoundError:
        return f"unchanged (no {path}: not Linux, or no PM QoS)"
    except PermissionError as exc:
        return f"unchanged ({path}: {exc.strerror}; needs root)"
    except OSError as exc:
        return f"unchanged ({path}: {exc.strerror})"
    try:
        os.write(fd, struct.pack("=i", max_us))
    except OSError as exc:
        os.close(fd)
        return f"unchanged ({path}: {exc.strerror})"
    release_cpu_latency()
    _cpu_latency_fd = fd
    return f"wake-up latency held at {max_us} us ({path})"


def release_cpu_latency() -> None:
    """Drop the request of :func:`hold_cpu_latency` (nothing if none is held)."""
    global _cpu_latency_fd
    fd, _cpu_latency_fd = _cpu_latency_fd, None
    if fd is not None:
        with contextlib.suppress(OSError):
            os.close(fd)


def cpu_latency_us(path: Path = CPU_LATENCY_PATH) -> int | None:
    """The wake-up latency the kernel keeps now (us; the tightest of every open request, about
    2e9 when there is none); None where it cannot be read."""
    try:
        with open(path, "rb") as fh:
            data = fh.read(4)
    except OSError:
        return None
    return struct.unpack("=i", data)[0] if len(data) == 4 else None


def apply_realtime_settings(*, cpu: int | None = None, fifo_priority: int = 50,
                            lock_memory: bool = True, freeze_gc: bool = True,
                            cpu_latency: bool = True) -> dict[str, str]:
    """Try the settings of a real-time process; returns ``{setting: outcome}``.

    ``cpu``: the CPU to pin to (default the last one this process may use; ``-1`` leaves the
    affinity alone). ``fifo_priority`` 0 leaves the scheduler alone. ``cpu_latency``: hold the
    CPUs' wake-up latency at 0 (:func:`hold_cpu_latency`)."""
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
    if freeze_gc:  # after freeze_start_up_heap, only what came since is walked
        gc.collect()
        gc.freeze()
        gc.disable()
        report["gc"] = "collected, frozen and disabled"
    if cpu_latency:
        report["cpu idle"] = hold_cpu_latency(0)
    return report


def freeze_start_up_heap() -> None:
    """Collect the garbage of the start-up and freeze what is left (the imported modules, the
    devices), so that later collections, the one of :func:`apply_realtime_settings` included,
    walk only the objects made since. Call it before a device streams: a full collection holds
    the interpreter lock for tens of milliseconds (~70 ms in a ground station with its
    libraries imported), and a device thread cannot take or timestamp its samples meanwhile."""
    gc.collect()
    gc.freeze()


def thaw_start_up_heap() -> None:
    """Undo :func:`freeze_start_up_heap` (its objects collectable again): a process that goes
    on after the flight, e.g. a campaign flying the next run."""
    gc.unfreeze()


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
    """Undo :func:`apply_realtime_settings`: GC on, SCHED_OTHER, memory unlocked, the CPU
    wake-up latency released."""
    release_cpu_latency()
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

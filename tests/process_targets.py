"""Entry points of child processes started by tests ("spawn" imports them by module name, so
they live in this module on the tests' path, not inside a test module)."""

from __future__ import annotations

import time
from typing import Any

import numpy as np


def hammer_mailbox(mailbox: Any, count: int, done: Any) -> None:
    """Publish ``count`` servo states whose slots all hold the same number."""
    from drivers.dynamixel.device import _S

    values = [0.0] * int(_S.N)
    for i in range(1, count + 1):
        values[1:] = [float(i)] * (int(_S.N) - 1)
        mailbox.publish(values)
    done.set()


def read_ring(name: str, n_cols: int, expected: int, out: Any) -> None:
    """Drain a float telemetry ring until ``expected`` rows arrived (or 60 s)."""
    from groundstation.telemetry import TelemetryRing

    ring = TelemetryRing((np.float64, n_cols), capacity=64, name=name)
    got: list[np.ndarray] = []
    deadline = time.monotonic() + 60.0
    while sum(len(g) for g in got) < expected and time.monotonic() < deadline:
        rows = ring.drain()
        if len(rows):
            got.append(rows)
        else:
            time.sleep(0.001)
    ring.close()
    out.put(np.concatenate(got) if got else np.empty((0, n_cols)))


def run_or_die(spec: Any) -> dict[str, Any]:
    """A campaign run that kills its worker process when its seed is 13 (a segfault, the OOM
    killer), else the real run."""
    import os

    from groundstation.campaign import execute_run

    if spec.seed == 13:
        os._exit(9)
    return execute_run(spec)

"""The shared-memory telemetry ring: rows cross a process boundary intact and in order; a
reader that falls behind costs dropped rows, counted, never a blocked writer."""

from __future__ import annotations

import multiprocessing as mp

import numpy as np

from groundstation.telemetry import TelemetryRing


def _reader(name: str, n_cols: int, expected: int, out: mp.Queue) -> None:  # type: ignore[type-arg]
    ring = TelemetryRing(n_cols, capacity=64, name=name)
    got: list[np.ndarray] = []
    import time

    deadline = time.monotonic() + 60.0
    while sum(len(g) for g in got) < expected and time.monotonic() < deadline:
        rows = ring.drain()
        if len(rows):
            got.append(rows)
        else:
            time.sleep(0.001)
    ring.close()
    out.put(np.concatenate(got) if got else np.empty((0, n_cols)))


def test_that_rows_reach_another_process_in_order() -> None:
    ctx = mp.get_context("spawn")
    ring = TelemetryRing(5, capacity=64)
    q: mp.Queue = ctx.Queue()  # type: ignore[type-arg]
    proc = ctx.Process(target=_reader, args=(ring.name, 5, 40, q))
    proc.start()
    try:
        for k in range(40):
            while not ring.push(np.full(5, float(k))):
                pass  # only if the reader is a ring behind; it keeps up here
        rows = q.get(timeout=60)
    finally:
        proc.join(timeout=60)
        ring.close()
    np.testing.assert_array_equal(rows[:, 0], np.arange(40.0))
    np.testing.assert_array_equal(rows[:, 4], np.arange(40.0))


def test_that_a_full_ring_drops_and_counts_new_rows() -> None:
    ring = TelemetryRing(3, capacity=8)
    try:
        accepted = [ring.push(np.full(3, float(k))) for k in range(12)]
        assert accepted == [True] * 8 + [False] * 4
        assert ring.dropped == 4 and ring.written == 8
        np.testing.assert_array_equal(ring.drain()[:, 0], np.arange(8.0))
        assert ring.push(np.full(3, 99.0))
        np.testing.assert_array_equal(ring.drain(), [[99.0, 99.0, 99.0]])
        assert ring.drain().shape == (0, 3)
    finally:
        ring.close()


def test_that_attaching_with_the_wrong_width_is_refused() -> None:
    ring = TelemetryRing(3, capacity=8)
    try:
        try:
            TelemetryRing(4, capacity=8, name=ring.name)
        except ValueError as exc:
            assert "has 3 columns, not 4" in str(exc)
        else:
            raise AssertionError("expected ValueError")
    finally:
        ring.close()

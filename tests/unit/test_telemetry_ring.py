"""The shared-memory telemetry ring: rows cross a process boundary intact and in order; a
reader that falls behind costs dropped rows, counted, never a blocked writer."""

from __future__ import annotations

import multiprocessing as mp

import numpy as np
from process_targets import read_ring

from groundstation.telemetry import TelemetryRing


def test_that_rows_reach_another_process_in_order() -> None:
    ctx = mp.get_context("spawn")
    ring = TelemetryRing((np.float64, 5), capacity=64)
    q: mp.Queue = ctx.Queue()  # type: ignore[type-arg]
    proc = ctx.Process(target=read_ring, args=(ring.name, 5, 40, q))
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
    ring = TelemetryRing((np.float64, 3), capacity=8)
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
    ring = TelemetryRing((np.float64, 3), capacity=8)
    try:
        try:
            TelemetryRing((np.float64, 4), capacity=8, name=ring.name)
        except ValueError as exc:
            assert "has rows of 24 bytes, not 32" in str(exc)
        else:
            raise AssertionError("expected ValueError")
    finally:
        ring.close()


def test_that_flight_record_rows_pass_through_intact() -> None:
    from groundstation.record import RECORD_DTYPE, row_from_fields

    ring = TelemetryRing(RECORD_DTYPE, capacity=4)
    try:
        row = row_from_fields(t_s=1.5, segment=3, pos_w_m=(0.1, -0.2, 1.0),
                              spin_cmd_hz=(16.0, 20.0, 30.0, 40.0, 50.0, 102.0))
        assert ring.push(row)
        got = ring.drain()
        assert got.dtype == RECORD_DTYPE and len(got) == 1
        assert got["t_s"][0] == 1.5 and got["segment"][0] == 3
        np.testing.assert_allclose(got["pos_w_m"][0], (0.1, -0.2, 1.0), rtol=1e-6)
        np.testing.assert_allclose(got["spin_cmd_hz"][0], (16, 20, 30, 40, 50, 102))
    finally:
        ring.close()


def test_that_a_flat_row_is_packed_into_the_ring_as_numpy_would_store_it() -> None:
    # the loop's path (push_flat, no numpy in the tick) against numpy's conversion (push)
    from groundstation.record import RECORD_DTYPE, flat_row, row_from_fields

    rows = [row_from_fields(t_s=2.5 + k, segment=-1 + k, measured=bool(k), sat_mask=5 * k,
                            landed=k % 2, alpha_ref_rad=float("nan"),
                            pos_w_m=(0.1 * k, -2.0, 1e-9), q_wb=(0.5, 0.5, -0.5, 0.5),
                            spin_cmd_hz=(16.0, 20.5, 30.25, 40.0, 1e6, -3.0))
            for k in range(3)]
    flat, ref = TelemetryRing(RECORD_DTYPE, capacity=8), TelemetryRing(RECORD_DTYPE, capacity=8)
    try:
        for row in rows:
            assert flat.push_flat(flat_row(row))
            assert ref.push(row)
        huge = row_from_fields(t_s=9.0, pos_w_m=(1e39, -1e300, 0.0))   # beyond float32
        assert flat.push_flat(flat_row(huge))
        with np.errstate(over="ignore"):
            assert ref.push(huge)
        got = flat.drain()
        assert got.tobytes() == ref.drain().tobytes()
        assert np.isposinf(got["pos_w_m"][-1][0]) and np.isneginf(got["pos_w_m"][-1][1])
        for _ in range(8):                  # full: refused and counted as push does
            flat.push_flat(flat_row(rows[0]))
        assert not flat.push_flat(flat_row(rows[0])) and flat.dropped == 1
    finally:
        flat.close()
        ref.close()

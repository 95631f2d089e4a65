"""Telemetry out of the 500 Hz loop without slowing it: a shared-memory ring of fixed-size rows,
written by the loop and drained by a separate, lower-priority process.

The loop's cost per tick is one numpy row copy and one counter store (a few microseconds, no
allocation, no lock, no system call). The ring never blocks the writer: when the reader falls a
whole ring behind, new rows are dropped and counted (the flight record then shows the gap),
which never happens at the reader's normal pace of one drain per 20-100 ms.

Rows have one numpy dtype (the flight record's structured row, or plain float64 columns); the
loop assigns a row tuple straight into the shared slot (about 3.5 us for a flight-record row).
Layout of the shared block: a header of four int64 (write sequence, read sequence, dropped rows,
row size in bytes) followed by ``capacity`` rows. Single writer, single reader; the
writer stores the row first and the write sequence second, and the reader reads the sequence
before the rows below it. x86-64 keeps stores in program order, so the reader never sees a
half-written row there; on weakly ordered CPUs a row could in principle be read stale, which
telemetry tolerates (nothing read back from the ring feeds the control loop).

Low-rate events (state transitions, faults) travel in a separate bounded queue.
"""

from __future__ import annotations

import contextlib
import struct
from multiprocessing import shared_memory
from typing import Any

import numpy as np
import numpy.typing as npt

from groundstation.record import pack_row_into, row_struct

_HEADER = 4  # int64 slots: write_seq, read_seq, dropped, n_cols


class TelemetryRing:
    """Single-writer / single-reader ring of float64 rows in shared memory."""

    def __init__(self, dtype: npt.DTypeLike, capacity: int = 1 << 14, *,
                 name: str | None = None) -> None:
        """Create a ring (``name=None``) or attach to an existing one by ``name``.

        ``dtype`` is one row: e.g. ``RECORD_DTYPE`` or ``(np.float64, 30)``."""
        self._owner = name is None
        self.dtype = np.dtype(dtype)
        size = 8 * _HEADER + self.dtype.itemsize * capacity
        if self._owner:
            self._shm = shared_memory.SharedMemory(create=True, size=size)
        else:
            # Readers are children of the creator (multiprocessing "spawn"): they share its
            # resource tracker, so attaching registers nothing new and the creator unlinks.
            self._shm = shared_memory.SharedMemory(name=name)
        self._header = np.ndarray((_HEADER,), dtype=np.int64, buffer=self._shm.buf, offset=0)
        if self._owner:
            self._header[:] = (0, 0, 0, self.dtype.itemsize)
        elif int(self._header[3]) != self.dtype.itemsize:
            raise ValueError(f"ring {name} has rows of {int(self._header[3])} bytes, "
                             f"not {self.dtype.itemsize}")
        self._rows: npt.NDArray[Any] = np.ndarray((capacity,), dtype=self.dtype,
                                                  buffer=self._shm.buf, offset=8 * _HEADER)
        self.capacity = capacity
        self._layout: struct.Struct | None = None      # push_flat's packer, made on first use
        self._row0 = 8 * _HEADER

    @property
    def name(self) -> str:
        return self._shm.name

    # -- writer (the loop) -------------------------------------------------------------------
    def push(self, row: Any) -> bool:
        """Append one row; ``False`` (and counted) if the reader is a whole ring behind."""
        header = self._header
        seq = int(header[0])
        if seq - int(header[1]) >= self.capacity:
            header[2] += 1
            return False
        self._rows[seq % self.capacity] = row
        header[0] = seq + 1
        return True

    def push_flat(self, values: tuple[Any, ...]) -> bool:
        """:meth:`push` of one row given as its flat values (sub-arrays spelled out, in field
        order: :func:`groundstation.record.flat_row`), packed straight into the ring: half the
        cost of numpy converting a nested tuple, in the loop's tick."""
        layout = self._layout
        if layout is None:
            layout = self._layout = row_struct(self.dtype)
        header = self._header
        seq = header.item(0)
        if seq - header.item(1) >= self.capacity:
            header[2] += 1
            return False
        pack_row_into(layout, self.dtype, self._shm.buf,
                      self._row0 + (seq % self.capacity) * layout.size, values)
        header[0] = seq + 1
        return True

    @property
    def dropped(self) -> int:
        return int(self._header[2])

    @property
    def written(self) -> int:
        return int(self._header[0])

    # -- reader (the telemetry process) ------------------------------------------------------
    def drain(self) -> npt.NDArray[Any]:
        """Copy out every row written since the last drain (``k`` rows of the ring's dtype)."""
        end = int(self._header[0])
        start = int(self._header[1])
        if end == start:
            return np.empty((0,), dtype=self.dtype)
        idx = np.arange(start, end) % self.capacity
        rows = self._rows[idx].copy()
        self._header[1] = end
        return rows

    def close(self) -> None:
        """Detach; the creating side also frees the block."""
        # Views into the buffer must go before the mapping can close.
        del self._header, self._rows
        self._shm.close()
        if self._owner:
            with contextlib.suppress(FileNotFoundError):
                self._shm.unlink()

"""The flight record: one fixed-size binary row per control tick, written as the flight goes.

File layout (little-endian)::

    8 bytes   magic  b"FHXREC\\x00\\x01"
    4 bytes   uint32 N, length of the JSON header
    N bytes   UTF-8 JSON header: {"format": "fasthex.record", "version": 1,
              "dtype": numpy descr of one row, "row_bytes": int, "metadata": {...}}
    rows      back to back, each ``row_bytes`` long, fields as in :data:`RECORD_DTYPE`

Rows are buffered and written with one ``os.write`` every ``flush_rows`` ticks (50 = 100 ms at
500 Hz), so a crash or ``kill -9`` loses at most the last 100 ms; the reader ignores a trailing
partial row. Units and frames are in the field names: ``*_w_*`` world (z up), ``*_b_*`` body,
``q_*`` Hamilton quaternions (w, x, y, z) body/reference/desired -> world; ``*_ref_*`` the
mission's reference, ``q_wd`` the controller's desired attitude R_d, ``pos_w_m``/``q_wb``/... the
true state (simulation) or best estimate (hardware), ``est_*`` what the controller was fed.
``alpha_ref_rad`` is NaN while the tilt planner is in ``auto`` mode. ``sat_mask`` has bit i set
when rotor i+1's command was clamped; ``segment`` is the mission segment index and ``measured``
marks the experiment proper (not takeoff/landing).
"""

from __future__ import annotations

import json
import os
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

MAGIC = b"FHXREC\x00\x01"
FORMAT = "fasthex.record"
VERSION = 1
DEFAULT_FLUSH_ROWS = 50

RECORD_DTYPE = np.dtype([
    ("t_s", "<f8"),
    ("segment", "<i2"),
    ("measured", "u1"),
    ("sat_mask", "u1"),
    ("landed", "u1"),
    ("pos_ref_w_m", "<f4", (3,)),
    ("vel_ref_w_m_s", "<f4", (3,)),
    ("acc_ref_w_m_s2", "<f4", (3,)),
    ("q_wr", "<f4", (4,)),
    ("alpha_ref_rad", "<f4"),
    ("alpha_cmd_rad", "<f4"),
    ("alpha_rad", "<f4"),
    ("q_wd", "<f4", (4,)),
    ("pos_w_m", "<f4", (3,)),
    ("vel_w_m_s", "<f4", (3,)),
    ("q_wb", "<f4", (4,)),
    ("omega_b_rad_s", "<f4", (3,)),
    ("est_pos_w_m", "<f4", (3,)),
    ("est_q_wb", "<f4", (4,)),
    ("spin_cmd_hz", "<f4", (6,)),
    ("spin_hz", "<f4", (6,)),
    ("thrust_n", "<f4", (6,)),
    ("f_r_w_n", "<f4", (3,)),
    ("u_f_b_n", "<f4", (3,)),
    ("u_tau_b_n_m", "<f4", (3,)),
    ("r_xy_n", "<f4"),
    ("theta_rad", "<f4"),
    ("eta_f", "<f4"),
])

Rows = npt.NDArray[np.void]


_FIELD_NAMES: tuple[str, ...] = tuple(RECORD_DTYPE.names or ())
_FIELD_ZERO: dict[str, Any] = {
    name: (0.0,) * RECORD_DTYPE[name].shape[0] if RECORD_DTYPE[name].shape else 0
    for name in _FIELD_NAMES
}
_FIELD_ZERO.update({name: (1.0, 0.0, 0.0, 0.0) for name in ("q_wr", "q_wd", "q_wb",
                                                            "est_q_wb")})
_FIELD_ZERO["eta_f"] = 1.0


def row_struct(dtype: np.dtype[Any]) -> struct.Struct:
    """The packed little-endian layout of one row of ``dtype`` (scalars and 1-D sub-arrays of
    f8, f4, i2, u1, no padding): packing a flat row with it gives numpy's bytes."""
    codes = {"<f8": "d", "<f4": "f", "<i2": "h", "|u1": "B"}
    fmt = "<"
    for name in dtype.names or ():
        sub = dtype.fields[name][0]  # type: ignore[index]
        base = sub.base if sub.shape else sub
        fmt += codes[base.str] * (sub.shape[0] if sub.shape else 1)
    layout = struct.Struct(fmt)
    if layout.size != dtype.itemsize:
        raise ValueError(f"row dtype has padding ({dtype.itemsize} bytes, packed {layout.size})")
    return layout


#: one record row packed from its flat values (3-vectors spelled out, in field order)
ROW_STRUCT = row_struct(RECORD_DTYPE)
#: values per field in a flat row (1 for scalars)
_FIELD_WIDTHS: tuple[int, ...] = tuple(
    RECORD_DTYPE[name].shape[0] if RECORD_DTYPE[name].shape else 1 for name in _FIELD_NAMES)
FLAT_ROW_LEN = sum(_FIELD_WIDTHS)


def flat_row(row: tuple[Any, ...]) -> tuple[Any, ...]:
    """A nested row (sub-arrays as tuples) spelled out as the flat values of :data:`ROW_STRUCT`."""
    out: list[Any] = []
    for value, width in zip(row, _FIELD_WIDTHS, strict=True):
        if width == 1:
            out.append(value)
        else:
            out.extend(value)
    return tuple(out)


def nested_row(flat: tuple[Any, ...], dtype: np.dtype[Any] = RECORD_DTYPE) -> tuple[Any, ...]:
    """The inverse of :func:`flat_row`: sub-arrays regrouped as tuples, in field order."""
    out: list[Any] = []
    i = 0
    for name in dtype.names or ():
        shape = dtype[name].shape
        width = shape[0] if shape else 1
        out.append(flat[i] if not shape else tuple(flat[i:i + width]))
        i += width
    return tuple(out)


def pack_row_into(layout: struct.Struct, dtype: np.dtype[Any], buf: Any, offset: int,
                  values: tuple[Any, ...]) -> None:
    """Pack one flat row at ``offset`` of ``buf``; what the packer refuses (a float beyond
    float32's range, a float in an integer field) is converted by numpy as it would store it
    (a huge float becomes inf) or refused with numpy's error."""
    try:
        layout.pack_into(buf, offset, *values)
    except (struct.error, OverflowError, TypeError):
        with np.errstate(over="ignore", invalid="ignore"):
            data = np.array([nested_row(values, dtype)], dtype=dtype).tobytes()
        buf[offset:offset + len(data)] = data


def row_from_fields(**fields: Any) -> tuple[Any, ...]:
    """A row tuple from keyword fields (the others zero, quaternions identity).

    Convenient and checked (unknown names raise ``TypeError``), at ~5 us per row; the hot loop
    of the simulator builds its tuples directly in :data:`RECORD_DTYPE` order.
    """
    unknown = set(fields) - set(_FIELD_NAMES)
    if unknown:
        raise TypeError(f"unknown record fields: {', '.join(sorted(unknown))}")
    return tuple(fields.get(name, _FIELD_ZERO[name]) for name in _FIELD_NAMES)


class RecordFormatError(ValueError):
    """The file is not a flight record this version can read."""


@dataclass(frozen=True)
class FlightRecord:
    """A flight record in memory: the header's metadata and the rows (structured array)."""

    metadata: dict[str, Any]
    rows: Rows

    def __len__(self) -> int:
        return len(self.rows)


class RecordWriter:
    """Collects rows; with a path, appends them to the file every ``flush_rows`` rows.

    ``append`` takes one tuple in :data:`RECORD_DTYPE` field order (3-vectors as tuples).
    Rows are also kept in memory unless ``keep_in_memory`` is false.
    """

    def __init__(self, path: str | Path | None, metadata: dict[str, Any] | None = None, *,
                 flush_rows: int = DEFAULT_FLUSH_ROWS, keep_in_memory: bool = True) -> None:
        self.path = Path(path) if path is not None else None
        self.metadata = dict(metadata or {})
        self.flush_rows = max(1, flush_rows)
        self.keep_in_memory = keep_in_memory
        # rows packed as they come (ROW_STRUCT), written or kept every flush_rows rows
        self._row_bytes = RECORD_DTYPE.itemsize
        self._buf = bytearray(self.flush_rows * self._row_bytes)
        self._n = 0
        self._kept: list[Rows] = []
        self._fd: int | None = None
        self.rows_written = 0
        if self.path is not None:
            header = json.dumps({"format": FORMAT, "version": VERSION,
                                 "dtype": RECORD_DTYPE.descr,
                                 "row_bytes": RECORD_DTYPE.itemsize,
                                 "metadata": self.metadata}).encode()
            self._fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
            os.write(self._fd, MAGIC + struct.pack("<I", len(header)) + header)

    def append(self, row: tuple[Any, ...]) -> None:
        """One row in :data:`RECORD_DTYPE` field order, sub-arrays as tuples."""
        try:
            values = flat_row(row)
        except (TypeError, ValueError):
            # not the tuples flat_row expects (a scalar numpy broadcasts): numpy converts it,
            # or refuses it with its own error
            start = self._n * self._row_bytes
            self._buf[start:start + self._row_bytes] = np.array(
                [row], dtype=RECORD_DTYPE).tobytes()
            self._n += 1
            if self._n >= self.flush_rows:
                self.flush()
            return
        self.append_flat(values)

    def append_flat(self, values: tuple[Any, ...]) -> None:
        """One row as the flat values of :data:`ROW_STRUCT` (the simulator's hot loop)."""
        pack_row_into(ROW_STRUCT, RECORD_DTYPE, self._buf, self._n * self._row_bytes, values)
        self._n += 1
        if self._n >= self.flush_rows:
            self.flush()

    def append_block(self, rows: Rows) -> None:
        """Append many rows at once (a structured array of :data:`RECORD_DTYPE`)."""
        self.flush()
        self._write_block(np.asarray(rows, dtype=RECORD_DTYPE))

    def flush(self) -> None:
        if not self._n:
            return
        block = np.frombuffer(bytes(self._buf[:self._n * self._row_bytes]), dtype=RECORD_DTYPE)
        self._n = 0
        self._write_block(block)

    def _write_block(self, block: Rows) -> None:
        if self._fd is not None:
            data = block.tobytes()
            view = memoryview(data)
            while view:
                n = os.write(self._fd, view)
                view = view[n:]
        if self.keep_in_memory:
            self._kept.append(block)
        self.rows_written += len(block)

    def close(self) -> FlightRecord:
        """Flush, close the file and return what was recorded (empty rows if not kept)."""
        self.flush()
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None
        rows = np.concatenate(self._kept) if self._kept else np.zeros(0, RECORD_DTYPE)
        return FlightRecord(self.metadata, rows)

    def __enter__(self) -> RecordWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def read_record(path: str | Path) -> FlightRecord:
    """Read a record file (also one still being written, or cut short by a crash). Only a
    regular file: a device such as /dev/zero would be read for ever (into all the memory)."""
    p = Path(path)
    if p.exists() and not p.is_file():
        raise RecordFormatError(f"{path}: not a regular file (a folder, a device or a pipe)")
    return parse_record(p.read_bytes(), str(path))


def parse_record(data: bytes, path: str = "<bytes>") -> FlightRecord:
    """Parse the bytes of a record file; :class:`RecordFormatError` for anything else."""
    if len(data) < 12 or data[:8] != MAGIC:
        raise RecordFormatError(f"{path}: not a fasthex flight record (bad magic)")
    (n,) = struct.unpack("<I", data[8:12])
    try:
        header = json.loads(data[12:12 + n].decode())
        if not isinstance(header, dict) or header.get("format") != FORMAT \
                or header.get("version") != VERSION:
            raise RecordFormatError(f"{path}: unsupported record format/version")
        dtype = np.dtype([(f[0], f[1], tuple(f[2])) if len(f) > 2 else (f[0], f[1])
                          for f in header["dtype"]])
        metadata = dict(header.get("metadata", {}))
    except RecordFormatError:
        raise
    except (UnicodeDecodeError, ValueError, TypeError, KeyError, IndexError) as exc:
        raise RecordFormatError(f"{path}: corrupt record header ({exc})") from None
    if dtype.itemsize == 0 or 12 + n > len(data):
        raise RecordFormatError(f"{path}: corrupt record header (no rows described)")
    body = data[12 + n:]
    count = len(body) // dtype.itemsize
    rows = np.frombuffer(body[:count * dtype.itemsize], dtype=dtype)
    return FlightRecord(metadata, rows)

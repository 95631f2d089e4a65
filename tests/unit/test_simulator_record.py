"""The flight record (written incrementally, survives kill -9) and the phase-split metrics."""

from __future__ import annotations

import contextlib
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from controller.reference import quat_from_euler_zyx
from groundstation.metrics import flight_metrics, phase_masks
from groundstation.record import (
    MAGIC,
    RECORD_DTYPE,
    RecordFormatError,
    RecordWriter,
    parse_record,
    read_record,
    row_from_fields,
)


def _row(t: float, **kw: object) -> tuple[object, ...]:
    vals: dict[str, object] = {name: 0 for name in RECORD_DTYPE.names or ()}
    for name in RECORD_DTYPE.names or ():
        shape = RECORD_DTYPE[name].shape
        if shape:
            vals[name] = (0.0,) * shape[0]
    vals.update({"t_s": t, "q_wr": (1.0, 0, 0, 0), "q_wd": (1.0, 0, 0, 0),
                 "q_wb": (1.0, 0, 0, 0), "est_q_wb": (1.0, 0, 0, 0), "eta_f": 1.0,
                 "measured": 1, "spin_cmd_hz": (70.0,) * 6})
    vals.update(kw)
    return tuple(vals[n] for n in RECORD_DTYPE.names or ())


def test_that_a_record_round_trips_with_its_metadata(tmp_path: Path) -> None:
    # Fixture
    path = tmp_path / "flight.rec"
    # Test
    with RecordWriter(path, {"mission": "m", "seed": 3}) as w:
        for k in range(123):
            w.append(_row(k * 0.002, pos_w_m=(k, 2.0, 3.0)))
    rec = read_record(path)
    # Assert
    assert rec.metadata == {"mission": "m", "seed": 3}
    assert len(rec) == 123
    assert rec.rows["pos_w_m"][122] == pytest.approx((122.0, 2.0, 3.0))
    assert rec.rows["t_s"][-1] == pytest.approx(0.244)


def test_that_rows_reach_the_file_every_flush_period_while_flying(tmp_path: Path) -> None:
    # Fixture
    path = tmp_path / "flight.rec"
    w = RecordWriter(path, flush_rows=50)
    # Test: 120 rows, not closed
    for k in range(120):
        w.append(_row(k * 0.002))
    on_disk = read_record(path)
    # Assert: at most the last 50 rows (100 ms at 500 Hz) are pending
    assert len(on_disk) == 100
    assert len(w.close()) == 120


def test_that_a_kill_9_loses_at_most_the_last_100_ms(tmp_path: Path) -> None:
    # Fixture: a writer process that kills itself without any cleanup
    path = tmp_path / "killed.rec"
    script = (
        "import os, signal\n"
        "from groundstation.record import RecordWriter, RECORD_DTYPE\n"
        "import numpy as np\n"
        f"w = RecordWriter({str(path)!r}, {{'x': 1}})\n"
        "row = np.zeros(1, RECORD_DTYPE)[0].item()\n"
        "for k in range(1234):\n"
        "    w.append((k * 0.002,) + row[1:])\n"
        "os.kill(os.getpid(), signal.SIGKILL)\n"
    )
    # Test
    proc = subprocess.run([sys.executable, "-c", script], check=False, timeout=120)
    rec = read_record(path)
    # Assert
    assert proc.returncode == -9
    assert 1234 - 50 < len(rec) <= 1234
    assert rec.rows["t_s"][-1] == pytest.approx((len(rec) - 1) * 0.002)


def test_that_a_partial_last_row_is_ignored(tmp_path: Path) -> None:
    path = tmp_path / "cut.rec"
    with RecordWriter(path) as w:
        for k in range(10):
            w.append(_row(k * 0.002))
    data = path.read_bytes()
    assert len(parse_record(data[:-7])) == 9


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=400), st.booleans())
def test_that_random_bytes_never_raise_anything_but_a_format_error(data: bytes,
                                                                   magic: bool) -> None:
    blob = (MAGIC + data) if magic else data
    with contextlib.suppress(RecordFormatError):
        parse_record(blob)


def _flight(alpha_deg: list[float], ref_deg: list[float], **kw: object) -> np.ndarray:
    rows = [_row(k * 0.002, alpha_rad=math.radians(a), alpha_ref_rad=math.radians(r), **kw)
            for k, (a, r) in enumerate(zip(alpha_deg, ref_deg, strict=True))]
    return np.array(rows, dtype=RECORD_DTYPE)


def test_that_phases_skip_two_seconds_after_entry_and_after_alpha_steps() -> None:
    # Fixture: 10 s at 0 deg, step to 30 deg at 10 s, tilt reaches 30 deg at 13 s
    n = 10_000
    t = np.arange(n) * 0.002
    ref = np.where(t >= 10.0, 30.0, 0.0)
    alpha = np.clip((t - 10.0) * 10.0, 0.0, 30.0)
    rows = _flight(list(alpha), list(ref))
    # Test
    masks = phase_masks(rows)
    # Assert
    udt_t, mdt_t = t[masks["udt"]], t[masks["mdt"]]
    assert udt_t[0] == pytest.approx(2.0) and udt_t[-1] < 10.1  # UDT: 2 .. 10.1 s
    assert mdt_t[0] == pytest.approx(14.002, abs=0.003)  # > 20 deg from 12 s, + 2 s settle
    assert masks["all"].all()


def test_that_the_metrics_measure_what_they_say() -> None:
    # Fixture: 5 mm off in y, rolled 1 deg, R_d pitched 2 deg, one rotor saturated
    q_b = quat_from_euler_zyx(math.radians(1.0), 0.0, 0.0)
    q_d = quat_from_euler_zyx(0.0, math.radians(2.0), 0.0)
    rows = _flight([30.0] * 2000, [30.0] * 2000, pos_w_m=(0.0, 0.005, 0.0), q_wb=q_b,
                   q_wd=q_d, sat_mask=1, eta_f=0.87)
    # Test
    m = flight_metrics(rows, min_spin_hz=16.0, max_spin_hz=102.0)
    # Assert
    assert m["all_pos_err_mean_mm"] == pytest.approx(5.0, rel=1e-5)
    assert m["all_roll_err_mean_deg"] == pytest.approx(1.0, rel=1e-4)
    assert m["all_pitch_err_mean_deg"] == pytest.approx(0.0, abs=1e-4)
    assert m["all_rd_dev_mean_deg"] == pytest.approx(2.0, rel=1e-3)
    assert m["all_inner_err_mean_deg"] == pytest.approx(math.sqrt(5.0), rel=1e-3)
    assert m["all_spin_saturated_frac"] == 1.0
    assert m["all_internal_force_loss_mean_frac"] == pytest.approx(0.13, rel=1e-5)
    assert m["all_spin_within_limits"] == 1.0
    assert m["udt_ticks"] == 0 and math.isnan(m["udt_pos_err_mean_mm"])
    assert m["mdt_ticks"] == 2000 - 1000  # the first 2 s of the phase are skipped


def test_that_rows_can_be_built_from_named_fields() -> None:
    # Test
    row = np.array([row_from_fields(t_s=1.5, pos_w_m=(1.0, 2.0, 3.0), segment=2)],
                   dtype=RECORD_DTYPE)[0]
    # Assert
    assert row["t_s"] == 1.5 and row["segment"] == 2
    assert tuple(row["pos_w_m"]) == (1.0, 2.0, 3.0)
    assert tuple(row["q_wb"]) == (1.0, 0.0, 0.0, 0.0)
    with pytest.raises(TypeError, match="pos_m"):
        row_from_fields(pos_m=(0, 0, 0))


def test_that_packed_rows_are_the_bytes_numpy_writes(tmp_path: Path) -> None:
    # the writer packs rows itself (nested or flat); a row the packer refuses (a float
    # segment, a numpy scalar flag) goes through numpy: the file holds numpy's bytes
    from groundstation.record import flat_row

    rows = [_row(0.002 * k, segment=k - 1, sat_mask=k, landed=k % 2, alpha_ref_rad=math.nan,
                 pos_w_m=(0.1 * k, -1.0, 1e-9), spin_hz=(1e6, -2.0, 0.5, 0.0, 70.0, 71.0))
            for k in range(7)]
    rows.append(_row(0.016, segment=2.0, measured=np.bool_(True)))
    rows.append(_row(0.018, pos_w_m=(1e39, -1e300, 0.0)))      # beyond float32: inf
    path = tmp_path / "r.fhr"
    with RecordWriter(path, flush_rows=3) as w:
        for k, row in enumerate(rows):
            if k % 2:
                w.append(row)
            else:
                w.append_flat(flat_row(row))
    got = read_record(path).rows
    with np.errstate(over="ignore"):
        assert got.tobytes() == np.array(rows, dtype=RECORD_DTYPE).tobytes()
    assert np.isposinf(got["pos_w_m"][-1][0]) and np.isneginf(got["pos_w_m"][-1][1])


def test_that_only_a_regular_file_is_read_as_a_record(tmp_path: Path) -> None:
    # a device is read for ever (/dev/zero: into all the memory); a folder is no record
    for path in (Path("/dev/null"), tmp_path):
        with pytest.raises(RecordFormatError) as err:
            read_record(path)
        assert str(err.value) == f"{path}: not a regular file (a folder, a device or a pipe)"


def test_that_a_truth_merge_that_cannot_write_leaves_the_record_and_no_stray_file(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import errno

    from groundstation.record import RECORD_DTYPE, RecordWriter
    from groundstation.session import merge_truth

    # Fixture: a record of 10 rows and a truth log of 10 samples
    record = tmp_path / "f.fhr"
    writer = RecordWriter(record, {"source": "test"}, keep_in_memory=False)
    rows = np.zeros(10, dtype=RECORD_DTYPE)
    rows["t_s"] = np.arange(10) / 500.0
    writer.append_block(rows)
    writer.close()
    before = record.read_bytes()
    truth = np.zeros((10, 14))
    truth[:, 0] = np.arange(10) / 500.0
    truth[:, 7] = 1.0
    truth.tofile(tmp_path / "truth.f64")

    def full_disk(self: RecordWriter, block: object) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(RecordWriter, "append_block", full_disk)
    # Test
    with pytest.raises(OSError):
        merge_truth(record, tmp_path / "truth.f64", 500.0)
    # Assert: the flight's own record unchanged, no .tmp beside it
    assert record.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f.fhr", "truth.f64"]

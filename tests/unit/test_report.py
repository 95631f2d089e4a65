"""The report's signals, figure and metrics table, and the event-line parser of the dashboard."""

from __future__ import annotations

import itertools
import json
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from groundstation.cli import main as cli_main
from groundstation.dashboard import parse_events
from groundstation.metrics import flight_metrics
from groundstation.record import RECORD_DTYPE, RecordWriter, row_from_fields
from groundstation.report import (
    FULL,
    MDT,
    UDT,
    actuation_state,
    metrics_json,
    metrics_markdown,
    panel_signals,
    phase_spans,
    render_figure,
    write_report,
)


def _quat_zyx(roll: float, pitch: float, yaw: float) -> tuple[float, float, float, float]:
    """(w, x, y, z) of Rz(yaw) Ry(pitch) Rx(roll)."""
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return (cr * cp * cy + sr * sp * sy, sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy)


def _rows(n: int = 6000, split: int = 3000) -> np.ndarray:
    """A synthetic hover: alpha 0 for ``split`` ticks, then 30 deg; a constant 3 mm x error."""
    rows = []
    for k in range(n):
        alpha = 0.0 if k < split else math.radians(30.0)
        rows.append(row_from_fields(
            t_s=k * 0.002, measured=1, pos_ref_w_m=(0.0, 0.0, 1.0), pos_w_m=(0.003, 0.0, 1.0),
            alpha_rad=alpha, alpha_cmd_rad=alpha, alpha_ref_rad=alpha,
            q_wb=_quat_zyx(math.radians(2.0), math.radians(-1.0), math.radians(5.0)),
            spin_hz=(70.0,) * 6, spin_cmd_hz=(70.0,) * 6, u_f_b_n=(3.0, 4.0, 20.0),
            r_xy_n=0.0 if k < split else 5.3, eta_f=1.0 if k < split else 0.87,
            sat_mask=0b100101 if k == 10 else 0))
    return np.array(rows, dtype=RECORD_DTYPE)


def test_that_panel_signals_recover_the_euler_angles_and_errors_of_a_known_attitude() -> None:
    s = panel_signals(_rows(10, 5))
    np.testing.assert_allclose(s.eul_deg[0], [2.0, -1.0, 5.0], atol=1e-4)
    # the reference is level: the attitude error is the attitude itself
    np.testing.assert_allclose(s.att_err_deg[0], [2.0, -1.0, 5.0], atol=1e-4)
    np.testing.assert_allclose(s.eul_ref_deg, 0.0, atol=1e-9)
    np.testing.assert_allclose(s.pos_err_mm[:, 0], 3.0, rtol=1e-5)
    np.testing.assert_allclose(s.pos_err_norm_mm, 3.0, rtol=1e-5)
    np.testing.assert_allclose(s.lat_force_n, 5.0, rtol=1e-6)  # |(3, 4)|


def test_that_saturated_rotors_are_counted_from_the_mask() -> None:
    s = panel_signals(_rows(20, 5))
    assert s.sat_count[10] == 3
    assert s.sat_count.sum() == 3


def test_that_the_actuation_state_uses_the_metric_phase_thresholds() -> None:
    alpha = np.array([0.0, 0.99, 1.0, 10.0, 20.0, 20.01, 35.0, -30.0])
    assert actuation_state(alpha).tolist() == [UDT, UDT, FULL, FULL, FULL, MDT, MDT, MDT]


def test_that_phase_spans_cover_the_flight_without_gaps() -> None:
    t = np.arange(10) * 0.5
    spans = phase_spans(t, np.array([0, 0, 0, 1, 1, 2, 2, 2, 0, 0]))
    assert [s[2] for s in spans] == [0, 1, 2, 0]
    assert spans[0][0] == 0.0 and spans[-1][1] == 4.5
    for (_, end, _), (start, _, _) in itertools.pairwise(spans):
        assert end == start
    assert phase_spans(np.zeros(0), np.zeros(0, dtype=np.int64)) == []


def test_that_the_markdown_table_holds_every_metric_value() -> None:
    metrics = flight_metrics(_rows(), min_spin_hz=16.0, max_spin_hz=102.0)
    md = metrics_markdown(metrics, "synthetic")
    for key in metrics:
        assert key.split("_", 1)[1] in md or key in md, key
    assert "| pos_err_mean_mm | 3 | 3 | 3 |" in md
    assert md.startswith("## synthetic")
    # NaN (no MDT ticks) is written as null in JSON, as simulate --json does
    short = flight_metrics(_rows(1500, 3000))
    assert metrics_json(short)["mdt_pos_err_mean_mm"] is None


def test_that_the_figure_has_red_under_actuated_and_green_fully_actuated_background(
        tmp_path: Path) -> None:
    import matplotlib.image as mpimg

    path = render_figure(_rows(), tmp_path / "plots.png", title="synthetic",
                         min_spin_hz=16.0, max_spin_hz=102.0)
    img = mpimg.imread(path)[..., :3]
    h, w = img.shape[:2]
    assert h > 1.3 * w  # eight stacked panels: a tall figure
    # the shading colours (red #d62728 / green #2ca02c at low alpha over white)
    left = img[int(0.1 * h):int(0.9 * h), int(0.15 * w):int(0.45 * w)].reshape(-1, 3)
    right = img[int(0.1 * h):int(0.9 * h), int(0.6 * w):int(0.9 * w)].reshape(-1, 3)

    def frac(px: np.ndarray, red: bool) -> float:
        r, g, b = px[:, 0], px[:, 1], px[:, 2]
        hit = (r > g + 0.05) & (r > b + 0.05) if red else (g > r + 0.03) & (g > b + 0.03)
        return float(np.mean(hit))

    assert frac(left, red=True) > 0.5 > frac(left, red=False)
    assert frac(right, red=False) > 0.5 > frac(right, red=True)


def test_that_write_report_writes_figure_and_metrics_equal_to_flight_metrics(
        tmp_path: Path) -> None:
    record = tmp_path / "synthetic.fhr"
    with RecordWriter(record, {"mission": "synthetic", "vehicle": "fasthex"}) as w:
        for row in _rows().tolist():
            w.append(row)
    files = write_report(record, tmp_path / "out")
    assert files.figure.stat().st_size > 10_000
    on_disk = json.loads(files.metrics_json.read_text())
    expected = metrics_json(flight_metrics(_rows(), min_spin_hz=16.0, max_spin_hz=102.0))
    assert set(on_disk) == set(expected)
    for key, value in expected.items():
        assert on_disk[key] == pytest.approx(value, rel=1e-9, nan_ok=True) if value is not None \
            else on_disk[key] is None, key


def test_that_report_on_a_file_that_is_not_a_record_is_a_user_error(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "notes.txt"
    bad.write_text("not a record")
    assert cli_main(["report", str(bad)]) == 2
    assert "not a fasthex flight record" in capsys.readouterr().err
    assert cli_main(["report", str(tmp_path / "missing.fhr")]) == 2


def test_that_report_on_a_record_without_rows_is_a_user_error(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # Fixture: a record cut to its header (a flight that wrote no row)
    record = tmp_path / "empty.fhr"
    RecordWriter(record, {"mission": "synthetic", "vehicle": "fasthex"}).close()
    # Test
    code = cli_main(["report", str(record)])
    # Assert: one line, and no report folder left behind
    assert code == 2
    assert capsys.readouterr().err == (f"fasthex: {record}: the record has no rows (a header "
                                       "only); nothing to report\n")
    assert not (tmp_path / "empty.fhr.report").exists()


def test_that_report_out_in_a_bad_place_is_one_line_before_any_work(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # Fixture: a record, a regular file, a path under it, and a folder the kernel refuses
    record = tmp_path / "flight.fhr"
    with RecordWriter(record, {"mission": "synthetic", "vehicle": "fasthex"}) as w:
        for row in _rows(10, 5).tolist():
            w.append(row)
    empty = tmp_path / "empty.fhr"
    RecordWriter(empty, {"mission": "synthetic", "vehicle": "fasthex"}).close()
    afile = tmp_path / "afile"
    afile.write_text("notes")
    # Test / Assert: one line each, exit 2 (they were FileExistsError, NotADirectoryError and
    # FileNotFoundError tracebacks, exit 1)
    for out, why in ((afile, "is a file; expected a folder for the report"),
                     (afile / "sub", "cannot create the report folder (Not a directory); "
                                     "expected a folder path"),
                     (Path("/proc/rep"), "cannot create the report folder (No such file or "
                                         "directory); expected a folder path")):
        assert cli_main(["report", str(record), "--out", str(out)]) == 2
        assert capsys.readouterr().err == f"fasthex: --out {out}: {why}\n"
    assert afile.read_text() == "notes"
    # a missing folder (and its parents) is made, and removed again with a refused record
    assert cli_main(["report", str(empty), "--out", str(tmp_path / "a" / "b")]) == 2
    assert "the record has no rows" in capsys.readouterr().err
    assert not (tmp_path / "a").exists()
    assert cli_main(["report", str(record), "--out", str(tmp_path / "a" / "b")]) == 0
    assert (tmp_path / "a" / "b" / "plots.png").is_file()


def test_that_event_lines_are_parsed_with_their_flight_time() -> None:
    text = ("flight-ctrl: tk3 firmware mkfl1.8 on /dev/x\n"
            "1.000 s PREFLIGHT -> ARMED: operator: arm\n"
            "\n"
            "FAULT mocap lost\n"
            "11.624 s LANDING -> DISARMED: touchdown\n")
    assert parse_events(text) == [
        (0.0, "flight-ctrl: tk3 firmware mkfl1.8 on /dev/x"),
        (1.0, "PREFLIGHT -> ARMED: operator: arm"),
        (1.0, "FAULT mocap lost"),
        (11.624, "LANDING -> DISARMED: touchdown"),
    ]


@given(st.text())
def test_that_any_text_parses_into_events_without_raising(text: str) -> None:
    events = parse_events(text)
    assert all(math.isfinite(t) and isinstance(s, str) and s for t, s in events)


@given(st.binary())
def test_that_any_bytes_decoded_leniently_parse_without_raising(data: bytes) -> None:
    parse_events(data.decode("utf-8", errors="replace"))


def test_that_a_dashboard_error_switches_the_dashboard_off_instead_of_raising(
        tmp_path: Path) -> None:
    from groundstation.dashboard import Dashboard

    dash = Dashboard("save", tmp_path / "x.rrd")
    dash.log_rows(_rows(100, 50))
    bad = np.zeros(3, dtype=[("t_s", "<f8")])  # not a flight-record row
    dash.log_rows(bad)
    assert dash.error is not None and dash.error.startswith("log_rows")
    dash.log_rows(_rows(100, 50))  # off now: counted, not shipped, no exception
    dash.log_event(1.0, "still fine")
    dash.close()
    assert dash.rows_logged == 203

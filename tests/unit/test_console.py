"""The operator's surface without a flight: the console's line discipline, the summary text,
JSON rounding, ``--version``, ``fly --help`` and where a record goes."""

from __future__ import annotations

import io
import json
import math
import re
from pathlib import Path

import pytest
from terminal_support import screen

from config import available
from groundstation.cli import main as cli_main
from groundstation.commands.fly import record_path
from groundstation.console import Console, number
from groundstation.metrics import rounded
from groundstation.summary import json_ready, summary_text


def test_that_unknown_values_are_shown_as_placeholders() -> None:
    assert number(math.nan, "5.1f", "mm") == "-- mm"
    assert number(math.inf, "5.2f", "V") == "-- V"
    assert number(None, ".1f") == "--"
    assert number(16.4, "5.2f", "V") == "16.40 V"


def test_that_console_events_never_share_a_line_with_the_status_and_the_status_is_erased(
) -> None:
    # Fixture
    out = io.StringIO()
    status = ["MISSION    12.0 s  pos. error   5.0 mm"]
    sut = Console(out, live=True, status=lambda: status[0], refresh_s=0.01)
    # Test
    sut._flush(show_status=True)
    sut.event("12.000 s TAKEOFF -> MISSION: takeoff complete")
    status[0] = "MISSION    12.5 s  pos. error   4.0 mm"
    sut._flush(show_status=True)
    sut.event("13.000 s MISSION -> LANDING: mission complete")
    sut.stop()
    # Assert
    assert screen(out.getvalue()) == ["12.000 s TAKEOFF -> MISSION: takeoff complete",
                                       "13.000 s MISSION -> LANDING: mission complete"]


def test_that_without_a_terminal_the_console_prints_plain_event_lines_only() -> None:
    out = io.StringIO()
    sut = Console(out, status=lambda: "MISSION status")  # StringIO is not a terminal
    sut.event("a")
    sut.event("b")
    sut._flush(show_status=True)
    sut.stop()
    assert out.getvalue() == "a\nb\n"


@pytest.mark.parametrize(("key", "value", "expected"), [
    ("all_ticks", 35000.0, 35000),
    ("all_spin_within_limits", 1.0, 1),
    ("all_duration_s", 69.9999999999923, 70.0),
    ("all_pos_err_mean_mm", 5.04912345, 5.05),
    ("all_roll_err_mean_deg", 0.15312345, 0.153),
    ("compute_p50_ms", 0.58912345, 0.589),
    ("all_spin_min_hz", 58.90812, 58.91),
    ("all_spin_saturated_frac", 0.000012, 0.0),
    ("all_pos_err_mean_mm", math.nan, None),
    ("deadline_misses", 2264, 2264),
    ("end_reason", "touchdown", "touchdown"),
])
def test_that_json_values_are_integers_or_rounded_to_their_resolution(
        key: str, value: object, expected: object) -> None:
    out = rounded(key, value)
    assert out == expected and type(out) is type(expected)


def test_that_json_rounding_keeps_every_key_and_goes_into_lists_and_dicts() -> None:
    summary = {"ticks": 10, "faults": [], "preflight": [{"check": "x", "pass": True,
                                                         "value": "1"}],
               "mavlink_commands": {"arm": 2}, "all_duration_s": 1.00000001}
    out = json_ready(summary)
    assert list(out) == list(summary)
    assert json.loads(json.dumps(out))["all_duration_s"] == 1.0
    assert out["preflight"] == summary["preflight"]


def _summary() -> dict[str, object]:
    base: dict[str, object] = {
        "session": "exp1-emulated", "end_reason": "touchdown", "ticks": 43484,
        "flight_time_s": 85.0, "wall_time_s": 61.6, "deadline_misses": 12,
        "compute_p50_ms": 0.3, "compute_p99_ms": 0.8, "period_p50_ms": 2.0,
        "jitter_p99_ms": 0.2, "latency_p50_ms": 0.3, "latency_p99_ms": 0.8, "faults": [],
        "transitions": [], "poses_rejected": 8, "fusion_delay_ms": 8.0,
        "telemetry_dropped": 0, "imu_gap_max_ms": 0.0, "imu_gap_max_at_s": 0.0,
        "imu_waits_empty": 0, "record": "flights/x.fhr",
        "preflight": [{"check": "estimator converged", "pass": True, "value": "flags OK"}],
        "state_source": "true state of the emulated vehicle"}
    for phase in ("all", "udt", "mdt"):
        for key in ("ticks", "duration_s", "pos_err_mean_mm", "pos_err_max_mm",
                    "roll_err_mean_deg", "pitch_err_mean_deg", "yaw_err_mean_deg",
                    "rd_dev_mean_deg", "rd_dev_max_deg", "inner_err_mean_deg", "spin_min_hz",
                    "spin_max_hz", "spin_saturated_frac", "internal_force_loss_mean_frac"):
            base[f"{phase}_{key}"] = math.nan if phase == "mdt" else 1.25
    base["all_spin_within_limits"] = 1.0
    return base


def test_that_the_summary_is_a_table_with_units_and_no_raw_keys() -> None:
    text = summary_text(_summary(), clock="lockstep", dashboard_mode="auto-headless")
    assert text.count("session ended:") == 1
    assert not re.search(r"\b(all|udt|mdt)_\w+", text)  # no raw metric keys
    assert not re.search(r"\b(nan|inf)\b", text)
    assert re.search(r"position error, mean\s+mm\s+1\.25\s+1\.25\s+--", text)
    assert "under-actuated" in text and "R_d off reference" in text
    assert "none (--rerun auto and no display)" in text
    assert "fasthex report flights/x.fhr" in text
    assert "lockstep: the simulated clock waits" in text
    assert max(len(line) for line in text.splitlines()) <= 79  # an 80-column terminal


def test_that_the_tick_count_is_not_read_as_ticks_of_flight() -> None:
    # 43484 ticks at 500 Hz are 87.0 s of session (preflight and arming included), while the
    # flight (from take-off) lasted 85.0 s: "85.0 s of flight (43484 ticks at 500 Hz)" read as
    # if the ticks were the flight's
    text = summary_text(_summary(), clock="lockstep", rate_hz=500.0)
    assert "flown:         85.0 s of flight in 61.6 s wall, 1.4x real time\n" in text, text
    assert "loop:          43484 ticks in all (87.0 s at 500 Hz, preflight included)\n" in text
    assert "(43484 ticks at 500 Hz)" not in text


def test_that_spin_limits_are_not_claimed_when_no_tick_was_scored() -> None:
    # a Ctrl-C during take-off: no measured tick, every metric "--", time scored 0.0
    summary = _summary()
    for phase in ("all", "udt", "mdt"):
        summary[f"{phase}_ticks"] = 0.0
        summary[f"{phase}_duration_s"] = 0.0
        for key in ("pos_err_mean_mm", "spin_min_hz", "spin_max_hz"):
            summary[f"{phase}_{key}"] = math.nan
    summary["all_spin_within_limits"] = 1.0  # vacuously: no tick to be outside them
    text = summary_text(summary)
    assert "respected on every tick" not in text
    assert "rotor spin limits: not scored (no measured tick)" in text
    # scored ticks: the verdict stands
    assert "rotor spin limits: respected on every tick" in summary_text(_summary())


def test_that_a_saved_dashboard_file_is_named_with_how_to_open_it() -> None:
    text = summary_text(_summary(), dashboard_mode="save", dashboard_file="flights/x.rrd")
    assert "dashboard:      flights/x.rrd" in text and "rerun flights/x.rrd" in text


def test_that_version_prints_the_package_version(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_:
        cli_main(["--version"])
    assert exit_.value.code == 0
    assert re.fullmatch(r"fasthex \d+\.\d+\.\d+\S*\n", capsys.readouterr().out)


def test_that_fly_help_lists_the_shipped_sessions(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        cli_main(["fly", "--help"])
    out = capsys.readouterr().out
    assert len(available("sessions")) >= 4
    for name in available("sessions"):
        assert re.search(rf"^  {re.escape(name)}\s", out, re.MULTILINE), name
    assert "Paper Exp. 1" in out


def test_that_the_record_path_comes_from_the_cli_then_the_session_then_the_default(
        tmp_path: Path) -> None:
    session_file = tmp_path / "lab" / "s.yaml"
    assert record_path("x/cli.fhr", "rec.fhr", session_file, "s") == Path("x/cli.fhr")
    assert record_path(None, "out/{session}.fhr", session_file, "s") == \
        tmp_path / "lab" / "out" / "s.fhr"
    assert record_path(None, str(tmp_path / "abs.fhr"), session_file, "s") == \
        tmp_path / "abs.fhr"
    stamped = record_path(None, "{session}-{time}.fhr", session_file, "s")
    assert re.fullmatch(r"s-\d{8}-\d{6}\.fhr", stamped.name)
    default = record_path(None, "", session_file, "s")
    assert default.parent == Path("flights") and default.name.startswith("s-")


def test_that_a_record_folder_that_cannot_be_created_is_one_line_before_the_flight(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # Fixture: the record's folder would be below a file
    (tmp_path / "f").write_text("")
    # Test
    code = cli_main(["fly", "--quiet", "--record", str(tmp_path / "f" / "x.fhr")])
    # Assert
    assert code == 2
    assert capsys.readouterr().err.splitlines()[-1] == (
        f"fasthex: cannot create the record's folder {tmp_path / 'f'}: File exists")


def test_that_replay_progress_is_drawn_on_a_terminal_and_erased_at_the_end() -> None:
    from groundstation.commands.replay import Progress

    class Tty(io.StringIO):
        def isatty(self) -> bool:
            return True

    out = Tty()
    sut = Progress(out, rows=100, duration_s=10.0)
    sut.update(50, 5.0, force=True)
    assert "50 %" in out.getvalue() and "5.0 of 10.0 s" in out.getvalue()
    sut.done()
    assert screen(out.getvalue()) == [""] or screen(out.getvalue()) == []
    piped = io.StringIO()
    Progress(piped, rows=100, duration_s=10.0).update(50, 5.0, force=True)
    assert piped.getvalue() == ""


def test_that_coinciding_cardan_curves_are_grouped() -> None:
    import numpy as np

    from groundstation.analysis import coinciding_groups

    x = np.linspace(0.0, 1.0, 50)
    curves = np.column_stack([x, 2 * x, x, 3 * x, 2 * x, x + 1e-3])
    assert coinciding_groups(curves, tol=1e-9) == [[0, 2], [1, 4], [3], [5]]


def test_that_a_terminal_of_unknown_width_still_gets_a_status_line() -> None:
    import os
    import pty

    from groundstation.console import _columns

    master, slave = pty.openpty()  # never sized: the kernel reports 0 columns
    try:
        with os.fdopen(os.dup(slave), "w") as stream:
            assert _columns(stream) == 80
    finally:
        os.close(master)
        os.close(slave)


def test_that_a_status_wider_than_the_terminal_is_cut_between_fields() -> None:
    out = io.StringIO()  # not a terminal: 80 columns assumed
    line = "MISSION    12.1 s  pos. error  7.2 mm  tilt  0.0 deg  battery 16.03 V  late ticks 2113"
    sut = Console(out, live=True, status=lambda: line + "  tick 0.39 ms")
    sut._flush(show_status=True)
    assert out.getvalue() == line[:line.rindex("  late")]


def test_that_a_lost_record_is_said_instead_of_a_count_of_dropped_rows() -> None:
    # the telemetry process died in flight: its ring's drop count stays 0, the record ends
    summary = _summary()
    summary["faults"] = ["7.602 s: flight record lost: the telemetry process exited (exit code "
                         "-9)"]
    text = summary_text(summary)
    assert "telemetry:     record lost at 7.602 s: the rows after it were not written\n" in text
    assert "record rows dropped" not in text
    assert "telemetry:     0 record rows dropped\n" in summary_text(_summary())

"""``fasthex analyze``: the table, the documented JSON keys and the plots."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from groundstation.cli import main

ROW_KEYS = {"tilt_deg", "rank", "condition_number", "hover_efficiency", "max_rotor_thrust_n",
            "max_lift_n", "lateral_force_radius_n", "cardan_error_deg"}


def test_that_json_output_has_the_documented_keys_and_paper_numbers(
        capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["analyze", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["schema"] == "fasthex.analyze" and out["version"] == 1
    assert out["vehicle"] == "fasthex"
    assert set(out) == {"schema", "version", "vehicle", "mass_kg", "weight_n", "rows",
                        "lateral_bound_fit", "cardan_peak_error_deg",
                        "cardan_peak_error_tilt_deg"}
    rows = {r["tilt_deg"]: r for r in out["rows"]}
    assert all(set(r) == ROW_KEYS for r in out["rows"])
    assert sorted(rows) == [0.0, 5.0, 10.0, 15.0, 20.0, 25.0, 30.0, 35.0]
    assert rows[0.0]["rank"] == 4 and rows[0.0]["condition_number"] is None
    assert rows[30.0]["rank"] == 6
    assert rows[35.0]["hover_efficiency"] == pytest.approx(0.819, abs=1e-3)
    assert rows[30.0]["lateral_force_radius_n"] == pytest.approx(6.67, abs=0.01)
    assert rows[0.0]["max_lift_n"] == pytest.approx(61.8, abs=0.01)
    fit = out["lateral_bound_fit"]
    assert fit["coeffs"][1] == pytest.approx(0.320, abs=0.002)
    assert out["cardan_peak_error_deg"][2] == pytest.approx(1.01, abs=0.005)


def test_that_the_table_lists_every_grid_row(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["analyze", "--vehicle", "fasthex-mini", "--step-deg", "10"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("vehicle fasthex-mini: mass 2 kg")
    rows = [line for line in out.splitlines() if line[:6].strip().replace(".", "").isdigit()]
    assert [float(r.split()[0]) for r in rows] == [0.0, 10.0, 20.0, 30.0]
    assert "lateral bound fit" in out


def test_that_plots_are_written(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["analyze", "--plots", str(tmp_path)]) == 0
    names = sorted(p.name for p in tmp_path.glob("*.png"))
    assert names == ["cardan_errors.png", "efficiency.png", "lateral_bound_fit.png",
                     "lateral_force_sets.png"]
    assert all((tmp_path / n).stat().st_size > 10_000 for n in names)


def test_that_a_bad_step_is_a_user_error(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["analyze", "--step-deg", "0"]) == 2
    assert capsys.readouterr().err == "fasthex: --step-deg must be at least 0.01 deg, got 0\n"


@pytest.mark.parametrize("step", ["1e-9", "0.009", "nan"])
def test_that_a_step_below_the_finest_grid_is_refused_before_any_work(
        step: str, capsys: pytest.CaptureFixture[str]) -> None:
    # Test: 1e-9 deg would be 35e9 grid rows (261 GiB)
    code = main(["analyze", "--step-deg", step])
    # Assert
    assert code == 2
    assert capsys.readouterr().err == (f"fasthex: --step-deg must be at least 0.01 deg, got "
                                       f"{float(step):g}\n")


def test_that_the_finest_step_is_accepted(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["analyze", "--vehicle", "fasthex-mini", "--step-deg", "0.01", "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)["rows"]
    assert len(rows) == 3001  # 0 .. 30 deg


def test_that_plots_into_an_existing_file_is_a_user_error(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # Fixture
    existing = tmp_path / "existing.txt"
    existing.write_text("notes\n")
    # Test
    code = main(["analyze", "--plots", str(existing)])
    # Assert: one line, before the table; the file untouched
    assert code == 2
    out, err = capsys.readouterr()
    assert out == ""
    assert err == (f"fasthex: --plots {existing}: is a file; expected a folder for the PNG "
                   "figures\n")
    assert existing.read_text() == "notes\n"


def test_that_plots_under_a_file_is_a_user_error(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "f").write_text("")
    assert main(["analyze", "--plots", str(tmp_path / "f" / "plots")]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"fasthex: --plots {tmp_path / 'f' / 'plots'}: cannot create the "
                          "folder (") and err.count("\n") == 1

"""``fasthex simulate`` end to end (short flights): JSON summary, table, flight record, errors."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from groundstation.cli import main
from groundstation.record import read_record


def test_that_json_output_has_unit_suffixed_keys_and_the_log_is_readable(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # Fixture
    log = tmp_path / "flight.rec"
    # Test: takeoff and the start of the settling hover of Exp. 1
    code = main(["simulate", "exp1-hover-tilt-steps", "--preset", "ideal", "--seed", "4",
                 "--duration", "6", "--json", "--log", str(log)])
    out = json.loads(capsys.readouterr().out)
    rec = read_record(log)
    # Assert
    assert code == 0
    assert out["mission"] == "exp1-hover-tilt-steps" and out["seed"] == 4
    assert out["sim_time_s"] == pytest.approx(6.0)
    assert out["sim_s_per_wall_s"] > 0.0
    for key in ("all_pos_err_mean_mm", "udt_roll_err_mean_deg", "mdt_spin_max_hz",
                "all_spin_saturated_frac", "all_internal_force_loss_mean_frac"):
        assert key in out
    assert out["all_ticks"] == 0  # nothing measured yet: takeoff and settling only
    assert out["all_pos_err_mean_mm"] is None  # NaN -> null
    assert len(rec) == 3000
    assert rec.metadata["preset"] == "ideal"
    assert rec.rows["pos_w_m"][-1][2] == pytest.approx(1.0, abs=0.01)  # took off
    assert not rec.rows["landed"][-1]


def test_that_the_table_reports_the_phases(capsys: pytest.CaptureFixture[str]) -> None:
    # Test: 10 s of Exp. 2b at a constant 30 deg after takeoff and settling
    code = main(["simulate", "exp2b-roll-sine", "--preset", "ideal", "--duration", "16",
                 "--tilt-deg", "30"])
    out = capsys.readouterr().out
    # Assert
    assert code == 0
    assert "UDT" in out and "MDT" in out
    assert "mean |e_p| [mm]" in out
    assert "real time" in out


def test_that_a_bad_mission_is_a_user_error(tmp_path: Path,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    # Fixture
    bad = tmp_path / "bad.yaml"
    bad.write_text("schema: fasthex.mission\nversion: 1\nname: x\nstart_pos_w_m: [0, 0, 0.1]\n"
                   "segments:\n  - {kind: hover, duration_s: 1}\n")
    # Test
    code = main(["simulate", str(bad)])
    # Assert
    assert code == 2
    err = capsys.readouterr().err
    assert "bad.yaml:6" in err and "segments[0].kind" in err


def test_that_a_nonpositive_duration_is_refused(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["simulate", "--duration", "0"]) == 2
    assert "--duration" in capsys.readouterr().err


def test_that_the_ukf_can_fly_the_takeoff_on_the_simulated_sensors(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # Fixture
    log = tmp_path / "ukf.rec"
    # Test: 1 s rest to initialise the filter, then takeoff and settling of Exp. 1
    code = main(["simulate", "--estimator", "ukf", "--duration", "9", "--json", "--log",
                 str(log)])
    out = json.loads(capsys.readouterr().out)
    rows = read_record(log).rows
    # Assert: hovering at the reference, the estimate within a few mm of the truth
    assert code == 0 and out["estimator"] == "ukf"
    last = rows[-500:]
    err = np.linalg.norm(last["pos_w_m"] - last["pos_ref_w_m"], axis=1)
    est_err = np.linalg.norm(last["est_pos_w_m"] - last["pos_w_m"], axis=1)
    assert err.max() < 0.03
    assert est_err.max() < 0.005

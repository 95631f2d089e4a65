"""The paper's three experiments flown through the full byte path (real drivers over ptys and
UDP, UKF, controller) in lockstep on the emulated vehicle, scored on the vehicle's true state
with the pass criteria of `fasthex simulate` (tests/integration/test_simulate_paper.py)."""

from __future__ import annotations

import math
from functools import cache
from pathlib import Path

import numpy as np
import pytest
from flight_support import fly_shipped_session

from groundstation.flight import FlightState
from groundstation.metrics import flight_metrics
from groundstation.record import FlightRecord, read_record

pytestmark = pytest.mark.slow

PAPER_EXP1 = {"pos_err_mean_mm": 8.7, "roll_err_mean_deg": 0.84, "pitch_err_mean_deg": 0.92,
              "yaw_err_mean_deg": 1.10}
PAPER_EXP2B_POS_MM = 10.4


@cache
def _flight(session: str, tmp: str) -> tuple[list[FlightState], FlightRecord, dict[str, float]]:
    out = fly_shipped_session(Path(tmp), session)
    rec = read_record(out.record_path)
    return ([t.to_state for t in out.result.transitions], rec,
            flight_metrics(rec.rows, min_spin_hz=16.0, max_spin_hz=102.0))


@pytest.fixture(scope="module")
def flights(tmp_path_factory: pytest.TempPathFactory
            ) -> dict[str, tuple[list[FlightState], FlightRecord, dict[str, float]]]:
    tmp = str(tmp_path_factory.mktemp("paper"))
    return {s: _flight(s, tmp) for s in ("exp1-emulated", "exp2a-emulated", "exp2b-emulated")}


def test_that_every_experiment_is_flown_to_a_normal_landing(
        flights: dict[str, tuple[list[FlightState], FlightRecord, dict[str, float]]]) -> None:
    for name, (states, rec, m) in flights.items():
        assert states == [FlightState.ARMED, FlightState.TAKEOFF, FlightState.MISSION,
                          FlightState.LANDING, FlightState.DISARMED], name
        assert rec.metadata["state"].startswith("true state"), name
        assert m["all_spin_within_limits"] == 1.0, name


def test_that_exp1_tracks_no_worse_than_the_paper(
        flights: dict[str, tuple[list[FlightState], FlightRecord, dict[str, float]]]) -> None:
    m = flights["exp1-emulated"][2]
    assert m["all_duration_s"] == pytest.approx(70.0, abs=0.1)
    for key, paper in PAPER_EXP1.items():
        assert m[f"all_{key}"] <= paper, key
    # MDT holds position better than UDT, as in the paper (5.5 vs 6.7 mm)
    assert m["mdt_ticks"] > 0 and m["udt_ticks"] > 0


def test_that_exp2b_tracks_position_no_worse_than_the_paper_and_rolls_once_tilted(
        flights: dict[str, tuple[list[FlightState], FlightRecord, dict[str, float]]]) -> None:
    m = flights["exp2b-emulated"][2]
    assert m["all_pos_err_mean_mm"] <= PAPER_EXP2B_POS_MM
    # UDT: the roll sine cannot be followed (R_d stays level); MDT at 30 deg: it is
    assert m["udt_rd_dev_mean_deg"] > 2.0
    assert m["mdt_rd_dev_mean_deg"] < 1.0
    assert m["mdt_roll_err_mean_deg"] < 1.0 < m["udt_roll_err_mean_deg"]


def test_that_exp2a_recomputes_r_d_in_udt_and_keeps_r_r_when_tilted(
        flights: dict[str, tuple[list[FlightState], FlightRecord, dict[str, float]]]) -> None:
    m = flights["exp2a-emulated"][2]
    assert m["udt_rd_dev_mean_deg"] > 2.0  # tilting to accelerate along x
    assert m["mdt_rd_dev_mean_deg"] < m["udt_rd_dev_mean_deg"] / 3.0
    rows = flights["exp2a-emulated"][1].rows
    measured = rows[rows["measured"] > 0]
    err = np.linalg.norm(measured["pos_w_m"] - measured["pos_ref_w_m"], axis=1)
    assert err.max() < 0.1  # bounded through the whole alpha ramp
    assert math.degrees(float(measured["alpha_rad"].max())) == pytest.approx(30.0, abs=0.5)

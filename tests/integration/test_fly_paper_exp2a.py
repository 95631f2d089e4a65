"""The paper's Experiment 2a (sine translation through an alpha ramp) flown through the full byte
path (real drivers over ptys and UDP, UKF, controller) in lockstep on the emulated vehicle,
scored on the vehicle's true state with the pass criteria of `fasthex simulate`
(tests/integration/test_simulate_paper.py). One experiment per module: pytest-xdist flies the
three side by side."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from flight_support import PaperFlight, assert_normal_paper_flight, fly_paper_experiment

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def flight(tmp_path_factory: pytest.TempPathFactory) -> PaperFlight:
    return fly_paper_experiment(Path(tmp_path_factory.mktemp("exp2a")), "exp2a-emulated")


def test_that_exp2a_is_flown_to_a_normal_landing(flight: PaperFlight) -> None:
    assert_normal_paper_flight(flight)


def test_that_exp2a_recomputes_r_d_in_udt_and_keeps_r_r_when_tilted(flight: PaperFlight) -> None:
    m = flight[2]
    assert m["udt_rd_dev_mean_deg"] > 2.0  # tilting to accelerate along x
    assert m["mdt_rd_dev_mean_deg"] < m["udt_rd_dev_mean_deg"] / 3.0
    rows = flight[1].rows
    measured = rows[rows["measured"] > 0]
    err = np.linalg.norm(measured["pos_w_m"] - measured["pos_ref_w_m"], axis=1)
    assert err.max() < 0.1  # bounded through the whole alpha ramp
    assert math.degrees(float(measured["alpha_rad"].max())) == pytest.approx(30.0, abs=0.5)

"""The paper's experiments flown closed-loop in the simulator (in process, 500 Hz).

What the paper reports, as checks on the simulated flights:
- with the ``paper-calibrated`` preset the mean errors are no worse than the paper's measured
  ones (Exp. 1: 8.7 mm, roll/pitch/yaw 0.84/0.92/1.10 deg; Exp. 2b: 10.4 mm) for three seeds,
  and far smaller with the ``ideal`` preset (the simulator's error sources are real);
- in UDT the controller re-computes R_d (tilts to hold position) and cannot follow a roll
  reference; with alpha at 30 deg R_d converges to R_r and Exp. 2b tracks the roll sine;
- spin commands never leave [16, 102] Hz; position errors stay bounded through every alpha step;
- the auto tilt mode holds Exp. 2a with R_d on R_r (closer than a fixed 30 deg, whose bound the
  peaks exceed) and less internal-force loss than the maximum tilt.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cache

import numpy as np
import pytest

from controller.missions import Mission
from groundstation.configs import load_disturbances, load_mission, load_vehicle
from groundstation.metrics import flight_metrics
from groundstation.record import RecordWriter
from sim_backend.closed_loop import fly_mission

pytestmark = pytest.mark.slow

PARAMS = load_vehicle("fasthex")
SEEDS = (1, 2, 3)
PAPER_EXP1 = {"pos_err_mean_mm": 8.7, "roll_err_mean_deg": 0.84, "pitch_err_mean_deg": 0.92,
              "yaw_err_mean_deg": 1.10}
PAPER_EXP2B_POS_MM = 10.4


@dataclass(frozen=True)
class Flight:
    metrics: dict[str, float]
    t_s: np.ndarray
    pos_err_m: np.ndarray
    spin_cmd_hz: np.ndarray
    alpha_ref_rad: np.ndarray
    measured: np.ndarray


@cache
def flight(mission: str, preset: str, seed: int, duration_s: float | None = None,
           tilt_deg: float | None = None) -> Flight:
    writer = RecordWriter(None)
    fly_mission(PARAMS, Mission(load_mission(mission)), load_disturbances(preset), seed=seed,
                sink=writer, duration_s=duration_s,
                tilt_override_rad=None if tilt_deg is None else math.radians(tilt_deg))
    rows = writer.close().rows
    return Flight(flight_metrics(rows, min_spin_hz=16.0, max_spin_hz=102.0),
                  rows["t_s"].copy(),
                  np.linalg.norm(rows["pos_w_m"] - rows["pos_ref_w_m"], axis=1),
                  rows["spin_cmd_hz"].copy(), rows["alpha_ref_rad"].copy(),
                  rows["measured"].astype(bool))


@pytest.mark.parametrize("seed", SEEDS)
def test_that_exp1_tracks_no_worse_than_the_paper(seed: int) -> None:
    m = flight("exp1-hover-tilt-steps", "paper-calibrated", seed).metrics
    for key, paper in PAPER_EXP1.items():
        assert m[f"all_{key}"] < paper, key
    # and not trivially: the calibrated disturbances do show
    assert m["all_pos_err_mean_mm"] > 2.0


@pytest.mark.parametrize("seed", SEEDS)
def test_that_exp2b_tracks_position_no_worse_than_the_paper(seed: int) -> None:
    m = flight("exp2b-roll-sine", "paper-calibrated", seed).metrics
    assert m["all_pos_err_mean_mm"] < PAPER_EXP2B_POS_MM


def test_that_the_ideal_preset_is_far_more_accurate_than_the_calibrated_one() -> None:
    ideal = flight("exp1-hover-tilt-steps", "ideal", 1).metrics
    real = flight("exp1-hover-tilt-steps", "paper-calibrated", 1).metrics
    assert ideal["all_pos_err_mean_mm"] < real["all_pos_err_mean_mm"] / 20.0
    for axis in ("roll", "pitch", "yaw"):
        key = f"all_{axis}_err_mean_deg"
        assert ideal[key] < real[key] / 10.0


def test_that_in_udt_the_controller_recomputes_r_d_and_in_mdt_keeps_r_r() -> None:
    # Exp. 1: R_r = I throughout; R_d leans to hold position only while under-actuated
    m = flight("exp1-hover-tilt-steps", "paper-calibrated", 1).metrics
    assert m["udt_rd_dev_mean_deg"] > 0.2
    assert m["mdt_rd_dev_mean_deg"] < 0.05
    assert m["mdt_roll_err_mean_deg"] < m["udt_roll_err_mean_deg"]
    assert m["mdt_pitch_err_mean_deg"] < m["udt_pitch_err_mean_deg"]


def test_that_exp2b_follows_the_roll_sine_only_once_tilted() -> None:
    m = flight("exp2b-roll-sine", "paper-calibrated", 1).metrics
    # UDT: mean |6 deg sin| = 3.8 deg is not followed; MDT: tracked to a fraction of a degree
    assert m["udt_roll_err_mean_deg"] > 2.5
    assert m["udt_rd_dev_mean_deg"] > 2.5
    assert m["mdt_roll_err_mean_deg"] < 0.5
    assert m["mdt_rd_dev_mean_deg"] < 0.05


@pytest.mark.parametrize("mission", ["exp1-hover-tilt-steps", "exp2b-roll-sine"])
def test_that_spin_commands_never_leave_the_rotor_limits(mission: str) -> None:
    for seed in SEEDS:
        f = flight(mission, "paper-calibrated", seed)
        spinning = f.spin_cmd_hz[np.all(f.spin_cmd_hz > 0.0, axis=1)]  # motors not stopped
        assert len(spinning) > 0.9 * len(f.spin_cmd_hz)
        assert spinning.min() >= 16.0 - 1e-4
        assert spinning.max() <= 102.0 + 1e-4


def test_that_the_position_error_stays_bounded_through_every_alpha_step() -> None:
    f = flight("exp1-hover-tilt-steps", "paper-calibrated", 1)
    steps = np.flatnonzero(np.abs(np.diff(f.alpha_ref_rad)) > math.radians(1.0)) + 1
    steps = steps[f.measured[steps]]  # not the return to 0 deg for landing
    assert len(steps) == 3  # 0 -> 30 -> 0 -> 30 deg
    for i in steps:
        window = (f.t_s >= f.t_s[i]) & (f.t_s < f.t_s[i] + 6.0)
        assert f.pos_err_m[window].max() < 0.03
    assert f.metrics["all_pos_err_max_mm"] < 30.0


def test_that_auto_tilt_holds_exp2a_on_r_r_with_less_internal_force_loss_than_35_deg() -> None:
    # 10 s settle + the first 45 s of the sine: enough to compare steady behaviour. Auto plans
    # for the controller's bound: R_d stays nearer R_r than at a fixed 30 deg (whose bound the
    # 5.2 N peaks exceed) for less internal-force loss than the maximum tilt.
    auto = flight("exp2a-sine-translation-auto", "paper-calibrated", 1, 65.0).metrics
    fixed30 = flight("exp2a-sine-translation", "paper-calibrated", 1, 65.0, 30.0).metrics
    fixed35 = flight("exp2a-sine-translation", "paper-calibrated", 1, 65.0, 35.0).metrics
    loss = "all_internal_force_loss_mean_frac"
    assert auto[loss] < fixed35[loss] - 0.01
    assert auto["all_rd_dev_mean_deg"] < 0.5 * fixed30["all_rd_dev_mean_deg"]
    assert auto["all_pos_err_mean_mm"] < 15.0
    assert auto["all_pos_err_max_mm"] < 50.0
    assert auto["all_spin_within_limits"] == 1.0
    assert auto["all_rd_dev_mean_deg"] < 1.0  # stays (nearly) level, unlike UDT


def test_that_exp2a_tilts_r_d_in_udt_and_leaves_r_r_only_at_the_peaks_at_30_deg() -> None:
    # UDT part of the paper's ramp profile: to accelerate sideways the body must lean
    udt = flight("exp2a-sine-translation", "paper-calibrated", 1, 30.0).metrics
    assert udt["udt_rd_dev_mean_deg"] > 3.0
    assert udt["udt_pos_err_mean_mm"] < 30.0
    # at 30 deg the 5.2 N peak demand is at the conservative bound: R_d stays level on average
    # but leaves R_r briefly at the peaks, as in the paper
    fixed = flight("exp2a-sine-translation", "paper-calibrated", 1, 65.0, 30.0).metrics
    assert fixed["mdt_rd_dev_mean_deg"] < 0.2
    assert fixed["mdt_rd_dev_max_deg"] > 0.5

"""The numerics behind ``fasthex tune``: the linearised loop margins, the disturbance recovery
metric, and a trial's score and constraints, on values worked out by hand."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from controller.loop_margins import loop_margins
from groundstation.campaign import TuneParameter, TuneSpec
from groundstation.configs import load_vehicle
from groundstation.metrics import disturbance_metrics
from groundstation.tune import INFEASIBLE_OBJECTIVE, score

FASTHEX = load_vehicle("fasthex")


def test_that_the_shipped_gains_have_the_margins_of_their_characteristic_polynomials() -> None:
    m = loop_margins(FASTHEX)
    # position: 3.1 s^3 + 14.14 s^2 + 50 s + 20 -> -2.05 +- 3.17j and -0.452 (the slow
    # integral pole the issue names); damping of the complex pair 2.05 / |p| = 0.544
    poles = np.roots([3.1, 14.14, 50.0, 20.0])
    pair = poles[np.abs(poles.imag) > 0][0]
    assert m.pos_min_damping == pytest.approx(-pair.real / abs(pair), rel=1e-9)
    assert m.pos_min_damping == pytest.approx(0.544, abs=1e-3)
    assert m.slowest_pole_rad_s == pytest.approx(0.452, abs=1e-3)
    # yaw: 0.164 s^3 + 0.5 s^2 + 6 s + 1: its pair is the least damped attitude mode
    yaw = np.roots([0.164, 0.5, 6.0, 1.0])
    yaw_pair = yaw[np.abs(yaw.imag) > 0][0]
    assert m.att_min_damping == pytest.approx(-yaw_pair.real / abs(yaw_pair), rel=1e-9)
    # the slower of roll and pitch over the position natural frequency:
    # sqrt(15 / 0.091) / sqrt(50 / 3.1)
    assert m.separation == pytest.approx(math.sqrt(15 / 0.091) / math.sqrt(50 / 3.1), rel=1e-12)
    assert m.routh_ratio == pytest.approx(14.14 * 50.0 / (3.1 * 20.0), rel=1e-12)


def test_that_a_larger_integral_gain_moves_the_slow_pole_out_and_costs_damping() -> None:
    c = dataclasses.replace(FASTHEX.controller, ki_pos=(80.0, 80.0, 80.0))
    m = loop_margins(dataclasses.replace(FASTHEX, controller=c))
    base = loop_margins(FASTHEX)
    assert m.slowest_pole_rad_s > 2.0 * base.slowest_pole_rad_s
    assert m.pos_min_damping < base.pos_min_damping


def record(t: np.ndarray, err_m: np.ndarray) -> np.ndarray:
    rows = np.zeros(len(t), dtype=[("t_s", float), ("measured", bool), ("pos_w_m", float, 3),
                                   ("pos_ref_w_m", float, 3)])
    rows["t_s"] = t
    rows["measured"] = True
    rows["pos_w_m"][:, 1] = err_m
    return rows


def test_that_the_recovery_time_is_when_the_smoothed_error_comes_back_under_10_mm() -> None:
    # Fixture: a 50 mm kick at 2 s decaying as exp(-(t - 2.2)/0.5) after its peak at 2.2 s:
    # under 10 mm at 2.2 + 0.5 ln 5 = 3.005 s; the 0.2 s trailing mean lags by ~0.1 s
    t = np.arange(0.0, 8.0, 0.002)
    err = np.where(t < 2.0, 0.003, np.where(t < 2.2, 0.003 + (t - 2.0) / 0.2 * 0.047,
                                            0.05 * np.exp(-(t - 2.2) / 0.5)))
    # Test
    out = disturbance_metrics(record(t, err), [(2.0, math.inf)])
    # Assert
    assert out["dist0_peak_err_mm"] == pytest.approx(50.0, abs=0.1)
    assert out["dist0_recovered"] == 1.0
    assert 1.0 < out["dist0_recovery_s"] < 1.2
    assert out["calm_pos_err_mean_mm"] == pytest.approx(3.0)


def test_that_an_error_that_never_settles_is_not_recovered_and_noise_spikes_do_not_count(
        ) -> None:
    t = np.arange(0.0, 6.0, 0.002)
    # a 20 mm offset from 1 s on: never recovered within its window
    stuck = disturbance_metrics(record(t, np.where(t < 1.0, 0.0, 0.02)), [(1.0, math.inf)])
    assert stuck["dist0_recovered"] == 0.0 and math.isnan(stuck["dist0_recovery_s"])
    # single-tick spikes to 15 mm on a 4 mm hover: the trailing mean never leaves 10 mm
    err = np.full(len(t), 0.004)
    err[::100] = 0.015
    calm = disturbance_metrics(record(t, err), [(1.0, math.inf)])
    assert calm["dist0_recovery_s"] == 0.0 and calm["dist0_recovered"] == 1.0


def test_that_each_event_is_judged_only_up_to_the_next_one() -> None:
    t = np.arange(0.0, 10.0, 0.002)
    err = np.where((t >= 2.0) & (t < 3.0), 0.03, 0.0) + np.where(t >= 6.0, 0.03, 0.0)
    out = disturbance_metrics(record(t, err), [(2.0, 5.0), (6.0, math.inf)])
    # the first: 30 mm for 1 s, then 0; its 0.2 s trailing mean is under 10 mm once two
    # thirds of the window are 0, 0.133 s later
    assert out["dist0_recovered"] == 1.0
    assert out["dist0_recovery_s"] == pytest.approx(1.0 + 0.2 * 2.0 / 3.0, abs=0.003)
    assert out["dist1_recovered"] == 0.0
    # judged only up to its own end: a window that ends before the hold is not recovered
    short = disturbance_metrics(record(t, err), [(2.0, 3.5)])
    assert short["dist0_recovered"] == 0.0


TUNE = TuneSpec(parameters=(TuneParameter(name="ki_pos", paths=("vehicle.controller.ki_pos",),
                                          low=5.0, high=200.0),))
MARGINS = {"pos_min_damping": 0.6, "separation": 3.0}


def test_that_a_trial_scores_mean_recovery_plus_weighted_calm_error() -> None:
    rows = [{"verdict": "ok", "dist0_recovery_s": 1.5, "calm_pos_err_mean_mm": 5.0,
             "all_spin_saturated_frac": 0.0},
            {"verdict": "ok", "dist0_recovery_s": None, "calm_pos_err_mean_mm": 7.0,
             "all_spin_saturated_frac": 0.0}]
    objective, constraints = score(TUNE, rows, MARGINS, calm_reference_mm=5.5)
    # (1.5 + 10 penalty) / 2 + 0.1 * 6.0
    assert objective == pytest.approx(5.75 + 0.6)
    assert constraints == pytest.approx([0.0, 0.0, 0.45 - 0.6, 2.5 - 3.0, 0.5])


def test_that_a_failed_flight_or_saturation_makes_a_trial_infeasible() -> None:
    rows = [{"verdict": "crash", "dist0_recovery_s": 1.0, "calm_pos_err_mean_mm": 5.0,
             "all_spin_saturated_frac": 0.02}]
    objective, constraints = score(TUNE, rows, MARGINS, calm_reference_mm=None)
    assert objective == INFEASIBLE_OBJECTIVE
    assert constraints[0] == 1.0 and constraints[1] == pytest.approx(0.02)
    _, none = score(TUNE, [], MARGINS, calm_reference_mm=None)
    assert none[0] > 0.0  # a trial with no rows is never feasible

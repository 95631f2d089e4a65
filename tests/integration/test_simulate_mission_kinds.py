"""Each new mission kind flown closed-loop in the in-process simulator (truth state source, the
``paper-calibrated`` preset, as ``fasthex simulate`` does) follows its path.

Tolerance, from the position loop of ``config/vehicles/fasthex.yaml``: K_p = 50 N/m, K_v =
14.14 N s/m on m = 3.1 kg give omega_n = sqrt(K_p / m) = 4.0 rad/s (zeta = 0.57). The reference's
acceleration is fed forward, so a perfect plant would track exactly; the worst case, a
feed-forward entirely lost (rotor and tilt lag, force errors), leaves a quasi-static error of
a_max / omega_n^2 = m a_max / K_p. Add the noise floor of the preset (hovering: an OU force of
0.3 N rms through K_p gives ~6 mm rms, peaks under 20 mm): max |e_p| <= a_max / omega_n^2 +
20 mm, and the mean under half of it.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from controller.missions import Mission
from groundstation.configs import load_disturbances, load_mission, load_vehicle
from groundstation.record import RecordWriter
from sim_backend.closed_loop import fly_mission

PARAMS = load_vehicle("fasthex")
NOISE_FLOOR_M = 0.020


@pytest.mark.parametrize("name", ["demo-circle", "demo-figure-eight", "demo-waypoints",
                                  "demo-ramp-pitched", "demo-trajectory"])
def test_that_the_mission_kind_is_tracked_within_the_position_loop_bound(name: str) -> None:
    # Fixture: fly to the end of the measured part (the landing is not measured)
    mission = Mission(load_mission(name, vehicle=PARAMS))
    interval = mission.measured_interval_s()
    assert interval is not None
    writer = RecordWriter(None, {})
    # Test
    result = fly_mission(PARAMS, mission, load_disturbances("paper-calibrated"), seed=1,
                         sink=writer, duration_s=interval[1])
    rows = writer.close().rows
    # Assert
    assert result.crash is None
    meas = rows["measured"].astype(bool)
    err_m = np.linalg.norm(rows["pos_w_m"] - rows["pos_ref_w_m"], axis=1)[meas]
    a_max = float(np.linalg.norm(rows["acc_ref_w_m_s2"], axis=1)[meas].max())
    omega_n = math.sqrt(PARAMS.controller.kp_pos[0] / PARAMS.mass_kg)
    bound_m = a_max / omega_n**2 + NOISE_FLOOR_M
    assert err_m.max() < bound_m
    assert err_m.mean() < 0.5 * bound_m

"""In flight, the desired tilt of Algorithm 1 equals the closed form of paper-notes item 7.

``theta* = max(0, angle(b3r, f_r) - asin(min(1, r_xy / |f_r|)))``, recomputed from the recorded
reference force, reference attitude and lateral bound of every tick of a flight through the
Exp. 2a sine (UDT, then the alpha ramp through the dead zone edge).
"""

from __future__ import annotations

import numpy as np

from controller.missions import Mission
from groundstation.configs import load_disturbances, load_mission, load_vehicle
from groundstation.metrics import quat_to_rot
from groundstation.record import RecordWriter
from sim_backend.closed_loop import fly_mission


def test_that_every_recorded_theta_matches_the_closed_form() -> None:
    # Fixture: 10 s settle + 18 s of the sine (alpha ramps from 10 s of the experiment)
    writer = RecordWriter(None)
    fly_mission(load_vehicle("fasthex"), Mission(load_mission("exp2a-sine-translation")),
                load_disturbances("paper-calibrated"), seed=5, sink=writer, duration_s=28.0)
    rows = writer.close().rows
    f = rows["f_r_w_n"].astype(float)
    b3r = quat_to_rot(rows["q_wr"])[:, :, 2]
    r_xy = rows["r_xy_n"].astype(float)
    # Test
    fn = np.linalg.norm(f, axis=1)
    angle = np.arctan2(np.linalg.norm(np.cross(b3r, f), axis=1), np.sum(b3r * f, axis=1))
    closed = np.maximum(0.0, angle - np.arcsin(np.minimum(1.0, r_xy / fn)))
    # Assert: float32 record, 20 bisection steps (theta_max / 2^21)
    theta = rows["theta_rad"].astype(float)
    assert np.max(np.abs(theta - closed)) < 2e-5
    assert np.count_nonzero(theta > 0.02) > 1000  # the UDT sine really needs tilting
    assert np.count_nonzero(r_xy > 0.0) > 1000  # and the bound opened during the ramp

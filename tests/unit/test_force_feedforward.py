"""The controller's external-force feed-forward and the closed loop's hand-over of the estimate.

Off (the default) the controller is the paper's and ignores any force it is given; on, the
estimate is subtracted from f_r, clipped to ``force_feedforward_limit_n``. In the closed loop a
:class:`ForceObservingSource` is told each commanded body force and its estimate reaches the
controller.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from controller.geometric import GeometricController
from controller.missions import Mission
from controller.params import VehicleParams
from controller.reference import IDENTITY_Q, ZERO3, Reference, Vec3, VehicleState
from estimator import EstimatorConfig
from groundstation.configs import load_disturbances, load_mission, load_vehicle
from groundstation.record import RecordWriter
from sim_backend.closed_loop import ForceObservingSource, UkfStateSource, fly_mission
from sim_backend.vehicle import ImuReading, PoseReading

PARAMS = load_vehicle("fasthex")
HOVER = (-0.14, -0.05, 1.0)
A30 = math.radians(30.0)


def _with_feedforward(on: bool, limit_n: float = 3.0) -> VehicleParams:
    return dataclasses.replace(PARAMS, controller=dataclasses.replace(
        PARAMS.controller, force_feedforward=on, force_feedforward_limit_n=limit_n))


def _step(params: VehicleParams, force: Vec3 | None) -> tuple[float, float, float]:
    # off hover by a few mm, so that the position terms are not zero
    state = VehicleState((HOVER[0] + 0.004, HOVER[1] - 0.003, HOVER[2] + 0.002),
                         (0.01, 0.0, -0.02), IDENTITY_Q, ZERO3)
    ref = Reference(0.0, HOVER, ZERO3, ZERO3, IDENTITY_Q, ZERO3, A30)
    return GeometricController(params).step(0.0, state, ref, A30, force).f_r_w_n


def test_that_the_paper_faithful_controller_is_the_default_and_ignores_the_force() -> None:
    # Fixture
    assert PARAMS.controller.force_feedforward is False
    # Test / Assert: bit-identical with and without a force
    assert _step(PARAMS, (0.4, -0.2, 1.0)) == _step(PARAMS, None)


def test_that_the_feedforward_subtracts_the_estimated_force_from_f_r() -> None:
    # Fixture
    base = _step(_with_feedforward(True), None)
    # Test
    got = _step(_with_feedforward(True), (0.4, -0.2, 1.0))
    # Assert
    assert got == pytest.approx((base[0] - 0.4, base[1] + 0.2, base[2] - 1.0), abs=1e-12)


def test_that_a_large_or_broken_force_estimate_is_clipped_or_ignored() -> None:
    # Fixture: a 30 N "force" (the ground's reaction before takeoff), limit 2 N
    params = _with_feedforward(True, limit_n=2.0)
    base = _step(params, None)
    # Test
    got = _step(params, (0.0, 18.0, 24.0))
    nan = _step(params, (math.nan, 0.0, 1.0))
    # Assert: 2 N along the estimate's direction; NaN changes nothing
    assert got == pytest.approx((base[0], base[1] - 1.2, base[2] - 1.6), abs=1e-12)
    assert nan == base


class _ConstantForceSource:
    """A fixed state and force estimate, and a log of the commanded body forces."""

    def __init__(self, state: VehicleState, force_w_n: Vec3) -> None:
        self.state = state
        self.force = force_w_n
        self.commands: list[Vec3] = []

    def update(self, t_s: float, imu: ImuReading, mocap: list[PoseReading]) -> VehicleState:
        return self.state

    def command_issued(self, force_b_n: Vec3) -> None:
        self.commands.append(force_b_n)

    def external_force_w_n(self) -> Vec3 | None:
        return self.force


def test_that_the_closed_loop_hands_the_force_estimate_to_the_controller() -> None:
    # Fixture: the same seed flown with a 1 N upward estimate, feed-forward off and on
    mission = Mission(load_mission("exp1-hover-tilt-steps"))
    preset = load_disturbances("ideal")
    f_r_z = {}
    for on in (False, True):
        source = _ConstantForceSource(
            VehicleState(mission.start_pos_w_m, ZERO3, IDENTITY_Q, ZERO3), (0.0, 0.0, 1.0))
        assert isinstance(source, ForceObservingSource)
        writer = RecordWriter(None)
        fly_mission(_with_feedforward(on), mission, preset, seed=3, sink=writer,
                    duration_s=0.1, state_source=source)
        rows = writer.close().rows
        f_r_z[on] = float(rows["f_r_w_n"][0, 2])
        # Assert: one commanded body force per tick; at alpha = 0 its z is the thrusts' sum
        assert len(source.commands) == len(rows) == 50
        assert source.commands[0][2] == pytest.approx(float(np.sum(rows["thrust_n"][0])),
                                                      rel=1e-5)
    # Assert: on the first tick (same state) the estimate went straight into f_r
    assert f_r_z[True] == pytest.approx(f_r_z[False] - 1.0, abs=1e-9)


def test_that_the_ukf_source_offers_a_force_only_once_initialised_and_observing() -> None:
    # Fixture
    source = UkfStateSource(3.1, 9.81)
    off = UkfStateSource(3.1, 9.81, EstimatorConfig(force_observer=False))
    imu = ImuReading(0.0, (0.0, 0.0, 0.0), (0.0, 0.0, 9.81))
    pose = PoseReading(0.0, (0.0, 0.0, 0.1), (1.0, 0.0, 0.0, 0.0))
    # Test / Assert: nothing before the rest period is over
    assert source.external_force_w_n() is None
    for k in range(400):                      # 0.8 s at rest at 500 Hz, poses at 100 Hz
        t = k * 0.002
        frames = [PoseReading(t, pose.pos_w_m, pose.q_wb)] if k % 5 == 0 else []
        for s in (source, off):
            s.update(t, ImuReading(t, imu.gyro_rad_s, imu.accel_m_s2), frames)
    assert source.ukf.initialized and off.ukf.initialized
    assert off.external_force_w_n() is None
    force = source.external_force_w_n()
    assert force is not None and len(force) == 3
    # the mass and gravity are the vehicle's, whatever the configuration said
    assert source.ukf.cfg.mass_kg == 3.1

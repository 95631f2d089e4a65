"""The per-tick value types (controller.values.tick_value): built like plain slotted
dataclasses, compared and hashed like the frozen ones they are to the type checker; and the
caches that came with them (the simulator's true state, the wrench mapper's rows)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from controller.geometric import Command
from controller.pipeline import ControlTick
from controller.reference import Reference, VehicleState
from drivers.mikrokopter import messages as mkm
from groundstation.configs import load_disturbances, load_vehicle
from groundstation.flight import (
    Directive,
    FlightState,
    HealthSnapshot,
    ReferenceSource,
    ServoHealth,
)
from sim_backend.simulator import FastHexSimulator
from sim_backend.vehicle import ImuReading, PoseReading

Z3 = (0.0, 0.0, 0.0)
Q1 = (1.0, 0.0, 0.0, 0.0)


def _values() -> list[object]:
    ref = Reference(0.5, (0.0, 0.0, 1.0), Z3, Z3, Q1, Z3, 0.1, 2, True)
    cmd = Command(0.5, (50.0,) * 6, (3.0,) * 6, (False,) * 6, Z3, Z3, Z3,
                  (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0), 4.0, 0.0, 0.1, Z3)
    return [VehicleState((0.0, 0.0, 1.0), Z3, Q1, Z3), ref, cmd, ControlTick(ref, 0.1, 0.1, cmd),
            HealthSnapshot(0.0, True, 0.01, True, ServoHealth.OK, 16.0, Z3, 0.0, False,
                           "mission", True),
            Directive(FlightState.MISSION, True, ReferenceSource.MISSION, False),
            ImuReading(0.5, Z3, (0.0, 0.0, 9.81)), PoseReading(0.5, Z3, Q1)]


@pytest.mark.parametrize("value", _values(), ids=lambda v: type(v).__name__)
def test_that_a_tick_value_compares_and_hashes_by_its_fields(value: object) -> None:
    twin = dataclasses.replace(value)  # type: ignore[type-var]
    assert twin == value and twin is not value
    assert hash(twin) == hash(value)
    assert {value: 1}[twin] == 1
    assert not hasattr(value, "__dict__")  # slotted
    first = dataclasses.fields(value)[0].name  # type: ignore[arg-type]
    changed = dataclasses.replace(value, **{first: None})  # type: ignore[type-var]
    assert changed != value


def test_that_the_simulators_true_state_follows_every_step() -> None:
    sim = FastHexSimulator(load_vehicle("fasthex"), load_disturbances("paper-calibrated"),
                           seed=3, start_pos_w_m=(0.0, 0.0, 1.0))
    sim.command_rotor_speeds_hz((80.0,) * 6)
    before = sim.state()
    assert sim.state() is before  # built once per step
    sim.advance(0.1)
    after = sim.state()
    assert after is not before and after.vel_w_m_s != before.vel_w_m_s
    sim.kick_body_rate((0.5, 0.0, 0.0))
    kicked = sim.state()
    assert kicked.omega_b_rad_s[0] == pytest.approx(after.omega_b_rad_s[0] + 0.5)


def test_that_the_motor_frame_encoder_matches_the_message() -> None:
    rng = np.random.default_rng(5)
    for _ in range(200):
        msg = mkm.MotorMessage(int(rng.integers(0, 256)), int(rng.integers(1, 13)),
                               bool(rng.integers(2)), bool(rng.integers(2)),
                               bool(rng.integers(2)), int(rng.integers(-32767, 32768)),
                               int(rng.integers(0, 1024)), float(rng.uniform(0.0, 70.0)))
        wire = mkm.encode_motor_state(msg.seq, msg.motor_id, msg.emergency, msg.spinning,
                                      msg.starting, msg.half_period_us, msg.throttle_raw,
                                      msg.current_a)
        assert wire == msg.encode()
        back = mkm.MotorMessage.decode(wire[1:])
        assert (back.seq, back.motor_id, back.spinning, back.half_period_us) == (
            msg.seq, msg.motor_id, msg.spinning, msg.half_period_us)
        # the wire carries mA in a u16: 65.535 A at most
        assert math.isclose(back.current_a, min(round(msg.current_a * 1e3), 65535) * 1e-3)

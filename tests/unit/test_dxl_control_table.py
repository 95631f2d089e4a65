"""The MX-28 (P1) control table as data, and the unit conversions around it."""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from drivers.dynamixel import control_table as ct
from drivers.dynamixel.control_table import Mode, Reg


def test_that_registers_do_not_overlap_and_fit_the_74_byte_table() -> None:
    used: set[int] = set()
    for r in ct.MX28_P1:
        span = set(range(r.address, r.address + r.size))
        assert not span & used, r
        used |= span
        assert r.address + r.size <= ct.TABLE_SIZE
        assert r.lo <= r.initial <= r.hi or r.access is ct.Access.R
    assert ct.TABLE_SIZE == 74 and ct.EEPROM_END == 24


def test_that_the_p1_addresses_are_not_the_p2_ones() -> None:
    assert (Reg.TORQUE_ENABLE, Reg.GOAL_POSITION, Reg.PRESENT_POSITION) == (24, 30, 36)
    assert ct.STATE_BLOCK_ADDRESS == 36 and ct.STATE_BLOCK_LENGTH == 11


def test_that_the_mode_follows_the_angle_limits() -> None:
    assert ct.mode_from_limits(4095, 4095) is Mode.MULTI_TURN
    assert ct.mode_from_limits(0, 0) is Mode.WHEEL
    assert ct.mode_from_limits(0, 4095) is Mode.JOINT


@pytest.mark.parametrize(("value", "bps"), [(1, 1_000_000), (3, 500_000), (16, 117_647),
                                            (34, 57_143), (207, 9_615), (252, 3_000_000)])
def test_that_the_baud_register_follows_the_formula_and_the_remapped_rates(value: int,
                                                                           bps: int) -> None:
    assert ct.baud_from_register(value) == bps


@given(st.integers(-28672, 28672))
def test_that_signed_positions_survive_the_sdk_unsigned_round_trip(steps: int) -> None:
    assert ct.to_signed16(ct.to_unsigned16(steps)) == steps


@given(st.integers(-1023, 1023))
def test_that_speed_and_load_direction_bit_round_trips(value: int) -> None:
    assert ct.signed_magnitude_11(ct.encode_signed_magnitude_11(value)) == value


def test_that_the_moving_speed_for_10_deg_s_of_tilt_never_exceeds_it() -> None:
    # 10 deg/s of tilt through a 20:1 worm = 200 deg/s at the servo = 33.3 rpm = 292.4 units.
    servo_rate = math.radians(10.0) / 0.05
    units = ct.moving_speed_for_rate(servo_rate)
    assert units == 292
    assert ct.speed_rad_s(units) <= servo_rate < ct.speed_rad_s(units + 1)

"""The emulated MX-28T's protocol and physics, driven in lockstep without a client."""

from __future__ import annotations

import math
from collections.abc import Iterator

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from drivers.dynamixel import protocol1 as p1
from drivers.dynamixel.control_table import ErrorBit, Instruction, Mode, Reg
from sim_backend.emulators.dynamixel_p1 import EmulatedMX28
from sim_backend.vehicle import BenchVehicle

DEG = math.pi / 180.0


@pytest.fixture
def bench() -> BenchVehicle:
    return BenchVehicle(max_tilt_rate_rad_s=100 * DEG)


@pytest.fixture
def emu(bench: BenchVehicle) -> Iterator[EmulatedMX28]:
    servo = EmulatedMX28(bench)
    yield servo
    servo.close()


def ask(emu: EmulatedMX28, inst: int, params: bytes = b"", dxl_id: int = 1) -> p1.Packet | None:
    packet = p1.Parser().feed(p1.encode_instruction(dxl_id, inst, params))[0]
    reply = emu.handle(packet)
    if reply is None:
        return None
    return p1.Parser().feed(reply)[0]


def write(emu: EmulatedMX28, reg: Reg, value: int, size: int) -> p1.Packet | None:
    data = (value & 0xFFFFFFFF).to_bytes(4, "little")[:size]
    return ask(emu, Instruction.WRITE, bytes((reg,)) + data)


def run(emu: EmulatedMX28, bench: BenchVehicle, seconds: float, dt: float = 0.002) -> None:
    for _ in range(round(seconds / dt)):
        bench.advance(dt)
        emu.step()


def test_that_ping_and_a_model_read_answer_as_the_sdk_expects(emu: EmulatedMX28) -> None:
    assert ask(emu, Instruction.PING) == p1.Packet(1, 0, b"")
    assert ask(emu, Instruction.READ, bytes((0, 2))) == p1.Packet(1, 0, bytes((29, 0)))
    assert ask(emu, Instruction.PING, dxl_id=2) is None
    assert ask(emu, Instruction.PING, dxl_id=0xFE) is None


def test_that_a_read_past_the_table_still_returns_len_bytes_with_a_range_error(
        emu: EmulatedMX28) -> None:
    reply = ask(emu, Instruction.READ, bytes((70, 10)))
    assert reply is not None and len(reply.params) == 10
    assert reply.code == ErrorBit.RANGE


def test_that_read_only_out_of_range_and_locked_writes_are_refused_with_range(
        emu: EmulatedMX28) -> None:
    for reg, value, size in ((Reg.PRESENT_POSITION, 5, 2), (Reg.MODEL_NUMBER, 1, 2),
                             (Reg.STATUS_RETURN_LEVEL, 3, 1), (Reg.MAX_TORQUE, 2000, 2)):
        reply = write(emu, reg, value, size)
        assert reply is not None and reply.code == ErrorBit.RANGE, reg
    assert emu.register(Reg.STATUS_RETURN_LEVEL) == 2
    write(emu, Reg.LOCK, 1, 1)
    reply = write(emu, Reg.RETURN_DELAY_TIME, 0, 1)
    assert reply is not None and reply.code == ErrorBit.RANGE
    assert emu.register(Reg.RETURN_DELAY_TIME) == 250


def test_that_a_joint_mode_goal_outside_the_limits_is_an_angle_limit_error(
        emu: EmulatedMX28) -> None:
    write(emu, Reg.CCW_ANGLE_LIMIT, 2000, 2)
    reply = write(emu, Reg.GOAL_POSITION, 3000, 2)
    assert reply is not None and reply.code == ErrorBit.ANGLE_LIMIT


def test_that_an_unknown_instruction_and_a_bare_action_are_instruction_errors(
        emu: EmulatedMX28) -> None:
    for inst in (0x77, Instruction.ACTION):
        reply = ask(emu, inst)
        assert reply is not None and reply.code == ErrorBit.INSTRUCTION


def test_that_a_bad_checksum_is_answered_with_the_checksum_bit(emu: EmulatedMX28) -> None:
    reply = emu.handle(p1.Packet(1, Instruction.PING, b"", checksum_ok=False))
    assert reply is not None and p1.Parser().feed(reply)[0].code == ErrorBit.CHECKSUM


def test_that_status_return_level_silences_writes_then_reads_but_never_ping(
        emu: EmulatedMX28) -> None:
    write(emu, Reg.STATUS_RETURN_LEVEL, 1, 1)
    assert write(emu, Reg.LED, 1, 1) is None
    assert emu.register(Reg.LED) == 1  # applied although not acknowledged
    assert ask(emu, Instruction.READ, bytes((Reg.LED, 1))) is not None
    write(emu, Reg.STATUS_RETURN_LEVEL, 0, 1)
    assert ask(emu, Instruction.READ, bytes((Reg.LED, 1))) is None
    assert ask(emu, Instruction.PING) is not None


def test_that_reg_write_waits_for_a_broadcast_action(emu: EmulatedMX28) -> None:
    ask(emu, Instruction.REG_WRITE, bytes((Reg.LED, 1)))
    assert emu.register(Reg.LED) == 0
    assert ask(emu, Instruction.READ, bytes((Reg.REGISTERED, 1))) == p1.Packet(1, 0, b"\x01")
    assert ask(emu, Instruction.ACTION, dxl_id=0xFE) is None
    assert emu.register(Reg.LED) == 1 and emu.register(Reg.REGISTERED) == 0


def test_that_sync_write_applies_its_own_slice_without_a_reply(emu: EmulatedMX28) -> None:
    params = bytes((Reg.GOAL_POSITION, 2, 3, 0x10, 0x00, 1, 0x20, 0x01))
    assert ask(emu, Instruction.SYNC_WRITE, params, dxl_id=0xFE) is None
    assert emu.register(Reg.GOAL_POSITION) == 0x120


def test_that_bulk_read_answers_the_entry_for_this_id(emu: EmulatedMX28) -> None:
    reply = ask(emu, Instruction.BULK_READ, bytes((0, 2, 5, 36, 2, 1, 0)), dxl_id=0xFE)
    assert reply == p1.Packet(1, 0, bytes((29, 0)))


def test_that_factory_reset_returns_to_joint_mode_and_id_1(emu: EmulatedMX28) -> None:
    write(emu, Reg.CW_ANGLE_LIMIT, 0x0FFF0FFF, 4)
    assert emu.mode() is Mode.MULTI_TURN
    assert ask(emu, Instruction.RESET) is not None
    assert emu.mode() is Mode.JOINT and emu.register(Reg.ID) == 1


def test_that_multi_turn_motion_drives_the_vehicle_tilt_at_the_moving_speed(
        emu: EmulatedMX28, bench: BenchVehicle) -> None:
    # Fixture: multi-turn, Moving Speed 292 (33.3 rpm = 9.99 deg/s of tilt).
    write(emu, Reg.CW_ANGLE_LIMIT, 0x0FFF0FFF, 4)
    write(emu, Reg.MOVING_SPEED, 292, 2)
    # Test
    write(emu, Reg.GOAL_POSITION, 7964, 2)
    run(emu, bench, 1.0)
    after_1s = bench.tilt_rad()
    run(emu, bench, 3.0)
    # Assert: 292 * 0.114 rpm * 6 deg/s/rpm * 0.05 = 9.99 deg/s of tilt.
    assert after_1s / DEG == pytest.approx(292 * 0.114 * 6 * 0.05, abs=0.1)
    assert bench.tilt_rad() / DEG == pytest.approx(35.0, abs=0.01)
    assert emu.register(Reg.PRESENT_POSITION) == 7964
    assert emu.register(Reg.TORQUE_ENABLE) == 1  # writing a goal turns the torque on


def test_that_negative_multi_turn_positions_are_signed(emu: EmulatedMX28,
                                                       bench: BenchVehicle) -> None:
    emu2 = EmulatedMX28(bench, zero_offset_steps=-8000)
    try:
        write(emu2, Reg.CW_ANGLE_LIMIT, 0x0FFF0FFF, 4)
        emu2.step()
        reply = ask(emu2, Instruction.READ, bytes((Reg.PRESENT_POSITION, 2)))
        assert reply is not None and reply.params == (-8000 & 0xFFFF).to_bytes(2, "little")
    finally:
        emu2.close()


def test_that_the_top_speed_caps_moving_speed_zero(emu: EmulatedMX28,
                                                   bench: BenchVehicle) -> None:
    write(emu, Reg.CW_ANGLE_LIMIT, 0x0FFF0FFF, 4)
    write(emu, Reg.GOAL_POSITION, 7964, 2)  # Moving Speed 0 = as fast as possible
    run(emu, bench, 0.5)
    # 55 rpm = 330 deg/s at the servo = 16.5 deg/s of tilt, but the bench allows 100.
    assert bench.tilt_rad() / DEG == pytest.approx(0.5 * 16.5, abs=0.2)


def test_that_an_overload_above_the_torque_limit_sets_the_bit_and_shuts_down(
        emu: EmulatedMX28, bench: BenchVehicle) -> None:
    write(emu, Reg.TORQUE_ENABLE, 1, 1)
    write(emu, Reg.TORQUE_LIMIT, 500, 2)
    emu.set_external_load(0.6)
    run(emu, bench, 0.01)
    reply = ask(emu, Instruction.PING)
    assert reply is not None and reply.code & ErrorBit.OVERLOAD
    assert emu.register(Reg.TORQUE_ENABLE) == 0  # Shutdown mask 0x24 includes overload


def test_that_the_thermal_model_heats_under_load_until_overheating(
        bench: BenchVehicle) -> None:
    emu = EmulatedMX28(bench, thermal_time_constant_s=1.0, full_load_temp_rise_c=80.0)
    try:
        write(emu, Reg.SHUTDOWN, 0, 1)  # keep the torque on whatever happens
        write(emu, Reg.TORQUE_ENABLE, 1, 1)
        emu.set_external_load(0.95)  # below the torque limit: no overload
        run(emu, bench, 5.0, dt=0.01)
        # Steady state 25 + 80 * 0.95^2 = 97 C; after 5 time constants within 1 C of it.
        assert emu.temperature_c == pytest.approx(25 + 80 * 0.95**2, abs=1.0)
        reply = ask(emu, Instruction.PING)
        assert reply is not None and reply.code == ErrorBit.OVERHEATING
    finally:
        emu.close()


def test_that_overheating_shuts_the_torque_down_by_default(bench: BenchVehicle) -> None:
    emu = EmulatedMX28(bench, thermal_time_constant_s=1.0, full_load_temp_rise_c=80.0)
    try:
        write(emu, Reg.TORQUE_ENABLE, 1, 1)
        emu.set_external_load(0.95)
        run(emu, bench, 2.0, dt=0.01)
        assert emu.register(Reg.TORQUE_ENABLE) == 0
        assert emu.temperature_c < 97.0
    finally:
        emu.close()


def test_that_a_supply_outside_the_voltage_limits_sets_the_voltage_bit(
        emu: EmulatedMX28) -> None:
    emu.set_supply_voltage(17.0)
    reply = ask(emu, Instruction.PING)
    assert reply is not None and reply.code == ErrorBit.VOLTAGE


def test_that_a_power_cycle_loses_the_turn_count_and_the_torque(
        emu: EmulatedMX28, bench: BenchVehicle) -> None:
    write(emu, Reg.CW_ANGLE_LIMIT, 0x0FFF0FFF, 4)
    write(emu, Reg.MOVING_SPEED, 0, 2)
    write(emu, Reg.GOAL_POSITION, 7964, 2)
    run(emu, bench, 3.0)
    emu.power_cycle()
    emu.step()
    assert emu.register(Reg.TORQUE_ENABLE) == 0
    assert emu.mode() is Mode.MULTI_TURN  # EEPROM kept
    assert emu.register(Reg.PRESENT_POSITION) == 7964 - 4096
    assert bench.tilt_rad() / DEG == pytest.approx(35.0, abs=0.01)  # the worm holds


@settings(max_examples=300, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.integers(0, 0xFE), st.integers(0, 0xFF), st.binary(max_size=40), st.booleans())
def test_that_any_instruction_is_answered_with_a_well_formed_status_or_nothing(
        emu: EmulatedMX28, dxl_id: int, code: int, params: bytes, ok: bool) -> None:
    id_before = emu.register(Reg.ID)
    reply = emu.handle(p1.Packet(dxl_id, code, params, ok))
    if reply is not None:
        (status,) = p1.Parser().feed(reply)
        assert status.checksum_ok and status.dxl_id in (id_before, emu.register(Reg.ID))
        assert status.code <= 0x7F
    assert emu.register(Reg.MODEL_NUMBER) == 29  # read-only stays read-only

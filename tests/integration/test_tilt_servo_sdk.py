"""The unmodified dynamixel-sdk 4.1.0 client against the emulated MX-28T over a real pty."""

from __future__ import annotations

import math
from collections.abc import Iterator

import dynamixel_sdk as sdk
import pytest

from drivers.dynamixel.control_table import Mode, Reg, to_signed16
from sim_backend.emulators.dynamixel_p1 import EmulatedMX28, Fault
from sim_backend.vehicle import BenchVehicle


@pytest.fixture
def emulator() -> Iterator[EmulatedMX28]:
    emu = EmulatedMX28(BenchVehicle(max_tilt_rate_rad_s=math.radians(100.0)), drive_clock=True)
    with emu:
        yield emu


@pytest.fixture
def port(emulator: EmulatedMX28) -> Iterator[sdk.PortHandler]:
    handler = sdk.PortHandler(emulator.path)
    assert handler.openPort()
    assert handler.setBaudRate(1_000_000)
    yield handler
    handler.closePort()


def test_that_the_sdk_pings_the_emulator_and_reads_model_29(port: sdk.PortHandler) -> None:
    model, result, error = sdk.PacketHandler(1.0).ping(port, 1)
    assert (model, result, error) == (29, sdk.COMM_SUCCESS, 0)


def test_that_a_string_protocol_version_silently_speaks_p2_and_gets_no_answer(
        port: sdk.PortHandler) -> None:
    _, result, _ = sdk.PacketHandler("1.0").ping(port, 1)
    assert result == sdk.COMM_RX_TIMEOUT


def test_that_multi_turn_goals_and_negative_positions_round_trip_through_the_sdk(
        emulator: EmulatedMX28, port: sdk.PortHandler) -> None:
    ph = sdk.PacketHandler(1.0)
    assert ph.write4ByteTxRx(port, 1, Reg.CW_ANGLE_LIMIT, 0x0FFF0FFF) == (sdk.COMM_SUCCESS, 0)
    assert emulator.mode() is Mode.MULTI_TURN
    assert ph.write2ByteTxRx(port, 1, Reg.GOAL_POSITION, -7964 & 0xFFFF) == (sdk.COMM_SUCCESS, 0)
    raw, result, _ = ph.read2ByteTxRx(port, 1, Reg.GOAL_POSITION)
    assert result == sdk.COMM_SUCCESS and to_signed16(raw) == -7964


def test_that_a_garbled_reply_is_corrupt_and_the_next_transaction_is_clean(
        emulator: EmulatedMX28, port: sdk.PortHandler) -> None:
    ph = sdk.PacketHandler(1.0)
    emulator.set_fault(Fault.GARBLE)
    assert ph.read1ByteTxRx(port, 1, Reg.PRESENT_TEMPERATURE)[1] == sdk.COMM_RX_CORRUPT
    emulator.set_fault(Fault.NONE)
    assert ph.read1ByteTxRx(port, 1, Reg.PRESENT_TEMPERATURE) == (25, sdk.COMM_SUCCESS, 0)


def test_that_with_status_return_level_1_a_write_times_out_although_applied(
        emulator: EmulatedMX28, port: sdk.PortHandler) -> None:
    ph = sdk.PacketHandler(1.0)
    assert ph.write1ByteTxRx(port, 1, Reg.STATUS_RETURN_LEVEL, 1) == (sdk.COMM_SUCCESS, 0)
    assert ph.write1ByteTxRx(port, 1, Reg.LED, 1)[0] == sdk.COMM_RX_TIMEOUT
    assert emulator.register(Reg.LED) == 1


def test_that_a_client_at_the_wrong_baud_gets_silence_until_it_switches(
        emulator: EmulatedMX28, port: sdk.PortHandler) -> None:
    ph = sdk.PacketHandler(1.0)
    assert port.setBaudRate(57600)  # the servo is at 1 Mbps (Baud Rate register 1)
    assert ph.ping(port, 1)[1] == sdk.COMM_RX_TIMEOUT
    assert emulator.wrong_baud_bytes > 0
    assert port.setBaudRate(1_000_000)
    assert ph.ping(port, 1)[:2] == (29, sdk.COMM_SUCCESS)

"""The emulated Flight-Ctrl on its own: stock-firmware answers, lockstep determinism, faults.

Stock frames are checked with our stock codec and with the reference's byte vectors; the tk3
side is exercised through the raw transport, without the FlightCtrl device, so that what is
checked is the emulator's own behaviour on the wire.
"""

from __future__ import annotations

import threading
import time

from drivers.mikrokopter import framing_stock as mk
from drivers.mikrokopter import framing_tk3 as tk3
from drivers.mikrokopter import messages as mkm
from drivers.transport import Transport, open_transport
from sim_backend.emulators.flightctrl import (
    EmulatedFlightCtrl,
    FlightCtrlEmulatorConfig,
    WireFaults,
)
from sim_backend.vehicle import BenchVehicle

TIMEOUT_S = 20.0


def _stock_replies(t: Transport, parser: mk.StockParser, want: int) -> list[mkm.StockMessage]:
    out: list[mkm.StockMessage] = []
    deadline = time.monotonic() + TIMEOUT_S
    while len(out) < want:
        assert time.monotonic() < deadline, f"got {out}"
        for frame in parser.feed(t.read(4096)):
            assert frame.address == mk.Address.FLIGHT_CTRL
            out.append(mkm.decode_stock_message(frame.cmd, frame.data))
    return out


def _tk3_messages(t: Transport, parser: tk3.Tk3Parser, want: int,
                  kind: type | None = None) -> list[mkm.BoardMessage]:
    out: list[mkm.BoardMessage] = []
    deadline = time.monotonic() + TIMEOUT_S
    while len(out) < want:
        assert time.monotonic() < deadline, f"got {out}"
        for raw in parser.feed(t.read(4096)):
            msg = mkm.decode_board_message(raw)
            if kind is None or isinstance(msg, kind):
                out.append(msg)
    return out[:want]  # the first `want` (a loaded host may deliver more in one read)


def test_that_a_stock_board_answers_the_reference_version_request_byte_for_byte() -> None:
    vehicle = BenchVehicle()
    with EmulatedFlightCtrl(vehicle, config=FlightCtrlEmulatorConfig(firmware="stock")) as emu:
        t = open_transport(f"pty://{emu.path}")
        try:
            t.write(bytes.fromhex("23 62 76 40 78 0d"))  # '#bv@x\r' from the reference
            got = b""
            deadline = time.monotonic() + TIMEOUT_S
            while not got.endswith(b"\r"):
                assert time.monotonic() < deadline
                got += t.read(64)
            # The reference's V vector: SW 2.12, proto 11, LabelTextCRC 0xA5, HW 25, BL 255
            assert got == bytes.fromhex("23 62 56 3d 5d 6d 48 66 4d 3d 3d 3d 3e 64 7c 3d 3d 3d 3d"
                                        " 53 63 0d")
            # a tk3 '?' is not understood by a stock board
            t.write(b"^?$")
            t.write(mk.encode_frame(mk.Address.ANY, b"v"))
            (version,) = _stock_replies(t, mk.StockParser(), 1)
            assert isinstance(version, mkm.VersionInfo)
        finally:
            t.close()


def test_that_a_stock_board_streams_debug_and_runs_the_engine_test() -> None:
    vehicle = BenchVehicle()
    lock = threading.Lock()
    with EmulatedFlightCtrl(vehicle, lock=lock,
                            config=FlightCtrlEmulatorConfig(firmware="stock")) as emu:
        t = open_transport(f"pty://{emu.path}")
        parser = mk.StockParser()
        try:
            engine_test = mk.encode_frame(mk.Address.FLIGHT_CTRL, b"t",
                                          bytes([255] * 6 + [0] * 10))
            t.write(engine_test)
            (ack,) = _stock_replies(t, parser, 1)
            assert isinstance(ack, mkm.EngineTestAck)
            t.write(mk.encode_frame(mk.Address.ANY, b"d", mkm.DebugRequest(20).payload()))
            debug: list[mkm.DebugOut] = []
            while len(debug) < 30:
                # the engine test times out unless renewed, as on the real board
                t.write(engine_test)
                debug += [m for m in _stock_replies(t, parser, 1) if isinstance(m, mkm.DebugOut)]
            # 16.4 V open circuit minus the sag of six motors at full engine-test set-point
            assert 14.0 < debug[-1].voltage_v < 16.3
            assert debug[-1].analog[12] > 200  # motor 1 set-point seen through Analog[12]
            with lock:
                assert min(vehicle.rotor_speeds_hz()) > 90.0
        finally:
            t.close()


def _lockstep_run(seed: int, ticks: int) -> list[bytes]:
    vehicle = BenchVehicle(seed=seed)
    with EmulatedFlightCtrl(vehicle, config=FlightCtrlEmulatorConfig(clock="lockstep")) as emu:
        t = open_transport(f"pty://{emu.path}")
        parser = tk3.Tk3Parser()
        frames: list[bytes] = []
        try:
            t.write(tk3.encode_frame(mkm.SetStreamPeriod(mkm.Stream.IMU, 2000).encode()))
            for i in range(ticks):
                (imu,) = _tk3_messages(t, parser, 1, mkm.ImuMessage)
                frames.append(imu.encode())
                t.write(tk3.encode_frame(mkm.SpinRates.from_hz([40.0 + i % 7] * 6).encode()))
            # the kick sample plus one per w; the last w may still be in flight
            assert round(emu.sim_time_s() / 0.002) in (ticks - 1, ticks)
        finally:
            t.close()
    return frames


def test_that_lockstep_runs_are_deterministic_for_a_seed() -> None:
    first = _lockstep_run(5, 300)
    assert first == _lockstep_run(5, 300)
    assert first != _lockstep_run(6, 300)
    assert [f[1] for f in first] == [i % 256 for i in range(300)]


def test_that_lockstep_free_runs_when_the_ground_station_goes_silent() -> None:
    vehicle = BenchVehicle()
    cfg = FlightCtrlEmulatorConfig(clock="lockstep", lockstep_grace_s=0.1)
    with EmulatedFlightCtrl(vehicle, config=cfg) as emu:
        t = open_transport(f"pty://{emu.path}")
        try:
            t.write(tk3.encode_frame(mkm.SetStreamPeriod(mkm.Stream.IMU, 2000).encode()))
            # one `w`, then silence: after the grace period the samples come anyway, paced in
            # real time (before the first `w` ever, the much longer first-`w` grace applies)
            t.write(tk3.encode_frame(mkm.SpinRates((0,) * 6).encode()))
            imus = _tk3_messages(t, tk3.Tk3Parser(), 20, mkm.ImuMessage)
            assert [m.seq for m in imus] == list(range(20))  # type: ignore[union-attr]
            assert emu.stats().freerun_entries >= 1
        finally:
            t.close()


def test_that_every_motor_reports_its_state_each_motor_period() -> None:
    vehicle = BenchVehicle()
    with EmulatedFlightCtrl(vehicle, config=FlightCtrlEmulatorConfig()) as emu:
        t = open_transport(f"pty://{emu.path}")
        try:
            t.write(tk3.encode_frame(mkm.StartMotors(3).encode()))
            t.write(tk3.encode_frame(mkm.SetStreamPeriod(mkm.Stream.MOTOR, 10_000).encode()))
            motors = _tk3_messages(t, tk3.Tk3Parser(), 12, mkm.MotorMessage)
            ids = [m.motor_id for m in motors]  # type: ignore[union-attr]
            assert sorted(ids[:6]) == [1, 2, 3, 4, 5, 6]
            third = [m for m in motors if m.motor_id == 3]  # type: ignore[union-attr]
            assert all(m.starting or m.spinning for m in third)  # type: ignore[union-attr]
        finally:
            t.close()


def test_that_corruption_and_drops_are_applied_at_the_configured_rate() -> None:
    vehicle = BenchVehicle()
    faults = WireFaults(corrupt_prob=0.05, drop_prob=0.05, seed=1)
    cfg = FlightCtrlEmulatorConfig(clock="lockstep", faults=faults, record_truth=True,
                                   lockstep_grace_s=0.05)
    with EmulatedFlightCtrl(vehicle, config=cfg) as emu:
        t = open_transport(f"pty://{emu.path}")
        try:
            t.write(tk3.encode_frame(mkm.SetStreamPeriod(mkm.Stream.IMU, 1000).encode()))
            deadline = time.monotonic() + TIMEOUT_S
            while emu.stats().imu_sent < 2000:
                assert time.monotonic() < deadline
                t.read(4096)
                t.write(tk3.encode_frame(mkm.SpinRates.from_hz([0.0] * 6).encode()))
        finally:
            t.close()
    stats = emu.stats()
    sent_bytes = 16 * stats.frames_sent
    # binomial: 5 % of ~32000 bytes, 6 sigma bounds
    for n in (stats.bytes_corrupted, stats.bytes_dropped):
        assert abs(n - 0.05 * sent_bytes) < 6 * (0.05 * 0.95 * sent_bytes) ** 0.5

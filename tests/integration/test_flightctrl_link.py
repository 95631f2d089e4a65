"""The real FlightCtrl driver against the emulated Flight-Ctrl over a real pty."""

from __future__ import annotations

import contextlib
import itertools
import math
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import replace

import pytest

from drivers.errors import DeviceLostError
from drivers.mikrokopter import (
    FlightCtrl,
    FlightCtrlConfig,
    FlightCtrlIdentityError,
    ImuSample,
    MotorState,
    StockFirmwareError,
    probe,
)
from drivers.mikrokopter import framing_tk3 as tk3
from drivers.mikrokopter import messages as mkm
from sim_backend.emulators.flightctrl import (
    EmulatedFlightCtrl,
    FlightCtrlEmulatorConfig,
    SentImu,
    WireFaults,
)
from sim_backend.ptylink import PtyEndpoint
from sim_backend.vehicle import GRAVITY_M_S2, BenchVehicle

TIMEOUT_S = 20.0  # generous: the CI machine is shared and loaded


MakeLink = Callable[..., tuple[EmulatedFlightCtrl, FlightCtrl, BenchVehicle]]


@pytest.fixture
def make_link() -> Iterator[MakeLink]:
    opened: list[tuple[EmulatedFlightCtrl, FlightCtrl]] = []

    def make(emu_config: FlightCtrlEmulatorConfig | None = None,
             fc_config: FlightCtrlConfig | None = None, connect: bool = True,
             ) -> tuple[EmulatedFlightCtrl, FlightCtrl, BenchVehicle]:
        vehicle = BenchVehicle(seed=3)
        emu = EmulatedFlightCtrl(vehicle, lock=threading.Lock(),
                                 config=emu_config or FlightCtrlEmulatorConfig(record_truth=True))
        emu.start()
        fc = FlightCtrl.open(f"pty://{emu.path}", fc_config)
        opened.append((emu, fc))
        if connect:
            fc.connect()
        return emu, fc, vehicle

    yield make
    for emu, fc in opened:
        fc.close()
        emu.stop()


def _lockstep(**kw: object) -> FlightCtrlEmulatorConfig:
    return FlightCtrlEmulatorConfig(clock="lockstep", record_truth=True, **kw)  # type: ignore[arg-type]


def _fly(fc: FlightCtrl, ticks: int, speeds_hz: list[float], resend_s: float | None = None
         ) -> list[ImuSample]:
    """The 500 Hz loop's I/O: per IMU sample, one w frame.

    With ``resend_s``, a w is also sent when no sample came for that long (a sample lost on a
    damaged wire would otherwise stall a lockstep exchange)."""
    samples: list[ImuSample] = []
    deadline = time.monotonic() + TIMEOUT_S
    while len(samples) < ticks:
        assert time.monotonic() < deadline, f"only {len(samples)} of {ticks} samples"
        sample = fc.wait_next(resend_s if resend_s is not None else TIMEOUT_S)
        if sample is not None:
            samples.append(sample)
        fc.send_rotor_speeds_hz(speeds_hz)
    return samples


def _truth(emu: EmulatedFlightCtrl) -> dict[int, SentImu]:
    return {s.seq: s for s in list(emu.sent_imu)}


def test_that_the_driver_identifies_the_emulated_board(make_link: MakeLink) -> None:
    _, fc, _ = make_link(connect=False)
    ident = fc.connect()
    assert (ident.protocol, ident.firmware_id, ident.accepted) == ("tk3", "mkfl1.8", True)


def test_that_an_unaccepted_firmware_id_is_refused_naming_the_device(make_link: MakeLink) -> None:
    emu, fc, _ = make_link(FlightCtrlEmulatorConfig(firmware_id="mkfl1.5"), connect=False)
    with pytest.raises(FlightCtrlIdentityError, match=r"mkfl1\.5") as info:
        fc.connect()
    assert info.value.device == emu.path


@contextlib.contextmanager
def _identity_board(replies: list[str]) -> Iterator[tuple[PtyEndpoint, list[bytes]]]:
    """A board on a real pty that answers each tk3 ``?`` with the next of ``replies`` (then
    stays silent); what it was sent is collected, complete once the context exits."""
    board = PtyEndpoint()
    heard: list[bytes] = []
    stop = threading.Event()

    def answer() -> None:
        pending = list(replies)
        while not stop.is_set():
            if board.wait_readable(0.05) and (data := board.read()):
                heard.append(data)
                for _ in range(data.count(b"^?$")):
                    if pending:
                        board.write(tk3.encode_frame(b"?" + pending.pop(0).encode("latin-1")))

    thread = threading.Thread(target=answer, daemon=True)
    thread.start()
    try:
        yield board, heard
    finally:
        stop.set()
        thread.join()
        if rest := board.read():  # anything sent after the last answer
            heard.append(rest)
        board.close()


def test_that_a_corrupted_identity_is_asked_again_and_the_board_accepted() -> None:
    # Fixture: tk3 frames carry no checksum; one byte of the first answer was hit on the line
    with _identity_board(["mk\x10l1.8", "mkfl1.8"]) as (board, heard):
        fc = FlightCtrl.open(f"pty://{board.path}", FlightCtrlConfig(identify_timeout_s=2.0))
        try:
            # Test
            ident = fc.identify()
        finally:
            fc.close()
    # Assert: the second answer is taken
    assert (ident.protocol, ident.firmware_id, ident.accepted) == ("tk3", "mkfl1.8", True)
    wire = b"".join(heard)  # then what close() sends
    assert wire.startswith(b"^?$^?$^") and wire.count(b"^?$") == 2


@pytest.mark.parametrize(("replies", "expected"), [
    (["mkfl1.5"] * 4, r"firmware id 'mkfl1\.5' is not one of the accepted mkfl1\.8\*$"),
    (["mk\x10l1.8", "mkfl1.5", "mk\x10l1.8", "mkfl\x7f.8"],
     r"firmware ids differ from one answer to the next \('mk\\x10l1\.8', 'mkfl1\.5', "
     r"'mkfl\\x7f\.8'\).*a corrupted link\?"),
])
def test_that_a_board_never_giving_an_accepted_id_is_refused_after_every_try(
        replies: list[str], expected: str) -> None:
    with _identity_board(replies) as (board, heard):
        fc = FlightCtrl.open(f"pty://{board.path}", FlightCtrlConfig(identify_timeout_s=2.0))
        try:
            with pytest.raises(FlightCtrlIdentityError, match=expected):
                fc.connect()
        finally:
            fc.close()
    wire = b"".join(heard)  # identify_attempts, no stock 'v', then what close() sends
    assert wire.count(b"^?$") == 4 and b"#bv" not in wire


def test_that_a_stock_firmware_board_is_reported_as_unable_to_fly(make_link: MakeLink) -> None:
    fast = FlightCtrlConfig(identify_attempts=2, identify_timeout_s=0.2)
    _, fc, _ = make_link(FlightCtrlEmulatorConfig(firmware="stock"), fast, connect=False)
    ident = fc.identify()
    assert (ident.protocol, ident.firmware_id, ident.accepted) == ("stock", "2.12a", False)
    with pytest.raises(StockFirmwareError, match="cannot stream the IMU at 500 Hz"):
        fc.connect()


def test_that_a_silent_port_raises_a_typed_error_naming_the_device() -> None:
    with PtyEndpoint() as silent:
        fc = FlightCtrl.open(f"pty://{silent.path}",
                             FlightCtrlConfig(identify_attempts=2, identify_timeout_s=0.05))
        try:
            with pytest.raises(FlightCtrlIdentityError, match="no answer") as info:
                fc.connect()
            assert info.value.device == silent.path
            # the host asked exactly as the reference says: two '?' then one stock 'v'
            sent = silent.read()
            assert sent == b"^?$^?$#bv@x\r"
        finally:
            fc.close()


@pytest.mark.parametrize("rate_hz", [500.0, 1000.0])
def test_that_imu_streams_at_the_set_rate_in_lockstep(rate_hz: float, make_link: MakeLink) -> None:
    # Fixture
    emu, fc, _ = make_link(_lockstep(), FlightCtrlConfig(imu_rate_hz=rate_hz))
    # Test
    samples = _fly(fc, 400, [0.0] * 6)
    # Assert: consecutive samples, one IMU period of simulated time apart, values exact
    truth = _truth(emu)
    period_ns = round(1e9 / rate_hz)
    seqs = [s.seq for s in samples]
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))
    for a, b in itertools.pairwise(samples):
        assert truth[b.seq].t_ns - truth[a.seq].t_ns == period_ns
        assert b.board_t_ns - a.board_t_ns == period_ns
    for s in samples:
        sent = truth[s.seq].message
        assert s.accel_m_s2 == sent.accel_m_s2 and s.gyro_rad_s == sent.gyro_rad_s
        assert s.accel_m_s2[2] == pytest.approx(GRAVITY_M_S2, abs=0.4)  # +g on body z at rest
    assert fc.link_stats().dropped == 0


@pytest.mark.parametrize("rate_hz", [500.0, 1000.0])
def test_that_imu_streams_at_the_set_rate_in_realtime(rate_hz: float, make_link: MakeLink) -> None:
    emu, fc, _ = make_link(fc_config=FlightCtrlConfig(imu_rate_hz=rate_hz))
    samples = _fly(fc, 200, [0.0] * 6)
    truth = _truth(emu)
    period_ns = round(1e9 / rate_hz)
    # The emulator sends on the simulated-time schedule (a loaded machine skips periods,
    # never bunches them): every interval is a whole number of periods.
    sent = sorted(truth.values(), key=lambda s: s.seq)
    assert all((b.t_ns - a.t_ns) % period_ns == 0 for a, b in itertools.pairwise(sent))
    for s in samples:
        assert s.accel_m_s2 == truth[s.seq].message.accel_m_s2
    stats = fc.link_stats()
    assert stats.imu.nominal_rate_hz == rate_hz
    assert stats.imu.received >= 200


def test_that_six_motors_start_and_report_the_commanded_spin_rates(make_link: MakeLink) -> None:
    # Fixture
    _, fc, vehicle = make_link(_lockstep(), FlightCtrlConfig(motor_rate_hz=100.0))
    # Test
    started = fc.start_motors(timeout_s=TIMEOUT_S)
    command = [60.0, 70.0, 80.0, 90.0, 100.0, 50.0]
    _fly(fc, 300, command)  # 0.6 s: 20 rotor time constants
    motors = fc.wait_motor_update(TIMEOUT_S)
    # Assert
    assert started.all_spinning
    assert motors is not None and motors.all_spinning
    for measured, wanted in zip(motors.speeds_hz, command, strict=True):
        # half-period quantisation: below wanted^2 / 5e5 Hz
        assert measured == pytest.approx(wanted, abs=wanted**2 / 5e5 + 1e-6)
    assert all(0.2 < c < 10.0 for c in motors.currents_a)
    assert vehicle.rotor_speeds_hz() == pytest.approx(command, abs=0.05)


@pytest.mark.parametrize("clock", ["lockstep", "realtime"])
def test_that_the_watchdog_stops_the_motors_and_raises_the_emergency_flag(
        clock: str, make_link: MakeLink) -> None:
    # Fixture: motors spinning at 70 Hz
    # watchdog longer than any scheduling hiccup of a loaded machine while we do send w
    cfg = FlightCtrlEmulatorConfig(clock=clock, watchdog_s=0.5,  # type: ignore[arg-type]
                                   lockstep_grace_s=0.2)
    emu, fc, _ = make_link(cfg, FlightCtrlConfig(motor_rate_hz=100.0))
    fc.start_motors(timeout_s=TIMEOUT_S)
    _fly(fc, 100, [70.0] * 6)
    assert emu.stats().watchdog_trips == 0
    # Test: the ground station goes silent
    deadline = time.monotonic() + TIMEOUT_S
    snap = fc.motors()
    while not all(m is not None and m.state == MotorState.EMERGENCY for m in snap.motors):
        assert time.monotonic() < deadline, f"no emergency: {snap}"
        snap = fc.wait_motor_update(1.0) or snap
    # Assert
    assert emu.stats().watchdog_trips == 1
    assert emu.commanded_rotor_speeds_hz() == (0.0,) * 6  # the vehicle's rotors were stopped


def test_that_a_disconnect_raises_device_lost_naming_the_device(make_link: MakeLink) -> None:
    emu, fc, _ = make_link()
    assert fc.wait_next(TIMEOUT_S) is not None
    path = emu.path
    emu.disconnect()
    deadline = time.monotonic() + TIMEOUT_S
    with pytest.raises(DeviceLostError) as info:
        while time.monotonic() < deadline:
            fc.wait_next(0.1)
    assert info.value.device == path
    assert fc.health().name == "LOST"
    with pytest.raises(DeviceLostError):
        fc.send_rotor_speeds_hz([50.0] * 6)


def test_that_a_timed_disconnect_is_seen_as_device_lost(make_link: MakeLink) -> None:
    cfg = replace(_lockstep(), faults=WireFaults(disconnect_after_s=0.1))
    emu, fc, _ = make_link(cfg)
    with pytest.raises(DeviceLostError):
        _fly(fc, 1000, [0.0] * 6)
    assert emu.sim_time_s() == pytest.approx(0.1)


def test_that_output_paced_at_500_kbaud_carries_the_1_khz_stream(make_link: MakeLink) -> None:
    emu, fc, _ = make_link(replace(_lockstep(), faults=WireFaults(baud=500_000)),
                           FlightCtrlConfig(imu_rate_hz=1000.0))
    samples = _fly(fc, 200, [0.0] * 6)
    truth = _truth(emu)
    assert all(s.gyro_rad_s == truth[s.seq].message.gyro_rad_s for s in samples)
    assert emu.stats().tx_overruns == 0


def _decode_wire_imu(wire: bytes) -> mkm.ImuMessage | None:
    """What any tk3 receiver makes of an (altered) I frame alone: one valid I, or nothing."""
    msgs = tk3.Tk3Parser().feed(wire)
    out = []
    for raw in msgs:
        try:
            msg = mkm.decode_board_message(raw)
        except mkm.MalformedMessageError:
            continue
        if isinstance(msg, mkm.ImuMessage):
            out.append(msg)
    return out[0] if len(out) == 1 else None


def test_that_one_percent_corrupted_bytes_are_dropped_and_counted(make_link: MakeLink) -> None:
    # Fixture: 1 % of the board's bytes corrupted, in lockstep (deterministic wire damage)
    emu, fc, _ = make_link(replace(_lockstep(), faults=WireFaults(corrupt_prob=0.01, seed=7)),
                           FlightCtrlConfig(motor_rate_hz=50.0))
    # Test
    samples = _fly(fc, 1500, [0.0] * 6, resend_s=0.02)
    # Assert
    truth = _truth(emu)
    stats = fc.link_stats()
    estats = emu.stats()
    assert estats.bytes_corrupted > 100  # the wire really was damaged
    altered = {k: v for k, v in truth.items() if v.altered}
    readable: dict[int, mkm.ImuMessage] = {}
    for k, v in altered.items():
        wire_msg = _decode_wire_imu(v.wire)
        if wire_msg is not None:
            readable[k] = wire_msg
    undetectable = held = 0
    exact: set[int] = set()
    prev: tuple[float, ...] | None = None  # the accelerometer last delivered

    def same(m: mkm.ImuMessage, s: ImuSample) -> tuple[bool, bool]:
        """(s is m's sample, with an accelerometer axis held at the last delivered value)."""
        if m.gyro_rad_s != s.gyro_rad_s:
            return False, False
        own = [a == b for a, b in zip(s.accel_m_s2, m.accel_m_s2, strict=True)]
        if all(own):
            return True, False
        return (prev is not None and all(o or a == p for o, a, p in
                                         zip(own, s.accel_m_s2, prev, strict=True)), True)

    for s in samples:
        sent = truth[s.seq].message
        ok, was_held = same(sent, s)
        if ok and not was_held:
            exact.add(s.seq)
        elif not ok:
            # A value that differs from what the board sent can only come from a frame that
            # the wire altered into another well-formed 14-byte I message: tk3 has no
            # checksum, so no receiver can tell. Anything else would be a driver bug.
            candidates = [readable[k] for k in range(s.seq - 20, s.seq + 21) if k in readable]
            found = [same(m, s) for m in candidates if m.seq == s.seq % 256]
            assert any(ok for ok, _ in found), s
            was_held = not any(ok and not h for ok, h in found)
            undetectable += 1
        # an accelerometer spike under the implausible-step limit is held at the value before
        held += was_held
        prev = s.accel_m_s2
    assert held <= stats.accel_spikes_held
    # every altered frame that no receiver could read as an I sample is dropped and counted
    unreadable = [k for k in altered if k not in readable]
    assert not exact & set(unreadable)
    assert stats.dropped + stats.imu.missing >= len(unreadable)
    assert len(samples) == 1500  # the link kept running
    print(f"\n{estats.bytes_corrupted} bytes corrupted, {len(altered)} I frames altered, "
          f"{len(unreadable)} unreadable (dropped, counted), {undetectable} delivered with "
          f"undetectable in-place damage, {held} with a spike held; link: {stats}")
    assert math.isfinite(stats.imu.measured_rate_hz)


@pytest.mark.parametrize(("firmware", "expected"), [("tk3", ("tk3", "mkfl1.8", True)),
                                                     ("stock", ("stock", "2.12a", False))])
def test_that_probe_identifies_a_board_without_configuring_it(
        firmware: str, expected: tuple[str, str, bool]) -> None:
    config = FlightCtrlEmulatorConfig(firmware=firmware)  # type: ignore[arg-type]
    with EmulatedFlightCtrl(BenchVehicle(), config=config) as emu:
        ident = probe(f"serial://{emu.path}?baud=500000",
                      FlightCtrlConfig(identify_attempts=2, identify_timeout_s=0.2))
        assert (ident.protocol, ident.firmware_id, ident.accepted) == expected
        assert emu.stats().imu_sent == 0  # nothing was configured


def test_that_probe_retries_a_silent_serial_port_at_the_stock_speed() -> None:
    with PtyEndpoint() as silent:
        with pytest.raises(FlightCtrlIdentityError, match=r"no answer to 'v'"):
            probe(f"serial://{silent.path}?baud=500000",
                  FlightCtrlConfig(identify_attempts=1, identify_timeout_s=0.05))
        # '?' and 'v' at 500000 baud, then 'v' alone at 57600
        assert silent.read() == b"^?$#bv@x\r#bv@x\r"


def test_that_a_loop_reading_in_its_own_thread_gets_every_sample_and_motor_state(
        make_link: MakeLink) -> None:
    # Fixture: connected with the reader thread, then handed over to the caller's thread
    emu, fc, vehicle = make_link(_lockstep(), FlightCtrlConfig(motor_rate_hz=100.0))
    fc.read_in_caller_thread()
    # Test: the motor start waits and the loop's waits now read the port themselves
    started = fc.start_motors(timeout_s=TIMEOUT_S)
    command = [60.0, 70.0, 80.0, 90.0, 100.0, 50.0]
    samples = _fly(fc, 300, command)
    motors = fc.wait_motor_update(TIMEOUT_S)
    # Assert: no sample skipped, values exact, motors read back, no reader thread left
    truth = _truth(emu)
    seqs = [s.seq for s in samples]
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))
    assert all(s.gyro_rad_s == truth[s.seq].message.gyro_rad_s for s in samples)
    assert started.all_spinning
    assert motors is not None
    for measured, wanted in zip(motors.speeds_hz, command, strict=True):
        assert measured == pytest.approx(wanted, abs=wanted**2 / 5e5 + 1e-6)
    assert vehicle.rotor_speeds_hz() == pytest.approx(command, abs=0.05)
    assert not any(t.name.startswith("flightctrl-reader") for t in threading.enumerate())
    # and a pulled cable is still a typed loss, seen by the waiting loop
    emu.disconnect()
    with pytest.raises(DeviceLostError):
        _fly(fc, 1000, command, resend_s=0.1)

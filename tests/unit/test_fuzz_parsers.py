"""Every parser and emulator input side survives random and mutated bytes, and nothing
physically impossible comes out: the fast version of ``tools/fuzz.py`` (same targets, same
checks, a few hundred inputs each), plus the reproduced cases that used to break."""

from __future__ import annotations

import importlib.util
import os
import select
import sys
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from drivers.dynamixel import protocol1 as p1
from drivers.dynamixel.control_table import ErrorBit, Instruction
from drivers.mikrokopter import framing_tk3 as tk3
from drivers.mikrokopter import messages as mkm
from drivers.mikrokopter.device import FlightCtrl, FlightCtrlConfig, MotorState
from drivers.mocap import natnet, vrpn
from drivers.mocap.natnet_client import NatNetClient, NatNetConfig
from drivers.mocap.pose import PoseLimits
from drivers.mocap.uri import parse_uri
from drivers.mocap.vrpn_client import VrpnClient, VrpnConfig
from drivers.transport import LoopTransport
from sim_backend.emulators.dynamixel_p1 import EmulatedMX28
from sim_backend.emulators.flightctrl import EmulatedFlightCtrl, FlightCtrlEmulatorConfig
from sim_backend.vehicle import BenchVehicle


def _load_targets() -> ModuleType:
    path = Path(__file__).resolve().parents[2] / "tools" / "fuzz_targets.py"
    spec = importlib.util.spec_from_file_location("fuzz_targets", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules.setdefault("fuzz_targets", module)
    spec.loader.exec_module(module)
    return module


FT = _load_targets()
NAMES = list(FT.TARGETS)


@pytest.fixture(scope="module", params=NAMES)
def target(request: pytest.FixtureRequest) -> Iterator[object]:
    t = FT.TARGETS[request.param]()
    yield t
    t.close()


@st.composite
def _inputs(draw: st.DrawFn, seeds: list[bytes]) -> bytes:
    """Random bytes, or a valid frame of the protocol with a few bytes changed, cut or added."""
    if draw(st.booleans()):
        return draw(st.binary(max_size=300))
    data = bytearray(draw(st.sampled_from(seeds)))
    for _ in range(draw(st.integers(1, 4))):
        op = draw(st.integers(0, 2))
        pos = draw(st.integers(0, len(data)))
        if op == 0 and pos < len(data):
            data[pos] = draw(st.integers(0, 255))
        elif op == 1:
            data[pos:pos] = draw(st.binary(min_size=1, max_size=8))
        else:
            del data[pos:pos + draw(st.integers(1, 8))]
    return bytes(data)


def test_that_random_and_mutated_bytes_never_raise_nor_deliver_impossible_values(
        target: object) -> None:
    # Fixture
    t = target
    seeds: list[bytes] = t.seeds  # type: ignore[attr-defined]

    @settings(max_examples=100, deadline=None, derandomize=True, database=None,
              suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
    @given(_inputs(seeds))
    def check(data: bytes) -> None:
        # Test
        try:
            bad = t.run(data)  # type: ignore[attr-defined]
        except t.allowed:  # type: ignore[attr-defined]
            return
        # Assert
        assert bad == 0, f"{t.name}: out-of-range value from {data.hex()}"  # type: ignore

    for seed in seeds:
        assert t.run(seed) == 0  # type: ignore[attr-defined]
    check()


# -------------------------------------------------------------------- reproduced cases


def test_that_the_emulated_servo_answers_a_249_byte_read_with_the_range_bit_and_lives() -> None:
    # Fixture: the servo thread on a real pty, a raw client on the slave
    servo = EmulatedMX28(BenchVehicle(), model_baud=False).start()
    fd = os.open(servo.path, os.O_RDWR | os.O_NOCTTY)
    try:
        def ask(wire: bytes) -> p1.Packet:
            os.write(fd, wire)
            parser = p1.Parser()
            for _ in range(200):
                assert select.select([fd], [], [], 5.0)[0], "the servo stopped answering"
                packets = parser.feed(os.read(fd, 512))
                if packets:
                    return packets[0]
            raise AssertionError("no status packet")

        # Test
        long_read = ask(p1.encode_instruction(1, Instruction.READ, bytes((0, 249))))
        ping = ask(p1.encode_instruction(1, Instruction.PING))
        # Assert
        assert long_read == p1.Packet(1, int(ErrorBit.RANGE), b"")
        assert ping == p1.Packet(1, 0, b"")
        assert servo.input_stats().rejected == 1 and servo.input_stats().input_errors == 0
    finally:
        os.close(fd)
        servo.close()


@pytest.mark.parametrize(("period_us", "step_s"), [(1 << 30, 1.0), (1, 0.0005)])
def test_that_a_lockstep_stream_period_outside_the_board_range_is_clamped(
        period_us: int, step_s: float) -> None:
    # Fixture
    emu = EmulatedFlightCtrl(BenchVehicle(),
                             config=FlightCtrlEmulatorConfig(clock="lockstep"))
    drain = FT._PtyDrain(emu.path)
    try:
        emu.feed(tk3.encode_frame(mkm.SetStreamPeriod(mkm.Stream.IMU, period_us).encode()))
        t0 = emu.sim_time_s()
        # Test: one spin-rate frame is one IMU period of physics
        emu.feed(tk3.encode_frame(mkm.SpinRates((32767,) * 6).encode()))
        drain.drain()
        # Assert
        assert emu.sim_time_s() - t0 == pytest.approx(step_s, abs=1e-9)
        assert emu.stream_periods_us()["I"] == round(step_s * 1e6)
        assert emu.stats().periods_clamped == 1
    finally:
        drain.close()
        emu.stop()


def test_that_the_motor_stream_is_held_to_what_the_line_can_carry() -> None:
    emu = EmulatedFlightCtrl(BenchVehicle(), config=FlightCtrlEmulatorConfig(clock="lockstep"))
    try:
        for stream in (mkm.Stream.MOTOR, mkm.Stream.BATTERY):
            emu.feed(tk3.encode_frame(mkm.SetStreamPeriod(stream, 1).encode()))
        # six 11-byte M frames per period: 500 Hz is 330 kbit/s of the 500 kbit/s line
        assert emu.stream_periods_us() == {"M": mkm.MIN_MOTOR_PERIOD_US,
                                           "B": mkm.MIN_STREAM_PERIOD_US}
    finally:
        emu.stop()


def test_that_the_emulated_bl_ctrl_holds_a_too_fast_command_at_its_top_speed() -> None:
    emu = EmulatedFlightCtrl(BenchVehicle(), config=FlightCtrlEmulatorConfig(clock="lockstep"))
    try:
        emu.feed(tk3.encode_frame(mkm.StartMotors().encode()))
        emu.feed(tk3.encode_frame(mkm.SpinRates((1, -1, 5000, 5000, 5000, 5000)).encode()))
        assert emu.stats().spin_rates_clamped == 2
        emu.feed(tk3.encode_frame(b"w\x00"))  # odd payload: malformed, counted
        assert emu.stats().dropped_inputs == 1
    finally:
        emu.stop()


def test_that_a_motor_frame_beyond_the_bl_ctrl_range_is_dropped_and_counted() -> None:
    # Fixture
    fc = FlightCtrl(LoopTransport("loop://test"), FlightCtrlConfig(), clock=lambda: 0)
    ok = mkm.MotorMessage(1, 1, False, True, False, 5000, 400, 1.5)        # 100 Hz, 1.5 A
    fast = mkm.MotorMessage(2, 1, False, True, False, 1, 400, 1.5)         # 500 kHz
    hot = mkm.MotorMessage(3, 2, False, True, False, 5000, 400, 65.0)      # 65 A
    # Test
    for msg in (ok, fast, hot):
        fc.feed(tk3.encode_frame(msg.encode()))
    # Assert
    motors = fc.motors().motors
    assert motors[0] is not None and motors[0].state is MotorState.SPINNING
    assert motors[0].speed_hz == pytest.approx(100.0)
    assert motors[1] is None
    assert fc.link_stats().implausible == 2
    fc.close()


def _natnet_client(limits: PoseLimits | None = None) -> tuple[NatNetClient, tuple[str, int]]:
    cfg = NatNetConfig(body="fasthex", limits=limits or PoseLimits())
    server = (cfg.server_ip, cfg.command_port)
    client = NatNetClient(cfg, clock=lambda: 10**12)
    client.feed_datagram(natnet.encode_server_info(FT._server_info((4, 1))), server)
    client.feed_datagram(natnet.encode_modeldef(FT._models(), (4, 1)), server)
    return client, server


def _frame(pos: tuple[float, float, float], latency_ticks: int = 40_000,
           q: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0), n: int = 1) -> bytes:
    rb = natnet.RigidBodyData(1, pos, q, 0.0005, True)
    frame = natnet.FrameOfData(n, (rb,), camera_mid_exposure_ticks=1_000_000,
                               transmit_ticks=1_000_000 + latency_ticks)
    return natnet.encode_frame(frame, (4, 1))


def test_that_natnet_poses_and_latencies_no_mocap_can_give_are_dropped_and_counted() -> None:
    # Fixture: 10 MHz hi-res clock, so 40 000 ticks = 4 ms
    client, server = _natnet_client()
    # Test
    client.feed_datagram(_frame((0.5, 1.5, 0.0)), server)
    good = client.latest()
    for bad in (_frame((1000.0, 1.5, 0.0), n=2),                    # 1 km away
                _frame((0.5, 1.5, 0.0), latency_ticks=20_000_000, n=3),  # 2 s late
                _frame((0.5, 1.5, 0.0), latency_ticks=-1000, n=4),       # sent before exposed
                _frame((0.5, 1.5, 0.0), q=(0.0, 0.0, 0.0, 2.0), n=5),    # |q| = 2
                _frame((float("nan"), 1.5, 0.0), n=6)):
        client.feed_datagram(bad, server)
    # Assert
    assert good is not None and good.valid and good.latency_s == pytest.approx(0.004)
    assert client.latest() is good
    assert client.stats().implausible_samples == 5


def test_that_the_workspace_radius_is_a_config_value() -> None:
    client, server = _natnet_client(PoseLimits(max_range_m=2.0))
    client.feed_datagram(_frame((0.5, 2.5, 0.0)), server)  # 2.55 m from the origin
    assert client.latest() is None and client.stats().implausible_samples == 1
    assert parse_uri("natnet://127.0.0.1?range_m=25").limits.max_range_m == 25.0
    assert parse_uri("vrpn://Tracker0@127.0.0.1?range_m=30").limits.max_range_m == 30.0


def test_that_a_vrpn_report_1_km_away_is_dropped_and_counted() -> None:
    client = VrpnClient(VrpnConfig(), clock=lambda: 10**12)
    client.feed_stream(FT._vrpn_preamble())
    client.feed_stream(FT._vrpn_report((0.1, 0.2, 1.0), (0.0, 0.0, 0.0, 1.0)))
    good = client.latest()
    client.feed_stream(FT._vrpn_report((1000.0, 0.0, 1.0), (0.0, 0.0, 0.0, 1.0)))
    client.feed_stream(FT._vrpn_report((0.1, 0.2, 1.0), (0.0, 0.0, 0.5, 0.5)))
    assert good is not None and good.valid and client.latest() is good
    assert client.stats().implausible_samples == 2


def test_that_a_connection_request_naming_an_impossible_port_does_not_parse() -> None:
    for lob in (b"127.0.0.1 0\0", b"127.0.0.1 70000\0", b"not-an-ip 3883\0"):
        with pytest.raises(vrpn.VrpnDecodeError):
            vrpn.decode_lob(lob)

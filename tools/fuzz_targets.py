"""Fuzz targets: every byte parser, every emulator's input side, and the MAVLink input.

Each :class:`Target` takes one input (``bytes``), runs it through real project code in process
and returns how many *out-of-range values* came out of it: a decoded or delivered value that
the hardware cannot produce (checked against the physical ranges below), an invariant of the
codec broken (a deframed message longer than its limit, a status packet that does not parse
back), or an emulator left in a state the board does not support (a stream period outside
500 us .. 1 s, a rotor faster than a BL-Ctrl, one input taking longer than ``STALL_S``). Any
exception other than the target's documented ones (``allowed``) is an *escape*.

Used by ``tools/fuzz.py`` (atheris or a mutational fuzzer, 1e6 inputs per target) and by the
property tests of the suite (``tests/unit/test_fuzz_parsers.py``, a few hundred inputs).
"""

from __future__ import annotations

import contextlib
import math
import os
import select
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

from drivers.dynamixel import protocol1 as p1
from drivers.dynamixel.control_table import (
    MULTI_TURN_MAX_STEPS,
    MULTI_TURN_MIN_STEPS,
    MX28_P1,
    Access,
    Instruction,
    Mode,
    Reg,
)
from drivers.mavlink.link import MavlinkCodec
from drivers.mikrokopter import framing_stock, framing_tk3
from drivers.mikrokopter import messages as mkm
from drivers.mikrokopter.device import FlightCtrl, FlightCtrlConfig
from drivers.mocap import natnet, qtm, vrpn
from drivers.mocap.natnet_client import NatNetClient, NatNetConfig
from drivers.mocap.pose import PoseSample
from drivers.mocap.qtm_client import QtmClient, QtmConfig
from drivers.mocap.vrpn_client import VrpnClient, VrpnConfig
from drivers.transport import LoopTransport
from sim_backend.emulators.dynamixel_p1 import EmulatedMX28
from sim_backend.emulators.flightctrl import EmulatedFlightCtrl, FlightCtrlEmulatorConfig
from sim_backend.emulators.natnet import MAX_CLIENTS, NatNetEmulatorConfig, NatNetServer
from sim_backend.emulators.qtm import QtmServer
from sim_backend.emulators.vrpn import VrpnServer
from sim_backend.vehicle import BenchVehicle

STALL_S = 0.5
"""An emulator busy for longer than this per received frame counts as a stall (out of range).
Measured as the CPU time of the feeding thread: the emulator's own work, whatever else the
machine runs (wall time on a shared machine would measure the neighbours). Per frame, because
a lockstep ``w`` legitimately simulates one IMU period (up to 1 s: about 0.15 s of work with
every stream at its fastest) and one input may carry a dozen of them."""

Check = Callable[[bytes], int]


@dataclass
class Target:
    name: str
    what: str
    run: Check
    seeds: list[bytes]
    allowed: tuple[type[BaseException], ...] = ()
    close: Callable[[], None] = field(default=lambda: None)


def _split(data: bytes) -> tuple[bytes, bytes]:
    """Two chunks, cut where the first byte says: parsers must not care where reads end."""
    if not data:
        return b"", b""
    cut = data[0] % (len(data) + 1)
    return data[:cut], data[cut:]


def _finite(*values: float) -> bool:
    return all(math.isfinite(v) for v in values)


# ------------------------------------------------------------------------------- MikroKopter


def _tk3_seeds() -> list[bytes]:
    enc = framing_tk3.encode_frame
    host: list[mkm.HostMessage] = [
        mkm.Identify(), mkm.SetStreamPeriod(mkm.Stream.IMU, 2000),
        mkm.SetStreamPeriod(mkm.Stream.BATTERY, 1_000_000), mkm.StartMotors(1),
        mkm.StopMotors(), mkm.SpinRates.from_hz([100, -100, 80, -80, 60, -60]),
        mkm.Throttles.from_pct([50] * 6), mkm.Beep(440)]
    board: list[mkm.BoardMessage] = [
        mkm.ImuMessage(7, (0.0, 0.0, 9.81), (0.01, -0.02, 0.03)),
        mkm.MotorMessage(9, 2, False, True, False, 5000, 400, 1.5),
        mkm.BatteryMessage(1, 16.8), mkm.MagMessage(3, (2e-5, -1e-5, 4e-5)),
        mkm.ClockRateMessage(1, 20), mkm.IdentityMessage("mkfl1.8"),
        mkm.TextMessage(b"N", "hello")]
    seeds = [enc(m.encode()) for m in host] + [enc(m.encode()) for m in board]
    seeds.append(b"".join(enc(m.encode()) for m in board))
    seeds.append(enc(b"X^$!\\") + b"^ab^cd$^abc!def$")
    return seeds


def tk3_framing() -> Target:
    """tk3 deframer plus both message decoders (board -> host and host -> board)."""

    def run(data: bytes) -> int:
        parser = framing_tk3.Tk3Parser()
        a, b = _split(data)
        bad = 0
        for msg in parser.feed(a) + parser.feed(b):
            if not 1 <= len(msg) <= framing_tk3.MAX_MESSAGE_BYTES:
                bad += 1
            if framing_tk3.Tk3Parser().feed(framing_tk3.encode_frame(msg)) != [msg]:
                bad += 1
            with contextlib.suppress(mkm.MalformedMessageError):
                mkm.decode_board_message(msg)
            with contextlib.suppress(mkm.MalformedMessageError):
                mkm.decode_host_message(msg)
        return bad

    return Target("tk3-framing", "tk3 '^..$' deframer + I/M/B/C/T/? and i/m/b/c/g/x/w/q/~",
                  run, _tk3_seeds())


def flightctrl_driver() -> Target:
    """The FlightCtrl receive path (deframe, decode, range checks, IMU time base): what it
    delivers in its mailboxes must be physically possible."""
    cfg = FlightCtrlConfig()
    clock = [0]

    def now() -> int:
        return clock[0]

    fc = FlightCtrl(LoopTransport("loop://fuzz"), cfg, clock=now)

    def run(data: bytes) -> int:
        clock[0] += 2_000_000
        before = (fc.latest_imu(), fc.motors(), fc.battery(), fc.magnetometer())
        a, b = _split(data)
        fc.feed(a)
        fc.feed(b)
        bad = 0
        imu = fc.latest_imu()
        if imu is not None and imu is not before[0] and not (
                _finite(*imu.gyro_rad_s, *imu.accel_m_s2)
                and max(map(abs, imu.gyro_rad_s)) <= cfg.max_gyro_rad_s
                and max(map(abs, imu.accel_m_s2)) <= cfg.max_accel_m_s2):
            bad += 1
        for m in fc.motors().motors:
            if m is not None and not (_finite(m.speed_hz, m.current_a, m.throttle_pct)
                                      and 0.0 <= m.speed_hz <= cfg.max_motor_speed_hz
                                      and 0.0 <= m.current_a <= cfg.max_motor_current_a
                                      and abs(m.throttle_pct) <= 100.0 + 1e-9):
                bad += 1
        bat = fc.battery()
        if bat is not None and not 0.0 <= bat.voltage_v <= cfg.max_battery_v:
            bad += 1
        mag = fc.magnetometer()
        if mag is not None and not (_finite(*mag.field_t)
                                    and max(map(abs, mag.field_t)) <= 1e-3):
            bad += 1  # 10 gauss: beyond any magnetometer's range
        return bad

    return Target("tk3-driver", "FlightCtrl.feed: tk3 frames -> IMU/motor/battery/mag samples",
                  run, _tk3_seeds(), close=fc.close)


def _stock_seeds() -> list[bytes]:
    enc = framing_stock.encode_frame
    fc = framing_stock.Address.FLIGHT_CTRL
    return [
        enc(fc, b"v"), enc(framing_stock.Address.ANY, b"d", b"\x0a"), enc(fc, b"c", b"\x05"),
        enc(fc, b"t", bytes([20] * 6 + [0] * 10)), enc(fc, b"t", b"\x01\x02\x03\x04"),
        enc(fc, b"b", b"\x00\x00\x00\x64\x01\x01\x00"),
        enc(fc, b"V", bytes.fromhex("020c0ba5000000 19ff00".replace(" ", ""))),
        enc(fc, b"C", bytes.fromhex("f1ff1e000807000000000200 0000".replace(" ", ""))),
        enc(fc, b"D", bytes(2) + b"".join(i.to_bytes(2, "little") for i in range(32))),
        enc(fc, b"B", b"\x01"), enc(fc, b"T"),
    ]


def stock_framing() -> Target:
    """Stock ``#..\\r`` deframer, modified base64 and the stock message decoders."""

    def run(data: bytes) -> int:
        parser = framing_stock.StockParser()
        a, b = _split(data)
        bad = 0
        for frame in parser.feed(a) + parser.feed(b):
            if len(frame.data) % 3 or len(frame.data) > 3 * (
                    (framing_stock.MAX_FRAME_CHARS - 6) // 4) or len(frame.cmd) != 1:
                bad += 1
            with contextlib.suppress(mkm.MalformedMessageError):
                mkm.decode_stock_message(frame.cmd, frame.data)
        with contextlib.suppress(ValueError):
            decoded = framing_stock.decode64(data)
            if framing_stock.encode64(decoded) != data:
                bad += 1
        return bad

    return Target("stock-framing", "stock '#..\\r' deframer + base64 + v/V/d/D/c/C/b/B/t/T",
                  run, _stock_seeds())


class _PtyDrain:
    """Reads and discards what an emulator writes to its pty, in its own thread: a client that
    keeps up, as the ground station does (the emulator then never waits for buffer space)."""

    def __init__(self, path: str) -> None:
        self.fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        self.bytes = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="fuzz-pty-drain", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            with contextlib.suppress(OSError):
                if select.select([self.fd], [], [], 0.05)[0]:
                    self.bytes += len(os.read(self.fd, 65536))

    def drain(self) -> None:
        """Kept for callers that want to be sure; the thread does the work."""

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=1.0)
        with contextlib.suppress(OSError):
            os.close(self.fd)


def flightctrl_emulator(firmware: str = "tk3") -> Target:
    """The emulated Flight-Ctrl's input side in lockstep (each ``w`` steps the physics): it
    must survive every frame, keep its streams within 500 us .. 1 s, never spin a rotor faster
    than a BL-Ctrl and never stall."""
    emu = EmulatedFlightCtrl(BenchVehicle(), config=FlightCtrlEmulatorConfig(
        clock="lockstep", firmware="stock" if firmware == "stock" else "tk3"))
    drain = _PtyDrain(emu.path)

    def run(data: bytes) -> int:
        t0 = time.thread_time()
        frames0 = emu.stats().frames_received
        a, b = _split(data)
        emu.feed(a)
        emu.feed(b)
        drain.drain()
        frames = max(1, emu.stats().frames_received - frames0)
        bad = 0 if time.thread_time() - t0 <= STALL_S * frames else 1
        for key, period_us in emu.stream_periods_us().items():
            shortest = mkm.MIN_MOTOR_PERIOD_US if key == "M" else mkm.MIN_STREAM_PERIOD_US
            if key in "IMBC" and not shortest <= period_us <= mkm.MAX_STREAM_PERIOD_US:
                bad += 1
        speeds = emu.commanded_rotor_speeds_hz()
        if not all(math.isfinite(s) and 0.0 <= s <= mkm.MAX_SPIN_HZ for s in speeds):
            bad += 1
        return bad

    def close() -> None:
        drain.close()
        emu.stop()

    seeds = _stock_seeds() if firmware == "stock" else _tk3_seeds()
    if firmware != "stock":
        seeds.append(framing_tk3.encode_frame(mkm.SetStreamPeriod(mkm.Stream.IMU, 1 << 30)
                                              .encode()))
        seeds.append(framing_tk3.encode_frame(mkm.SetStreamPeriod(mkm.Stream.IMU, 1).encode()))
        seeds.append(framing_tk3.encode_frame(mkm.SpinRates((1,) * 6).encode()))
    return Target(f"flightctrl-emu-{firmware}",
                  f"EmulatedFlightCtrl.feed ({firmware} firmware, lockstep)", run, seeds,
                  close=close)


# ------------------------------------------------------------------------------- Dynamixel


def _dxl_seeds() -> list[bytes]:
    ins = p1.encode_instruction
    return [
        ins(1, Instruction.PING), ins(1, Instruction.READ, bytes((43, 1))),
        ins(1, Instruction.READ, bytes((36, 11))), ins(1, Instruction.READ, bytes((0, 249))),
        ins(1, Instruction.WRITE, bytes((6, 0xFF, 0x0F, 0xFF, 0x0F))),
        ins(1, Instruction.WRITE, bytes((30, 0x1C, 0x1F))),
        ins(1, Instruction.WRITE, bytes((24, 1))), ins(1, Instruction.REG_WRITE, bytes((30, 0, 8))),
        ins(0xFE, Instruction.ACTION), ins(1, Instruction.RESET),
        ins(0xFE, Instruction.SYNC_WRITE, bytes((30, 2, 1, 0x10, 0x00))),
        ins(0xFE, Instruction.BULK_READ, bytes((0, 2, 1, 30))),
        p1.encode_status(1, 0x24), p1.encode_status(1, 0, bytes((0x20,))),
    ]


def dxl_protocol1() -> Target:
    """Protocol 1.0 deframer in both directions (instruction and status packets)."""

    def run(data: bytes) -> int:
        parser = p1.Parser()
        a, b = _split(data)
        bad = 0
        for pkt in parser.feed(a) + parser.feed(b):
            if pkt.dxl_id == 0xFF or len(pkt.params) + 2 > p1.MAX_LENGTH:
                bad += 1
                continue
            if pkt.checksum_ok:
                # Re-encoding a good packet gives it back, as instruction and (7-bit) status.
                wire = p1.encode_instruction(pkt.dxl_id, pkt.code, pkt.params)
                if p1.Parser().feed(wire) != [pkt]:
                    bad += 1
                if pkt.code <= 0x7F and p1.Parser().feed(
                        p1.encode_status(pkt.dxl_id, pkt.code, pkt.params)) != [pkt]:
                    bad += 1
        return bad

    return Target("dxl-protocol1", "Protocol 1.0 deframer, instruction and status packets",
                  run, _dxl_seeds())


def dxl_emulator() -> Target:
    """The emulated MX-28T's input side: every reply is a valid status packet, a READ is
    answered with exactly the bytes asked (or the Range bit), the registers stay in range."""
    emu = EmulatedMX28(BenchVehicle(), step_on_wall_clock=False, model_baud=False)
    rw = [r for r in MX28_P1 if r.access is Access.RW and r.reg != Reg.GOAL_POSITION]
    mirror = p1.Parser()  # sees the same bytes as the servo's parser: the same packets

    def run(data: bytes) -> int:
        a, b = _split(data)
        asked = mirror.feed(data)
        replies = emu.feed(a) + emu.feed(b)
        bad = 0
        for wire in replies:
            pkts = p1.Parser().feed(wire)
            if len(pkts) != 1 or not pkts[0].checksum_ok or pkts[0].code > 0x7F:
                bad += 1
        if len(asked) == 1 and len(replies) == 1 and asked[0].checksum_ok \
                and asked[0].code == Instruction.READ and len(asked[0].params) == 2:
            length = asked[0].params[1]
            (status,) = p1.Parser().feed(replies[0])
            if len(status.params) != length and not (status.code & 0x08 and not status.params):
                bad += 1
        for r in rw:
            if not r.lo <= emu.register(r.reg) <= r.hi:
                bad += 1
        goal = emu.register(Reg.GOAL_POSITION)
        lo, hi = ((MULTI_TURN_MIN_STEPS, MULTI_TURN_MAX_STEPS) if emu.mode() is Mode.MULTI_TURN
                  else (-MULTI_TURN_MAX_STEPS, MULTI_TURN_MAX_STEPS))
        if not lo <= goal <= hi:
            bad += 1
        return bad

    return Target("dxl-emu", "EmulatedMX28.feed: instruction packets -> status packets", run,
                  _dxl_seeds(), close=emu.close)


# ------------------------------------------------------------------------------- NatNet

_VERSIONS: tuple[natnet.NatNetVersion | None, ...] = (None, *natnet.SUPPORTED_VERSIONS)


def _server_info(version: natnet.NatNetVersion) -> natnet.ServerInfo:
    return natnet.ServerInfo("Motive", (3, 1, 0, 0), (*version, 0, 0), 10_000_000, 1511,
                             False, natnet.DEFAULT_MULTICAST_GROUP)


def _models() -> natnet.ModelDefinitions:
    rb = natnet.RigidBodyDescription("fasthex", 1, -1, (0.0, 0.0, 0.0),
                                     ((0.1, 0.0, 0.0), (0.0, 0.1, 0.0)), (1, 2), ("m1", "m2"))
    return natnet.ModelDefinitions((rb,), (natnet.MarkerSetDescription("fasthex", ("m1", "m2")),))


def _natnet_frame(version: natnet.NatNetVersion, n: int = 7) -> bytes:
    rb = natnet.RigidBodyData(1, (0.5, 1.5, -0.2), (0.0, 0.0, 0.0, 1.0), 0.0005, True)
    frame = natnet.FrameOfData(n, (rb,), timestamp_s=1.25, camera_mid_exposure_ticks=1_000_000,
                               data_received_ticks=1_020_000, transmit_ticks=1_040_000)
    return natnet.encode_frame(frame, version)


def _natnet_seeds() -> list[bytes]:
    seeds = [natnet.encode_connect("ping"), natnet.encode_connect("empty"),
             natnet.encode_connect("sdk4"), natnet.encode_keepalive(),
             natnet.encode_request_modeldef(), natnet.encode_command("Bitstream,3.1"),
             natnet.encode_disconnect(), natnet.encode_response(0),
             natnet.encode_unrecognized()]
    for v in natnet.SUPPORTED_VERSIONS:
        seeds += [_natnet_frame(v), natnet.encode_modeldef(_models(), v)]
    seeds.append(natnet.encode_server_info(_server_info((4, 1))))
    return seeds


def natnet_codec() -> Target:
    """NatNet server -> client decoding at every bitstream version, and client requests."""

    def run(data: bytes) -> int:
        bad = 0
        for v in _VERSIONS:
            with contextlib.suppress(natnet.NatNetDecodeError):
                msg = natnet.decode_message(data, v)
                if isinstance(msg, natnet.FrameOfData) and not all(
                        isinstance(rb.body_id, int) for rb in msg.rigid_bodies):
                    bad += 1
        with contextlib.suppress(natnet.NatNetDecodeError):
            natnet.decode_request(data)
        return bad

    return Target("natnet-codec", "NatNet decode_message (3.0-4.1, before SERVERINFO) and "
                  "decode_request", run, _natnet_seeds())


def _pose_bad(s: PoseSample | None, max_range_m: float, max_latency_s: float) -> int:
    if s is None or not s.valid:
        return 0
    q_norm = math.sqrt(sum(c * c for c in s.q_wb))
    ok = (_finite(*s.pos_w_m, *s.q_wb)
          and math.sqrt(sum(c * c for c in s.pos_w_m)) <= max_range_m
          and abs(q_norm - 1.0) <= 1e-6
          and 0.0 <= s.latency_s <= max_latency_s and s.t_ns <= s.rx_t_ns)
    return 0 if ok else 1


def natnet_driver() -> Target:
    """NatNetClient's receive path after a 4.1 handshake: every delivered pose is finite,
    inside the 100 m workspace, a unit quaternion, with a latency in 0..1 s."""
    cfg = NatNetConfig(body="fasthex")
    server = (cfg.server_ip, cfg.command_port)
    clock = [10**12]
    client = NatNetClient(cfg, clock=lambda: clock[0])
    client.feed_datagram(natnet.encode_server_info(_server_info((4, 1))), server)
    client.feed_datagram(natnet.encode_modeldef(_models(), (4, 1)), server)

    def run(data: bytes) -> int:
        clock[0] += 10_000_000
        client.feed_datagram(data, server)
        return _pose_bad(client.latest(), cfg.limits.max_range_m,
                         cfg.limits.max_latency_s + cfg.network_delay_s)

    seeds = [_natnet_frame((4, 1), n) for n in (1, 2, 1000)] + _natnet_seeds()
    return Target("natnet-driver", "NatNetClient.feed_datagram -> PoseSample", run, seeds)


def natnet_emulator() -> Target:
    """The emulated Motive's command port (in process, replies dropped)."""
    server = NatNetServer(BenchVehicle(), NatNetEmulatorConfig())

    def run(data: bytes) -> int:
        server.handle_datagram(data, ("127.0.0.1", 40_000 + (data[0] if data else 0)))
        bad = 0 if len(server.unicast_clients) <= MAX_CLIENTS else 1
        return bad + (0 if server.version in natnet.SUPPORTED_VERSIONS else 1)

    return Target("natnet-emu", "NatNetServer.handle_datagram (command port)", run,
                  _natnet_seeds())


# ------------------------------------------------------------------------------- VRPN

_TRACKER_ID = 0
_POS_QUAT_ID = 0


def _vrpn_preamble() -> bytes:
    return (vrpn.encode_cookie()
            + vrpn.encode_description(vrpn.SystemType.SENDER_DESCRIPTION, _TRACKER_ID,
                                      "Tracker0")
            + vrpn.encode_description(vrpn.SystemType.TYPE_DESCRIPTION, _POS_QUAT_ID,
                                      vrpn.POS_QUAT_TYPE))


def _vrpn_report(pos: tuple[float, float, float], q: tuple[float, float, float, float]) -> bytes:
    return vrpn.encode_message(_TRACKER_ID, _POS_QUAT_ID,
                               vrpn.encode_pos_quat(vrpn.TrackerPose(0, pos, q)), 12.5)


def _vrpn_seeds() -> list[bytes]:
    return [_vrpn_report((0.5, -0.2, 1.0), (0.0, 0.0, 0.0, 1.0)),
            _vrpn_report((1.0, 2.0, 3.0), (0.0, 0.0, 0.0, 0.0)),
            vrpn.encode_description(vrpn.SystemType.SENDER_DESCRIPTION, 3, "Tracker1"),
            vrpn.encode_message(1, -5, b"", 1.0), vrpn.encode_cookie() + b"\0" * 24,
            vrpn.encode_lob("127.0.0.1", 4000)]


def vrpn_codec() -> Target:
    """VRPN stream parser (cookie, framing), Pos_Quat, descriptions and connection requests."""

    def run(data: bytes) -> int:
        bad = 0
        parser = vrpn.VrpnStreamParser(expect_cookie=bool(data[:1] and data[0] & 1))
        a, b = _split(data)
        with contextlib.suppress(vrpn.VrpnDecodeError):
            for m in parser.feed(a) + parser.feed(b):
                if not vrpn.HEADER_SIZE <= m.length <= vrpn.MAX_MESSAGE_BYTES:
                    bad += 1
                with contextlib.suppress(vrpn.VrpnDecodeError):
                    vrpn.decode_pos_quat(m.payload)
                with contextlib.suppress(vrpn.VrpnDecodeError):
                    vrpn.decode_description(m.payload)
        with contextlib.suppress(vrpn.VrpnDecodeError):
            _, port = vrpn.decode_lob(data)
            if not 1 <= port <= 65535:
                bad += 1
        return bad

    return Target("vrpn-codec", "VrpnStreamParser + Pos_Quat/description/lob decoders", run,
                  _vrpn_seeds())


def vrpn_driver() -> Target:
    """VrpnClient's receive path on a fresh connection (cookie and descriptions first): every
    delivered pose is finite, inside the workspace, a unit quaternion."""
    cfg = VrpnConfig()
    preamble = _vrpn_preamble()
    clock = [10**12]

    def run(data: bytes) -> int:
        clock[0] += 10_000_000
        client = VrpnClient(cfg, clock=lambda: clock[0])
        client.feed_stream(preamble)
        a, b = _split(data)
        client.feed_stream(a)
        client.feed_stream(b)
        return _pose_bad(client.latest(), cfg.limits.max_range_m, cfg.limits.max_latency_s)

    return Target("vrpn-driver", "VrpnClient.feed_stream -> PoseSample", run, _vrpn_seeds())


def vrpn_emulator() -> Target:
    """The emulated VRPN server's inputs: UDP connection requests and a client's TCP stream
    (in process, on a socket pair; the reply side is drained)."""
    server = VrpnServer(BenchVehicle())
    ours, theirs = socket.socketpair()
    for s in (ours, theirs):
        s.setblocking(False)

    def run(data: bytes) -> int:
        # A source that no request can name: the server never calls anyone back while fuzzed.
        server.handle_lob(data, ("fuzz", 0))
        conn = server.connection_for(ours)
        a, b = _split(vrpn.encode_cookie() + data if data[:1] == b"\x00" else data)
        if server.handle_stream(conn, a):
            server.handle_stream(conn, b)
        with contextlib.suppress(BlockingIOError, OSError):
            while theirs.recv(65536):
                pass
        return 0

    def close() -> None:
        ours.close()
        theirs.close()

    ping = vrpn.encode_description(vrpn.SystemType.TYPE_DESCRIPTION, 0, vrpn.PING_TYPE) \
        + vrpn.encode_message(0, 0, b"", 1.0)
    seeds = [vrpn.encode_cookie(), ping, *_vrpn_seeds()]
    return Target("vrpn-emu", "VrpnServer.handle_lob + handle_stream", run, seeds,
                  close=close)


# ------------------------------------------------------------------------------- QTM RT

_QTM_YAW_90 = (0.0, 1.0, 0.0, -1.0, 0.0, 0.0, 0.0, 0.0, 1.0)


def _qtm_frame(kind: qtm.ComponentType, matrix: bool, n: int = 7) -> bytes:
    body = qtm.SixDofBody((500.0, -200.0, 1000.0), _QTM_YAW_90 if matrix else None,
                          None if matrix else (0.0, 0.0, 90.0), 0.4)
    return qtm.encode_data_frame(qtm.DataFrame(
        1_000_000 + n, n, (qtm.SixDofComponent(kind, 0, 0, (body, body)),)))


def _qtm_seeds() -> list[bytes]:
    return [_qtm_frame(qtm.ComponentType.C6D, True), _qtm_frame(qtm.ComponentType.C6D_EULER_RES,
                                                                False),
            qtm.encode_command(qtm.WELCOME), qtm.encode_event(qtm.Event.CAPTURE_STARTED),
            qtm.encode_xml(qtm.encode_6d_parameters(["fasthex", "pad"])),
            qtm.encode_command("StreamFrames AllFrames UDP:6734 3DNoLabels 6DEuler"),
            qtm.encode_command("GetParameters 6D"), qtm.encode_command("Version 1.19"),
            qtm.encode_command("GetCurrentFrame 6DRes")]


def qtm_codec() -> Target:
    """QTM stream parser (framing), data frames, events, parameters XML, StreamFrames."""

    def run(data: bytes) -> int:
        bad = 0
        parser = qtm.QtmStreamParser()
        a, b = _split(data)
        with contextlib.suppress(qtm.QtmDecodeError):
            for p in parser.feed(a) + parser.feed(b):
                if len(p.body) + qtm.HEADER_SIZE > qtm.MAX_PACKET_BYTES:
                    bad += 1
                with contextlib.suppress(qtm.QtmDecodeError):
                    frame = qtm.decode_data(p.body)
                    # a body takes at least 24 bytes (position and Euler angles)
                    bad += sum(1 for c in frame.components if len(c.bodies) * 24 > len(p.body))
                with contextlib.suppress(qtm.QtmDecodeError):
                    qtm.decode_event(p.body)
                with contextlib.suppress(qtm.QtmDecodeError):
                    qtm.decode_6d_body_names(qtm.decode_text(p.body))
        with contextlib.suppress(qtm.QtmDecodeError):
            _, _, port, _ = qtm.parse_stream_command(data.decode("latin-1"))
            if port is not None and not 1 <= port <= 65535:
                bad += 1
        return bad

    return Target("qtm-codec", "QtmStreamParser + data/event/parameters/StreamFrames decoders",
                  run, _qtm_seeds())


def qtm_driver() -> Target:
    """QtmClient's receive path after GetParameters (body "fasthex", index 0): every delivered
    pose is finite, inside the workspace, a unit quaternion, with a latency in 0..1 s."""
    cfg = QtmConfig(body="fasthex")
    clock = [10**12]
    client = QtmClient(cfg, clock=lambda: clock[0])
    client._on_parameters(qtm.encode_6d_parameters(["fasthex", "pad"]))
    client._server_ip = "127.0.0.1"

    def run(data: bytes) -> int:
        clock[0] += 10_000_000
        a, b = _split(data)
        if not client.feed_stream(a) or not client.feed_stream(b):
            client.feed_stream(b"")  # the parser started over, as after a reconnection
        client.feed_datagram(data, ("127.0.0.1", qtm.DEFAULT_PORT))
        return _pose_bad(client.latest(), cfg.limits.max_range_m, cfg.limits.max_latency_s)

    return Target("qtm-driver", "QtmClient.feed_stream/feed_datagram -> PoseSample", run,
                  _qtm_seeds())


def qtm_emulator() -> Target:
    """The emulated QTM server's command side on a client's TCP stream (in process, on a
    socket pair; the reply side is drained; UDP frames are never sent: not started)."""
    server = QtmServer(BenchVehicle())
    ours, theirs = socket.socketpair()
    for s in (ours, theirs):
        s.setblocking(False)

    def run(data: bytes) -> int:
        conn = server.connection_for(ours)
        a, b = _split(data)
        if server.handle_stream(conn, a):
            server.handle_stream(conn, b)
        with contextlib.suppress(BlockingIOError, OSError):
            while theirs.recv(65536):
                pass
        stream = conn.stream
        return 0 if stream is None or stream.divisor >= 1 else 1

    def close() -> None:
        ours.close()
        theirs.close()

    return Target("qtm-emu", "QtmServer.handle_stream (commands)", run, _qtm_seeds(),
                  close=close)


# ------------------------------------------------------------------------------- MAVLink

_KEY = bytes(range(32))


def _mavlink_seeds() -> list[bytes]:
    seeds = []
    for key in (None, _KEY):
        c = MavlinkCodec(1, 1, key=key)
        seeds += [
            c.encode(c.tx.heartbeat_encode(2, 12, 0, 0, 4, 3)),
            c.encode(c.tx.vision_position_estimate_encode(1_000_000, 1.0, -2.0, -1.5, 0.1,
                                                          -0.1, 0.5)),
            c.encode(c.tx.command_long_encode(1, 1, 21, 0, 0, 0, 0, 0, 0, 0, 0)),
            c.encode(c.tx.att_pos_mocap_encode(1_000_000, [1.0, 0.0, 0.0, 0.0], 1.0, 2.0, -1.0)),
        ]
    return seeds


def mavlink_input() -> Target:
    """MAVLink input through the link codec (drivers.mavlink.link.MavlinkCodec), unsigned and
    with signing on. Value ranges are the bridge's business: only escapes are counted."""
    plain = MavlinkCodec(255, 190)
    signed = MavlinkCodec(255, 190, key=_KEY)

    def run(data: bytes) -> int:
        a, b = _split(data)
        bad = 0
        for codec in (plain, signed):
            for msg in codec.decode(a) + codec.decode(b):
                if msg.get_type() == "BAD_DATA":
                    bad += 1
        return bad

    return Target("mavlink-decode", "MavlinkCodec.decode (unsigned and signed)", run,
                  _mavlink_seeds())


TARGETS: dict[str, Callable[[], Target]] = {
    "tk3-framing": tk3_framing,
    "tk3-driver": flightctrl_driver,
    "stock-framing": stock_framing,
    "flightctrl-emu-tk3": lambda: flightctrl_emulator("tk3"),
    "flightctrl-emu-stock": lambda: flightctrl_emulator("stock"),
    "dxl-protocol1": dxl_protocol1,
    "dxl-emu": dxl_emulator,
    "natnet-codec": natnet_codec,
    "natnet-driver": natnet_driver,
    "natnet-emu": natnet_emulator,
    "vrpn-codec": vrpn_codec,
    "vrpn-driver": vrpn_driver,
    "vrpn-emu": vrpn_emulator,
    "qtm-codec": qtm_codec,
    "qtm-driver": qtm_driver,
    "qtm-emu": qtm_emulator,
    "mavlink-decode": mavlink_input,
}
"""Every target by name, built on demand (some own a pty or sockets: ``close()`` them)."""

"""Emulated OptiTrack NatNet server (Motive) streaming an emulated vehicle's true pose.

Speaks the real NatNet bitstream (3.0, 3.1, 4.0 or 4.1) over UDP, encoded with
:mod:`drivers.mocap.natnet`, so any NatNet client can read it (``protocol-mocap-mavlink.md``
§2): commands on ``command_port`` (CONNECT -> extended SERVERINFO, REQUEST_MODELDEF ->
MODELDEF, KEEPALIVE, REQUEST ``Bitstream,x.y`` (switches the stream and SERVERINFO's version,
unless ``honour_bitstream`` is False) and other text commands -> RESPONSE 0, DISCONNECT);
frames to every client that sent CONNECT/KEEPALIVE in the last ``client_timeout_s``
(unicast) or to ``multicast_group:data_port`` on ``multicast_interface`` (multicast; loopback
by default, TTL 0: nothing leaves the machine).

What a real system does to the stream is configurable: rate 10-1000 Hz, Gaussian position and
attitude noise, a system latency (frames are sent ``latency_s`` after their mid-exposure and
the hi-res stamps say so), marker-occlusion dropouts (tracking-valid cleared, the stale pose
left in the packet, as a careless client would misuse it), frame-number jumps and packet loss.

Two ways to run it:

- realtime: :meth:`NatNetServer.start` with ``realtime=True`` paces captures on the wall
  clock in its own thread;
- lockstep: the emulated backend calls :meth:`NatNetServer.publish_due` with the simulated time
  after advancing the vehicle; exactly the frames due by then are captured and sent. With
  ``defer=True`` a frame sent after a latency is captured later, at
  :meth:`NatNetServer.capture_deferred` (the backend calls it once the board's reply is out,
  before the vehicle moves on): the same packet, off the lockstep round trip.

Every vehicle call is made under the shared ``lock`` (do not hold it when calling
``publish_due``). The command port is always served by its own thread, which survives any
datagram: one that does not decode is answered UNRECOGNIZED_REQUEST, a CONNECT beyond
``MAX_CLIENTS`` unicast clients is ignored, a handler failure is logged; all are counted
(:attr:`EmulatorCounters.dropped_inputs`). :meth:`NatNetServer.handle_datagram` runs the
command side in process (fuzzing).
"""

from __future__ import annotations

import contextlib
import logging
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from config.schema import ConfigValueError, spec
from drivers.mocap import natnet
from drivers.mocap.frames import (
    IDENTITY_Q,
    FrameConfig,
    FrameTransform,
    Quat,
    Vec3,
    quat_from_axis_angle,
    quat_mul,
    quat_rotate,
)
from sim_backend.emulators.schedule import CaptureSchedule
from sim_backend.vehicle import EmulatedVehicle

log = logging.getLogger(__name__)

#: Marker positions of the emulated rigid bodies in their own frame (m): four markers on
#: the arms, asymmetric as a real marker tree must be.
DEFAULT_MARKERS_B_M: tuple[Vec3, ...] = ((0.25, 0.0, 0.03), (-0.12, 0.2, 0.03),
                                         (-0.12, -0.2, 0.05), (0.0, 0.05, 0.12))


@dataclass(frozen=True)
class StaticBody:
    """An extra rigid body at a fixed world pose (a landing pad, another object)."""

    name: str
    body_id: int
    pos_w_m: Vec3 = (0.0, 0.0, 0.0)
    q_wb: Quat = IDENTITY_Q


@dataclass(frozen=True)
class NatNetEmulatorConfig:
    """The emulated Motive server. Loadable from YAML (``config.schema``)."""

    version: str = "4.1"
    host: str = "127.0.0.1"
    command_port: int = spec(natnet.DEFAULT_COMMAND_PORT, ge=0, le=65535,
                             doc="0 picks a free port")
    data_port: int = spec(natnet.DEFAULT_DATA_PORT, ge=1, le=65535)
    mode: Literal["unicast", "multicast"] = "unicast"
    multicast_group: str = natnet.DEFAULT_MULTICAST_GROUP
    multicast_interface: str = "127.0.0.1"
    # Motive's cameras run from 30 Hz (Flex 13) to 1000 Hz (Prime^x 13); the disturbance
    # presets' range, so that a preset flies in fly at the rate it says
    rate_hz: float = spec(100.0, ge=10.0, le=1000.0)
    body_name: str = "fasthex"
    body_id: int = spec(1, ge=0)
    static_bodies: tuple[StaticBody, ...] = ()
    pos_noise_m: float = spec(0.0, ge=0.0, doc="standard deviation per axis")
    rot_noise_rad: float = spec(0.0, ge=0.0, doc="standard deviation per axis")
    latency_s: float = spec(0.0, ge=0.0, le=0.5, doc="mid-exposure -> transmit")
    occlusion_probability: float = spec(0.0, ge=0.0, le=1.0, doc="per frame, starts a dropout")
    occlusion_frames: int = spec(10, ge=1)
    frame_jump_probability: float = spec(0.0, ge=0.0, le=1.0, doc="per frame")
    frame_jump_frames: int = spec(10_000, ge=2)
    loss_probability: float = spec(0.0, ge=0.0, le=1.0, doc="per frame, packet not sent")
    high_res_clock_hz: int = spec(10_000_000, ge=1)
    server_clock_offset_s: float = spec(0.0, ge=0.0, le=1e6,
                                        doc="the server's clock minus the emulator's")
    server_clock_drift_ppm: float = spec(0.0, ge=-50_000.0, le=50_000.0,
                                         doc="rate error of the server's clock")
    client_timeout_s: float = spec(10.0, gt=0.0)
    honour_bitstream: bool = spec(True, doc="False: answer Bitstream,x.y with success but keep "
                                  "streaming (and announcing) the configured version")
    app_name: str = "Motive"
    seed: int = 0
    frames: FrameConfig = field(default_factory=FrameConfig)

    def __post_init__(self) -> None:
        try:
            natnet.parse_version(self.version)
        except ValueError as exc:
            raise ConfigValueError("version", str(exc)) from exc
        if not 10.0 <= self.rate_hz <= 1000.0:
            raise ConfigValueError("rate_hz", "must be in [10, 1000] Hz")
        if self.mode not in ("unicast", "multicast"):
            raise ConfigValueError("mode", "must be 'unicast' or 'multicast'")
        ids = [self.body_id] + [b.body_id for b in self.static_bodies]
        if len(set(ids)) != len(ids):
            raise ConfigValueError("static_bodies", "rigid-body ids must be unique")


@dataclass
class EmulatorCounters:
    frames_captured: int = 0
    frames_sent: int = 0  # datagrams (per client in unicast)
    frames_lost: int = 0  # captured but deliberately not sent
    occluded_frames: int = 0
    frame_jumps: int = 0
    malformed_requests: int = 0
    refused_clients: int = 0  # CONNECT/KEEPALIVE beyond MAX_CLIENTS
    input_errors: int = 0  # datagrams whose handling failed unexpectedly (logged)

    @property
    def dropped_inputs(self) -> int:
        return self.malformed_requests + self.refused_clients + self.input_errors


MAX_CLIENTS = 64
"""Unicast clients served at once; more would let a flood of CONNECTs grow without bound."""


class NatNetServer:
    """Emulated Motive: one vehicle rigid body plus optional static bodies."""

    def __init__(self, vehicle: EmulatedVehicle, config: NatNetEmulatorConfig | None = None,
                 lock: threading.Lock | None = None,
                 wall_clock: Callable[[], float] = time.monotonic) -> None:
        self.config = cfg = config or NatNetEmulatorConfig()
        self._vehicle = vehicle
        self._lock = lock or threading.Lock()
        self._wall = wall_clock
        self._version = natnet.parse_version(cfg.version)
        self._transform = FrameTransform(cfg.frames)
        self._rng = np.random.default_rng(cfg.seed)
        self.counters = EmulatorCounters()
        self._clients: dict[tuple[str, int], float] = {}
        self._clients_lock = threading.Lock()
        self._cmd: socket.socket | None = None
        self._mcast: socket.socket | None = None
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._stream_lock = threading.Lock()
        self._schedule: CaptureSchedule[bytes] = CaptureSchedule(1.0 / cfg.rate_hz)
        self._frame_number = 0
        self._occluded_left = 0
        self._stale: tuple[Vec3, tuple[float, float, float, float]] | None = None
        self._models_changed = False
        self._t0_wall = 0.0

    # ------------------------------------------------------------------ lifecycle

    def __enter__(self) -> NatNetServer:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def command_port(self) -> int:
        """The bound command port (the real one when configured as 0)."""
        assert self._cmd is not None, "server not started"
        return int(self._cmd.getsockname()[1])

    @property
    def version(self) -> natnet.NatNetVersion:
        return self._version

    @property
    def unicast_clients(self) -> list[tuple[str, int]]:
        """Addresses frames are sent to in unicast (CONNECT/KEEPALIVE seen recently)."""
        with self._clients_lock:
            return list(self._clients)

    def start(self, realtime: bool = True) -> None:
        """Bind the command port and serve it; with ``realtime``, also stream on the wall clock."""
        cfg = self.config
        self._cmd = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._cmd.bind((cfg.host, cfg.command_port))
        self._cmd.settimeout(0.1)
        if cfg.mode == "multicast":
            m = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            m.bind((cfg.multicast_interface, 0))
            m.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF,
                         socket.inet_aton(cfg.multicast_interface))
            ttl = 0 if cfg.multicast_interface.startswith("127.") else 1
            m.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, ttl)
            m.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_LOOP, 1)
            self._mcast = m
        self._stop.clear()
        self._threads = [threading.Thread(target=self._serve_commands, name="natnet-emu-cmd",
                                          daemon=True)]
        if realtime:
            self._t0_wall = self._wall()
            self._threads.append(threading.Thread(target=self._stream_realtime,
                                                  name="natnet-emu-stream", daemon=True))
        for t in self._threads:
            t.start()

    def close(self) -> None:
        self._stop.set()
        for t in self._threads:
            t.join(timeout=5.0)
        self._threads = []
        for s in (self._cmd, self._mcast):
            if s is not None:
                s.close()
        self._cmd = self._mcast = None

    # ------------------------------------------------------------------ descriptions

    def server_info(self) -> natnet.ServerInfo:
        cfg = self.config
        return natnet.ServerInfo(cfg.app_name, (3, 1, 0, 0), (*self._version, 0, 0),
                                 cfg.high_res_clock_hz, cfg.data_port,
                                 cfg.mode == "multicast", cfg.multicast_group)

    def model_definitions(self) -> natnet.ModelDefinitions:
        cfg = self.config
        bodies = [(cfg.body_name, cfg.body_id)] + [(b.name, b.body_id)
                                                   for b in cfg.static_bodies]
        rbs = tuple(natnet.RigidBodyDescription(
            name, bid, -1, (0.0, 0.0, 0.0), DEFAULT_MARKERS_B_M,
            tuple(range(1, len(DEFAULT_MARKERS_B_M) + 1)),
            tuple(f"{name}_{i + 1}" for i in range(len(DEFAULT_MARKERS_B_M))))
            for name, bid in bodies)
        msets = tuple(natnet.MarkerSetDescription(rb.name, rb.marker_names) for rb in rbs)
        return natnet.ModelDefinitions(rbs, msets)

    # ------------------------------------------------------------------ commands

    def _serve_commands(self) -> None:
        assert self._cmd is not None
        while not self._stop.is_set():
            try:
                data, addr = self._cmd.recvfrom(65536)
            except TimeoutError:
                continue
            except OSError:
                return
            self.handle_datagram(data, addr)

    def handle_datagram(self, data: bytes, addr: tuple[str, int]) -> None:
        """Serve one command datagram from ``addr``. Never raises for any content."""
        try:
            req = natnet.decode_request(data)
        except natnet.NatNetDecodeError:
            self.counters.malformed_requests += 1
            self._reply(natnet.encode_unrecognized(), addr)
            return
        try:
            self._on_request(req, addr)
        except Exception:
            self.counters.input_errors += 1
            log.exception("natnet emulator: request %r from %s failed", req, addr)

    def _on_request(self, req: natnet.ClientRequest, addr: tuple[str, int]) -> None:
        kind = req.message_id
        if kind in (natnet.MessageId.CONNECT, natnet.MessageId.KEEPALIVE):
            with self._clients_lock:
                if addr not in self._clients and len(self._clients) >= MAX_CLIENTS:
                    self.counters.refused_clients += 1
                    return
                self._clients[addr] = self._wall()
            if kind == natnet.MessageId.CONNECT:
                self._reply(natnet.encode_server_info(self.server_info()), addr)
        elif kind == natnet.MessageId.DISCONNECT:
            with self._clients_lock:
                self._clients.pop(addr, None)
        elif kind == natnet.MessageId.REQUEST_MODELDEF:
            self._reply(natnet.encode_modeldef(self.model_definitions(), self._version), addr)
        elif kind == natnet.MessageId.REQUEST:
            self._reply(natnet.encode_response(self._command(req.text)), addr)
        else:
            self._reply(natnet.encode_unrecognized(), addr)

    def _command(self, text: str) -> int:
        if text.startswith("Bitstream,"):
            if self.config.mode != "unicast":
                return -1
            try:
                version = natnet.parse_version(text.split(",", 1)[1])
            except ValueError:
                return -1
            if self.config.honour_bitstream:
                with self._stream_lock:
                    self._version = version
            return 0
        return 0  # TimelinePlay, TimelineStop, ...: accepted, nothing to do

    def _reply(self, data: bytes, addr: tuple[str, int]) -> None:
        if self._cmd is not None:
            with contextlib.suppress(OSError):
                self._cmd.sendto(data, addr)

    # ------------------------------------------------------------------ streaming

    def occlude(self, frames: int) -> None:
        """Occlude the vehicle's markers for the next ``frames`` frames (tracking invalid, as
        Motive reports a rigid body it lost)."""
        with self._stream_lock:
            self._occluded_left = max(self._occluded_left, int(frames))

    def inject_frame_jump(self, frames: int) -> None:
        """Make the next frame number jump by ``frames`` (as after a Motive restart)."""
        with self._stream_lock:
            self._frame_number += frames - 1
            self.counters.frame_jumps += 1

    def announce_models_changed(self) -> None:
        """Set the "models changed" flag in the next frame."""
        self._models_changed = True

    def _noisy(self, pos: Vec3, q: Quat) -> tuple[Vec3, Quat]:
        cfg = self.config
        if cfg.pos_noise_m > 0.0:
            n = self._rng.normal(0.0, cfg.pos_noise_m, 3)
            pos = (pos[0] + float(n[0]), pos[1] + float(n[1]), pos[2] + float(n[2]))
        if cfg.rot_noise_rad > 0.0:
            r = self._rng.normal(0.0, cfg.rot_noise_rad, 3)
            angle = float(np.linalg.norm(r))
            q = quat_mul(q, quat_from_axis_angle((float(r[0]), float(r[1]), float(r[2])),
                                                 angle))
        return pos, q

    def _rigid_body(self, body_id: int, pos_w: Vec3, q_wb: Quat, valid: bool
                    ) -> natnet.RigidBodyData:
        p, q = self._transform.to_mocap(pos_w, q_wb)
        return natnet.RigidBodyData(body_id, p, q, 0.0004 if valid else 0.0, valid)

    def _capture(self, t_capture_s: float) -> bytes | None:
        """Build the frame captured at ``t_capture_s`` (server time base); None if lost."""
        cfg = self.config
        rng = self._rng
        with self._lock:
            pose = self._vehicle.true_pose()
        self._frame_number += 1
        if cfg.frame_jump_probability > 0.0 and rng.random() < cfg.frame_jump_probability:
            self._frame_number += cfg.frame_jump_frames - 1
            self.counters.frame_jumps += 1
        if self._occluded_left == 0 and cfg.occlusion_probability > 0.0 \
                and rng.random() < cfg.occlusion_probability:
            self._occluded_left = cfg.occlusion_frames
        occluded = self._occluded_left > 0
        if occluded:
            self._occluded_left -= 1
            self.counters.occluded_frames += 1
        pos_w, q_wb = self._noisy(pose.pos_w_m, pose.q_wb)
        if occluded and self._stale is not None:
            vehicle_rb = natnet.RigidBodyData(cfg.body_id, self._stale[0], self._stale[1],
                                              0.0, False)
        else:
            vehicle_rb = self._rigid_body(cfg.body_id, pos_w, q_wb, not occluded)
            self._stale = (vehicle_rb.pos, vehicle_rb.q_xyzw)
        rbs = [vehicle_rb] + [self._rigid_body(b.body_id, b.pos_w_m, b.q_wb, True)
                              for b in cfg.static_bodies]
        marker_sets = []
        labeled = []
        bodies = [(cfg.body_name, pos_w, q_wb, not occluded)] + \
            [(b.name, b.pos_w_m, b.q_wb, True) for b in cfg.static_bodies]
        for rb, (name, p_w, q, visible) in zip(rbs, bodies, strict=True):
            mk = []
            for i, m in enumerate(DEFAULT_MARKERS_B_M):
                r = quat_rotate(q, m)
                pm = self._transform.point_to_mocap((p_w[0] + r[0], p_w[1] + r[1], p_w[2] + r[2]))
                mk.append(pm)
                labeled.append(natnet.LabeledMarker((rb.body_id << 16) | (i + 1), pm, 0.014,
                                                    0x04 if visible else 0x01, 0.0002))
            marker_sets.append(natnet.MarkerSetData(name, tuple(mk)))
        freq = cfg.high_res_clock_hz
        # the stamps are on the server's own clock (offset and rate error configurable)
        rate = 1.0 + cfg.server_clock_drift_ppm * 1e-6
        t_mid = round((cfg.server_clock_offset_s + t_capture_s * rate) * freq)
        t_tx = round((cfg.server_clock_offset_s + (t_capture_s + cfg.latency_s) * rate) * freq)
        params = 0x02 if self._models_changed else 0
        self._models_changed = False
        frame = natnet.FrameOfData(
            self._frame_number, tuple(rbs), tuple(marker_sets), (), (), tuple(labeled),
            0, 0, t_capture_s, t_mid, t_mid + round(0.0005 * freq), t_tx,
            (int(t_capture_s), int((t_capture_s % 1.0) * 2**32) & 0xFFFFFFFF), params)
        self.counters.frames_captured += 1
        if cfg.loss_probability > 0.0 and rng.random() < cfg.loss_probability:
            self.counters.frames_lost += 1
            return None
        return natnet.encode_frame(frame, self._version)

    def _send_frame(self, packet: bytes) -> None:
        cfg = self.config
        if cfg.mode == "multicast":
            if self._mcast is not None:
                with contextlib.suppress(OSError):
                    self._mcast.sendto(packet, (cfg.multicast_group, cfg.data_port))
                    self.counters.frames_sent += 1
            return
        now = self._wall()
        with self._clients_lock:
            for addr, seen in list(self._clients.items()):
                if now - seen > cfg.client_timeout_s:
                    del self._clients[addr]
            targets = list(self._clients)
        for addr in targets:
            self._reply(packet, addr)
            self.counters.frames_sent += 1

    def publish_due(self, now_s: float, defer: bool = False) -> int:
        """Capture every frame due by ``now_s`` (server time, s) and send those whose
        transmit time (capture + latency) has come. Returns the number of frames captured.

        The first call starts the frame schedule at ``now_s``. In lockstep the pose of a frame
        due between two calls is the vehicle's at ``now_s``, and its mid-exposure stamp is
        ``now_s``: the stamp always matches the pose in the packet. ``defer``: a frame sent
        after a latency is captured at :meth:`capture_deferred` instead (lockstep, see
        :mod:`sim_backend.emulators.schedule`).
        """
        with self._stream_lock:
            captured, due = self._schedule.due(now_s, self.config.latency_s,
                                               lambda: self._capture(now_s), defer)
        for packet in due:
            self._send_frame(packet)
        return captured

    def capture_deferred(self) -> int:
        """Capture the frames ``publish_due(..., defer=True)`` left; returns how many."""
        with self._stream_lock:
            return self._schedule.capture_deferred()

    def next_event_s(self) -> float:
        """Server time of the next capture or transmission."""
        with self._stream_lock:
            return self._schedule.next_event_s()

    def _stream_realtime(self) -> None:
        while not self._stop.is_set():
            now = self._wall() - self._t0_wall
            try:
                self.publish_due(now)
            except Exception:  # keep the emulator alive; the failure is logged
                log.exception("natnet emulator: publishing failed")
            wait = self.next_event_s() - (self._wall() - self._t0_wall)
            if wait > 0.0:
                self._stop.wait(min(wait, 0.05))


def free_udp_port(host: str = "127.0.0.1") -> int:
    """A UDP port free right now on ``host`` (for multicast data ports in tests and tools)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


__all__ = ["NatNetEmulatorConfig", "NatNetServer", "StaticBody", "free_udp_port"]

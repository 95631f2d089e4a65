"""The MAVLink bridge: the ground station seen by a GCS (QGroundControl, MAVProxy) over UDP.

A ground-station part: it knows the flight phases and the operator vocabulary
(:mod:`groundstation.operator`) and maps them onto the wire layer of :mod:`drivers.mavlink`
(codec, link, signing, frames). The session wiring (keys, the loop's command queue, the stats
file) is :mod:`groundstation.gcs`.

Wire protocol: MAVLink2, ``common`` dialect (pymavlink 2.4.50), one UDP link chosen by URI
(:mod:`drivers.mavlink.link`: ``udpout:HOST:PORT`` or ``udpin:HOST:PORT``), system id 1 and
component id 1 (MAV_COMP_ID_AUTOPILOT1) by default, optionally signed
(:mod:`drivers.mavlink.signing`).

Telemetry out (rates in Hz from :class:`MavlinkConfig`, 0 disables; layout in
:mod:`groundstation.mavlink_messages`): HEARTBEAT, SYS_STATUS, EXTENDED_SYS_STATE (landed
state), ATTITUDE, ATTITUDE_QUATERNION, LOCAL_POSITION_NED, ODOMETRY, ACTUATOR_OUTPUT_STATUS,
and STATUSTEXT, once, for every event of the snapshots, every phase transition
(``ARMED -> TAKEOFF``; off with ``phase_events=False`` when the events already carry the
transitions, as a flight session's do) and every health flag that changes (``fault: mocap`` /
``ok: mocap``). Every phase change also goes out at once in a HEARTBEAT and an
EXTENDED_SYS_STATE of the snapshot that made it, each change in order, however briefly the
phase lasted. A GCS may change a rate with MAV_CMD_SET_MESSAGE_INTERVAL. At the end,
:meth:`MavlinkBridge.announce_final` repeats the final state (HEARTBEAT disarmed,
EXTENDED_SYS_STATE, one STATUSTEXT) for a while so that a GCS sees how the session ended.

Commands in (each answered by COMMAND_ACK with the sink's :class:`CommandResult`):

=====================================  ========================================================
COMMAND_LONG / COMMAND_INT             operator command
=====================================  ========================================================
COMPONENT_ARM_DISARM (400)             p1 = 1: Arm; p1 = 0: Disarm; p1 = 0 and p2 = 21196
                                       (force): EmergencyStop
NAV_TAKEOFF (22)                       Takeoff(alt_m = p7, height above the world origin)
NAV_LAND (21)                          Land
DO_FLIGHTTERMINATION (185)             p1 >= 0.5: EmergencyStop
USER_1 (31010)                         SetTilt(tilt_rad = radians(p1)), p1 in degrees
REQUEST_MESSAGE (512)                  p1 = message id: sent at once if it is one of ours,
                                       AUTOPILOT_VERSION included; else UNSUPPORTED
REQUEST_AUTOPILOT_CAPABILITIES (520)   AUTOPILOT_VERSION
SET_MESSAGE_INTERVAL (511)             p1 = message id, p2 = interval us (0 default, -1 off)
anything else (GET_HOME_POSITION ...)  UNSUPPORTED
=====================================  ========================================================

SET_POSITION_TARGET_LOCAL_NED (frame LOCAL_NED; position and optionally yaw) and
SET_ATTITUDE_TARGET (quaternion) become :class:`PoseSetpoint` (accepted only in MISSION; no ACK
exists for them, the result is counted and an accepted position target is echoed as
POSITION_TARGET_LOCAL_NED). PARAM_REQUEST_LIST / PARAM_REQUEST_READ / PARAM_SET serve the
:class:`ParamSpec` table (REAL32); a PARAM_SET outside the range or refused by the sink is
answered with the unchanged value. MISSION_REQUEST_LIST gets MISSION_COUNT 0, FTP requests get a
NAK (so MAVProxy falls back to PARAM_REQUEST_LIST), TIMESYNC requests are answered, GCS
HEARTBEATs are tracked for link-loss detection; everything else is ignored and counted by type.
Messages addressed to another system or component are ignored.

Security, secure by default:

* With a key (:func:`~drivers.mavlink.signing.load_signing_key`, never the session YAML)
  every outgoing frame is signed, and incoming frames are accepted only when signed with that
  key and fresh; unsigned, wrongly signed, replayed and stale frames are dropped before being
  looked at, and counted apart. ``allow_unsigned_ids`` lists the messages accepted *unsigned*
  (default: RADIO_STATUS 109 and RADIO 166, status reports from telemetry radios that cannot
  sign; neither can command anything). A badly signed frame is never accepted.
* Without a key, every command that changes the flight (arm, disarm, take-off, land,
  emergency stop, tilt, setpoints, PARAM_SET) is refused with MAV_RESULT_DENIED and counted
  (``refused_unsigned``), unless the owner passes ``allow_unsigned_commands=True``. Telemetry,
  parameter reads, message requests and rates still work.
* No frame raises out of the bridge: each handler is guarded (a failure is counted in
  ``handler_errors`` and answered FAILED when it was a command). Values outside the physical
  range are refused and counted (``refused_out_of_range``), never delivered: non-finite
  parameters, a take-off height outside (0, MAX_TAKEOFF_ALT_M], a tilt outside
  [0, ``max_tilt_rad``], setpoint positions farther than ``setpoint_range_m`` from the origin,
  quaternions that cannot be normalised, MoCap poses beyond
  :data:`~drivers.mavlink.mocap.MAX_POSE_RANGE_M` or with non-finite angles.

MoCap input: ATT_POS_MOCAP (q + NED position) and VISION_POSITION_ESTIMATE (NED position +
roll/pitch/yaw) are converted to the world frame and offered by :attr:`MavlinkBridge.mocap`, a
:class:`~drivers.mocap.pose.PoseSource` (:class:`~drivers.mavlink.mocap.MavlinkPoseSource`).

Threading: :meth:`MavlinkBridge.publish` is called by the telemetry process at any rate; it
only swaps a reference and appends events under a lock (never blocks on I/O). Either
:meth:`start` a service thread (wall clock), or call :meth:`step` with the session time from
the owner's loop (lockstep runs).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import Counter, deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from pymavlink.dialects.v20 import common as mavlink2

from drivers.mavlink.config import MavlinkConfig
from drivers.mavlink.frames import ned_to_world, q_ned_to_world, q_normalized
from drivers.mavlink.link import MavlinkCodec, UdpEndpoint
from drivers.mavlink.mocap import MavlinkPoseSource
from drivers.mavlink.signing import (
    SignatureVerifier,
    SigningKeyError,
    SigningStats,
    load_signing_key,
)
from groundstation import mavlink_messages as messages
from groundstation.operator import (
    MAX_TAKEOFF_ALT_M,
    MAX_TILT_RAD,
    Arm,
    CommandResult,
    Disarm,
    EmergencyStop,
    FlightPhase,
    Land,
    OperatorCommand,
    OperatorCommandSink,
    ParamSpec,
    PoseSetpoint,
    SetParam,
    SetTilt,
    Severity,
    StatusEvent,
    Takeoff,
    VehicleTelemetry,
)

log = logging.getLogger(__name__)
M = mavlink2

FORCE_DISARM_MAGIC = 21196
MAV_CMD_SET_TILT = M.MAV_CMD_USER_1
FTP_OPCODE_NAK = 129
FTP_OPEN_OPCODES = (3, 4, 6, 11)  # ListDirectory, OpenFileRO, CreateFile, OpenFileWO
FTP_ERR_UNKNOWN_COMMAND = 7
FTP_ERR_FILE_NOT_FOUND = 10
#: Default bound on offboard setpoint positions (m from the world origin): a lab cage.
SETPOINT_RANGE_M = 10.0
#: Phase changes remembered between two service passes (each sent as its own state messages).
MAX_PHASE_CHANGES = 16


_BUILDERS: dict[str, Callable[[VehicleTelemetry], Any]] = {
    "SYS_STATUS": messages.sys_status,
    "EXTENDED_SYS_STATE": messages.extended_sys_state,
    "ATTITUDE": messages.attitude,
    "ATTITUDE_QUATERNION": messages.attitude_quaternion,
    "LOCAL_POSITION_NED": messages.local_position_ned,
    "ODOMETRY": messages.odometry,
    "ACTUATOR_OUTPUT_STATUS": messages.actuator_output_status,
}
_MSG_IDS: dict[int, str] = {
    M.MAVLINK_MSG_ID_HEARTBEAT: "HEARTBEAT",
    M.MAVLINK_MSG_ID_SYS_STATUS: "SYS_STATUS",
    M.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: "EXTENDED_SYS_STATE",
    M.MAVLINK_MSG_ID_ATTITUDE: "ATTITUDE",
    M.MAVLINK_MSG_ID_ATTITUDE_QUATERNION: "ATTITUDE_QUATERNION",
    M.MAVLINK_MSG_ID_LOCAL_POSITION_NED: "LOCAL_POSITION_NED",
    M.MAVLINK_MSG_ID_ODOMETRY: "ODOMETRY",
    M.MAVLINK_MSG_ID_ACTUATOR_OUTPUT_STATUS: "ACTUATOR_OUTPUT_STATUS",
}


@dataclass(frozen=True, slots=True)
class BridgeStats:
    messages_out: dict[str, int]
    frames_in: int  # well-formed frames received (before the signature check)
    corrupted_in: int  # bytes that were not a valid frame
    signing: SigningStats | None  # None when signing is off
    command_results: dict[str, int]  # COMMAND_LONG/INT results by name
    setpoint_results: dict[str, int]  # SET_*_TARGET results by name
    ignored: dict[str, int]  # messages we do not act upon, by type
    events_dropped: int  # status events lost because the queue was full
    no_peer_drops: int  # telemetry frames not sent: no GCS address yet (udpin)
    gcs_heartbeat_age_s: float  # inf before the first GCS heartbeat
    refused_unsigned: int = 0  # flight-changing commands refused: no key, unsigned not allowed
    refused_out_of_range: int = 0  # commands, setpoints, params, poses with unphysical values
    handler_errors: int = 0  # messages whose handling failed (guarded, never raised)

    @property
    def rejected_frames(self) -> int:
        """Frames dropped by the signature check (0 without a key)."""
        return 0 if self.signing is None else self.signing.rejected


class MavlinkBridge:
    """Telemetry out, operator commands in, over one MAVLink link. See the module docstring."""

    def __init__(self, config: MavlinkConfig, sink: OperatorCommandSink, *,
                 params: Sequence[ParamSpec] = (), key: bytes | None = None,
                 allow_unsigned_commands: bool = False, phase_events: bool = True,
                 max_tilt_rad: float = MAX_TILT_RAD,
                 setpoint_range_m: float = SETPOINT_RANGE_M,
                 clock: Callable[[], float] = time.monotonic,
                 clock_ns: Callable[[], int] = time.monotonic_ns,
                 max_events: int = 256) -> None:
        if config.signing and key is None:
            raise ValueError("signing is on but no key was given (load_signing_key)")
        self.config = config
        self.signing = config.signing
        # without a key anyone on the network could send these: refused unless allowed
        self.allow_unsigned_commands = allow_unsigned_commands
        self._phase_events = phase_events
        self.max_tilt_rad = max_tilt_rad
        self.setpoint_range_m = setpoint_range_m
        self._sink = sink
        self._clock = clock
        self._clock_ns = clock_ns
        self._codec = MavlinkCodec(config.sysid, config.compid, key if config.signing else None,
                                   config.link_id, frozenset(config.allow_unsigned_ids))
        self._endpoint = UdpEndpoint(config.uri)
        self._params: dict[str, ParamSpec] = {p.name: p for p in params}
        self._param_order = [p.name for p in params]
        self._param_values = {p.name: float(p.value) for p in params}
        self.mocap = MavlinkPoseSource(clock_ns, config.mocap_latency_s)
        # mailbox written by publish(), read by the service thread
        self._lock = threading.Lock()
        self._latest: VehicleTelemetry | None = None
        self._events: deque[StatusEvent] = deque()
        self._max_events = max_events
        self._events_dropped = 0
        self._prev_phase: FlightPhase | None = None
        self._prev_health: dict[str, bool] | None = None
        # service-thread state
        self._periods = {name: (1.0 / hz if hz > 0 else None)
                         for name, hz in config.rates_hz().items()}
        self._next_due: dict[str, float] = {}
        # the snapshots that changed the phase, oldest first: the next pass sends a HEARTBEAT
        # and an EXTENDED_SYS_STATE of each, so a phase shorter than a service pass (a phase
        # the loop left before the thread ran: a busy machine, a lockstep mission) still goes
        # out, in order. Bounded: a loop flapping phases cannot grow it.
        self._phase_changes: deque[VehicleTelemetry] = deque(maxlen=MAX_PHASE_CHANGES)
        self._chunk_id = 0
        self._gcs_heartbeat_t: float | None = None
        self._out: Counter[str] = Counter()
        self._cmd_results: Counter[str] = Counter()
        self._sp_results: Counter[str] = Counter()
        self._ignored: Counter[str] = Counter()
        self._refused_unsigned = 0
        self._refused_range = 0
        self._handler_errors = 0
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._step_lock = threading.Lock()

    @classmethod
    def from_config(cls, config: MavlinkConfig, sink: OperatorCommandSink, *,
                    params: Sequence[ParamSpec] = (),
                    environ: Mapping[str, str] | None = None,
                    **kwargs: Any) -> MavlinkBridge:
        """The bridge of a session: with signing on, the key is read from ``key_file`` or
        the ``key_env`` variable (:class:`SigningKeyError` naming them when there is none)."""
        key = None
        if config.signing:
            key = load_signing_key(config.key_file, config.key_env, environ)
            if key is None:
                raise SigningKeyError(
                    config.uri, f"signing is on but no key: set ${config.key_env} or key_file")
        return cls(config, sink, params=params, key=key, **kwargs)

    # -- the telemetry side -------------------------------------------------------------

    def publish(self, tel: VehicleTelemetry) -> None:
        """Hand over the newest snapshot. Never blocks on I/O; events are queued (bounded,
        drops counted); phase changes and health changes become status events here."""
        h = tel.health
        health = {"imu": h.imu_ok, "mocap": h.mocap_ok, "estimator": h.estimator_ok,
                  "motors": h.motors_ok, "servo": h.servo_ok, "battery": h.battery_ok,
                  "geofence": h.geofence_ok}
        with self._lock:
            new: list[StatusEvent] = []
            if self._prev_phase is not None and tel.phase is not self._prev_phase:
                # the new phase goes out in a HEARTBEAT and an EXTENDED_SYS_STATE (the landed
                # state) of this very snapshot at the next service pass, not up to a period
                # later and not replaced by a later phase: a phase that lasts less than that (a
                # short lockstep mission, a brief LANDING) is still seen
                self._phase_changes.append(tel)
                if self._phase_events:
                    sev = Severity.EMERGENCY if tel.phase is FlightPhase.CUT \
                        else Severity.NOTICE
                    new.append(StatusEvent(
                        tel.t_s, f"{self._prev_phase.name} -> {tel.phase.name}", sev))
            if self._prev_health is not None:
                for name, ok in health.items():
                    if ok != self._prev_health[name]:
                        new.append(StatusEvent(tel.t_s, f"{'ok' if ok else 'fault'}: {name}",
                                               Severity.INFO if ok else Severity.WARNING))
            new.extend(tel.events)
            for ev in new:
                if len(self._events) >= self._max_events:
                    self._events_dropped += 1
                else:
                    self._events.append(ev)
            self._prev_phase = tel.phase
            self._prev_health = health
            self._latest = tel

    def post_event(self, text: str, severity: Severity = Severity.INFO) -> None:
        """Queue a status event outside a snapshot (e.g. a message from the session)."""
        t = self._latest.t_s if self._latest is not None else 0.0
        with self._lock:
            if len(self._events) >= self._max_events:
                self._events_dropped += 1
            else:
                self._events.append(StatusEvent(t, text, severity))

    # -- servicing -----------------------------------------------------------------------

    def step(self, now_s: float | None = None, wait_s: float = 0.0) -> None:
        """One service pass: act on every datagram waiting, then send what is due at
        ``now_s`` (the bridge clock when None). Blocks only when ``wait_s`` > 0: then it
        first waits up to ``wait_s`` for a datagram (a lockstep owner waiting on the GCS)."""
        if wait_s > 0.0:
            self._endpoint.wait_readable(wait_s)
        now = self._clock() if now_s is None else now_s
        with self._step_lock:
            for data, sender in self._endpoint.recv_all():
                self._feed_locked(data, now, sender)
            self._send_due(now)

    def feed(self, data: bytes, now_s: float,
             sender: tuple[str, int] | None = None) -> None:
        """Act on one datagram as if it had arrived now (the input path of :meth:`step`;
        public for tests and fuzzing). Never raises: every failure is counted."""
        with self._step_lock:
            self._feed_locked(data, now_s, sender)

    def _feed_locked(self, data: bytes, now: float, sender: tuple[str, int] | None) -> None:
        try:
            msgs = self._codec.decode(data)
        except Exception:  # the codec guards itself; this is the last line
            self._handler_failed("datagram")
            return
        if msgs and sender is not None:
            self._endpoint.adopt_peer(sender)
        for msg in msgs:
            try:
                self._handle(msg, now)
            except Exception:  # a bad message must not stop the link
                self._handler_failed(_type_of(msg))

    def _handler_failed(self, kind: str) -> None:
        self._handler_errors += 1
        self._ignored["ERROR_" + kind] += 1
        # one traceback tells the story; a flood of bad frames must not flood the log
        if self._handler_errors == 1:
            log.warning("%s: error handling %s (further errors counted only)",
                        self._endpoint.name, kind, exc_info=True)
        else:
            log.debug("%s: error handling %s", self._endpoint.name, kind, exc_info=True)

    def set_rate(self, name: str, hz: float) -> None:
        """Send ``name`` (one of :meth:`MavlinkConfig.rates_hz`) at ``hz`` from now on."""
        with self._step_lock:
            self._periods[name] = 1.0 / hz if hz > 0 else None
            self._next_due.pop(name, None)

    def announce_final(self, text: str, duration_s: float, *,
                       severity: Severity = Severity.NOTICE, interval_s: float = 0.5,
                       sleep: Callable[[float], None] = time.sleep) -> None:
        """Announce the session's end: ``text`` once as STATUSTEXT, then HEARTBEAT and
        EXTENDED_SYS_STATE of the last snapshot every ``interval_s`` for ``duration_s``
        (wall time: a GCS's link-state logic runs on its own clock). Serves the link
        meanwhile, also without the service thread."""
        self.post_event(text, severity)
        for name in ("HEARTBEAT", "EXTENDED_SYS_STATE"):
            self.set_rate(name, 1.0 / interval_s)
        end = self._clock() + duration_s
        threaded = self._thread is not None
        while True:
            now = self._clock()
            if not threaded:
                self.step(now)
            if now >= end:
                break
            sleep(min(0.05, end - now))
        if not threaded:
            self.step()

    def next_due_s(self, now_s: float) -> float:
        """Seconds until the next telemetry message is due (for the service thread's wait)."""
        if not self._next_due or self._phase_changes:
            return 0.0
        return max(0.0, min(self._next_due.values()) - now_s)

    def start(self) -> None:
        """Serve the link in a daemon thread driven by the bridge clock."""
        if self._thread is not None:
            return
        self._thread = threading.Thread(target=self._run, name="mavlink-bridge", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            now = self._clock()
            try:
                self.step(now)
            except Exception:  # e.g. a send the OS refuses: counted, logged once
                self._handler_failed("step")
            wait = min(self.next_due_s(self._clock()), 0.05)
            if wait > 0:
                self._endpoint.wait_readable(wait)

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None

    def close(self) -> None:
        self.stop()
        self._endpoint.close()

    def __enter__(self) -> MavlinkBridge:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def local_address(self) -> tuple[str, int]:
        return self._endpoint.local_address

    def param_value(self, name: str) -> float:
        return self._param_values[name]

    def gcs_link_ok(self, now_s: float | None = None) -> bool:
        """A GCS heartbeat arrived within ``gcs_timeout_s``."""
        now = self._clock() if now_s is None else now_s
        t = self._gcs_heartbeat_t
        return t is not None and now - t <= self.config.gcs_timeout_s

    def stats(self, now_s: float | None = None) -> BridgeStats:
        now = self._clock() if now_s is None else now_s
        v = self._codec.verifier
        t = self._gcs_heartbeat_t
        with self._lock:
            dropped = self._events_dropped
        with self._step_lock:  # the counters move only inside step()
            return self._stats_locked(now, v, t, dropped)

    def _stats_locked(self, now: float, v: SignatureVerifier | None, t: float | None,
                      dropped: int) -> BridgeStats:
        return BridgeStats(
            messages_out=dict(self._out), frames_in=self._codec.frames_in,
            corrupted_in=self._codec.corrupted, signing=None if v is None else v.stats(),
            command_results=dict(self._cmd_results), setpoint_results=dict(self._sp_results),
            ignored=dict(self._ignored), events_dropped=dropped,
            no_peer_drops=self._endpoint.no_peer_drops,
            gcs_heartbeat_age_s=math.inf if t is None else now - t,
            refused_unsigned=self._refused_unsigned, refused_out_of_range=self._refused_range,
            handler_errors=self._handler_errors)

    # -- sending -------------------------------------------------------------------------

    def _send(self, msg: Any) -> None:
        if self._endpoint.send(self._codec.encode(msg)):
            self._out[msg.get_type()] += 1

    def _send_due(self, now: float) -> None:
        with self._lock:
            tel = self._latest
            events = list(self._events)
            self._events.clear()
            changes = list(self._phase_changes)
            self._phase_changes.clear()
        for ev in events:
            self._chunk_id = self._chunk_id % 65535 + 1
            for m in messages.statustext(ev, self._chunk_id):
                self._send(m)
        for snap in changes:  # each phase change in its own state messages, then the cadence
            for name in ("HEARTBEAT", "EXTENDED_SYS_STATE"):  # again from now
                period = self._periods.get(name)
                if period is not None:
                    self._send_now(name, snap)
                    self._next_due[name] = now + period
        for name, period in self._periods.items():
            if period is None:
                self._next_due.pop(name, None)
                continue
            due = self._next_due.setdefault(name, now)
            if now + 1e-9 < due:
                continue
            self._send_now(name, tel)
            # keep the cadence; after a stall, restart from now instead of bursting
            nxt = due + period
            self._next_due[name] = nxt if nxt > now else now + period

    def _send_now(self, name: str, tel: VehicleTelemetry | None) -> None:
        """One telemetry message of ``tel`` (a HEARTBEAT even before the first snapshot)."""
        if name == "HEARTBEAT":
            self._send(messages.heartbeat(tel))
        elif tel is not None:
            self._send(_BUILDERS[name](tel))

    # -- receiving -----------------------------------------------------------------------

    def _for_us(self, msg: Any) -> bool:
        ts = getattr(msg, "target_system", 0)
        tc = getattr(msg, "target_component", 0)
        return ts in (0, self.config.sysid) and tc in (0, self.config.compid)

    def _handle(self, msg: Any, now: float) -> None:
        kind = msg.get_type()
        if kind == "HEARTBEAT":
            if msg.type == M.MAV_TYPE_GCS:
                self._gcs_heartbeat_t = now
            return
        if kind in ("COMMAND_LONG", "COMMAND_INT"):
            if self._for_us(msg):
                self._on_command(msg)
            return
        if kind in ("PARAM_REQUEST_LIST", "PARAM_REQUEST_READ", "PARAM_SET"):
            if self._for_us(msg):
                self._on_param(msg, kind)
            return
        if kind == "SET_POSITION_TARGET_LOCAL_NED":
            if self._for_us(msg):
                self._on_position_target(msg)
            return
        if kind == "SET_ATTITUDE_TARGET":
            if self._for_us(msg):
                self._on_attitude_target(msg)
            return
        if kind == "MISSION_REQUEST_LIST":
            if self._for_us(msg):
                self._send(M.MAVLink_mission_count_message(
                    msg.get_srcSystem(), msg.get_srcComponent(), 0, msg.mission_type))
            return
        if kind == "FILE_TRANSFER_PROTOCOL":
            if msg.target_system in (0, self.config.sysid):
                self._on_ftp(msg)
            return
        if kind == "TIMESYNC":
            if msg.tc1 == 0:
                self._send(M.MAVLink_timesync_message(self._clock_ns(), msg.ts1))
            return
        if kind == "ATT_POS_MOCAP":
            q = tuple(float(v) for v in msg.q)
            if len(q) != 4 or not self.mocap.on_pose(
                    (float(msg.x), float(msg.y), float(msg.z)), q,
                    "ATT_POS_MOCAP"):
                self._refused_range += 1
            return
        if kind == "VISION_POSITION_ESTIMATE":
            if not self.mocap.on_euler_pose((float(msg.x), float(msg.y), float(msg.z)),
                                            float(msg.roll), float(msg.pitch), float(msg.yaw),
                                            "VISION_POSITION_ESTIMATE"):
                self._refused_range += 1
            return
        self._ignored[kind] += 1

    def _trusted(self) -> bool:
        """May a frame that got this far change the flight? With a key every accepted frame
        was signed (allow-listed unsigned ids command nothing); without one, only if the
        owner allowed unsigned commands."""
        return self.signing or self.allow_unsigned_commands

    def _refuse_unsigned(self) -> CommandResult:
        self._refused_unsigned += 1
        return CommandResult.DENIED

    def _out_of_range(self) -> CommandResult:
        self._refused_range += 1
        return CommandResult.DENIED

    def _submit(self, cmd: OperatorCommand) -> CommandResult:
        if not self._trusted():
            return self._refuse_unsigned()
        try:
            return CommandResult(self._sink.submit(cmd))
        except Exception:
            log.exception("%s: command sink failed on %s", self._endpoint.name, cmd)
            return CommandResult.FAILED

    def _command_to_operator(self, command: int, p: list[float]
                             ) -> OperatorCommand | CommandResult | None:
        """The operator command for ``command``; a result when it is malformed; None when
        we do not support it."""
        if command in (M.MAV_CMD_COMPONENT_ARM_DISARM, M.MAV_CMD_DO_FLIGHTTERMINATION,
                       MAV_CMD_SET_TILT) and not math.isfinite(p[0]):
            return self._out_of_range()
        if command == M.MAV_CMD_COMPONENT_ARM_DISARM:
            if p[0] >= 0.5:
                return Arm()
            if _as_int(p[1]) == FORCE_DISARM_MAGIC:
                return EmergencyStop("force disarm")
            return Disarm()
        if command == M.MAV_CMD_NAV_TAKEOFF:
            if not (math.isfinite(p[6]) and 0.0 < p[6] <= MAX_TAKEOFF_ALT_M):
                return self._out_of_range()
            return Takeoff(alt_m=p[6])
        if command == M.MAV_CMD_NAV_LAND:
            return Land()
        if command == M.MAV_CMD_DO_FLIGHTTERMINATION and p[0] >= 0.5:
            return EmergencyStop("flight termination")
        if command == MAV_CMD_SET_TILT:
            tilt = math.radians(p[0])
            if not 0.0 <= tilt <= self.max_tilt_rad + 1e-9:  # the vehicle's mechanical range
                return self._out_of_range()
            return SetTilt(tilt_rad=min(tilt, self.max_tilt_rad))
        return None

    def _on_command(self, msg: Any) -> None:
        command = int(msg.command)
        if msg.get_type() == "COMMAND_LONG":
            p = [msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6,
                 msg.param7]
        else:  # COMMAND_INT: x, y are scaled integers, z a float
            p = [msg.param1, msg.param2, msg.param3, msg.param4, float(msg.x), float(msg.y),
                 msg.z]
        try:
            result = self._service_command(command, p)
            if result is None:
                cmd = self._command_to_operator(command, p)
                if cmd is None:
                    result = CommandResult.UNSUPPORTED
                elif isinstance(cmd, CommandResult):
                    result = cmd
                else:
                    result = self._submit(cmd)
        except Exception:  # still answer: a GCS waiting for the ACK would retry forever
            self._handler_failed(f"COMMAND {command}")
            result = CommandResult.FAILED
        self._cmd_results[result.name] += 1
        self._send(M.MAVLink_command_ack_message(command, int(result), 0, 0,
                                                 msg.get_srcSystem(), msg.get_srcComponent()))

    def _service_command(self, command: int, p: list[float]) -> CommandResult | None:
        """Commands about the link itself; None for operator commands."""
        R = CommandResult
        if command in (M.MAV_CMD_REQUEST_MESSAGE, M.MAV_CMD_SET_MESSAGE_INTERVAL) and not (
                math.isfinite(p[0]) and math.isfinite(p[1])):
            return R.DENIED
        if command == M.MAV_CMD_REQUEST_MESSAGE:
            msg_id = int(p[0])
            if msg_id == M.MAVLINK_MSG_ID_AUTOPILOT_VERSION:
                self._send_autopilot_version()
                return R.ACCEPTED
            name = _MSG_IDS.get(msg_id)
            if name is None or (name != "HEARTBEAT" and self._latest is None):
                return R.UNSUPPORTED if name is None else R.TEMPORARILY_REJECTED
            self._send_now(name, self._latest)
            return R.ACCEPTED
        if command == M.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES:
            self._send_autopilot_version()
            return R.ACCEPTED
        if command == M.MAV_CMD_SET_MESSAGE_INTERVAL:
            name = _MSG_IDS.get(int(p[0]))
            if name is None:
                return R.UNSUPPORTED
            interval_us = p[1]
            if interval_us == 0:
                hz = self.config.rates_hz()[name]
                self._periods[name] = 1.0 / hz if hz > 0 else None
            elif interval_us < 0:
                self._periods[name] = None
            elif interval_us < 1000:  # faster than 1 kHz makes no sense for a 500 Hz loop
                return R.DENIED
            else:
                self._periods[name] = interval_us * 1e-6
            return R.ACCEPTED
        return None

    def _send_autopilot_version(self) -> None:
        caps = (M.MAV_PROTOCOL_CAPABILITY_MAVLINK2 | M.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT
                | M.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
                | M.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
                | M.MAV_PROTOCOL_CAPABILITY_SET_ATTITUDE_TARGET)
        self._send(M.MAVLink_autopilot_version_message(
            caps, 0, 0, 0, 0, [0] * 8, [0] * 8, [0] * 8, 0, 0, 0))

    # parameters

    def _param_msg(self, name: str) -> Any:
        return M.MAVLink_param_value_message(
            name.encode("ascii"), self._param_values[name], M.MAV_PARAM_TYPE_REAL32,
            len(self._param_order), self._param_order.index(name))

    def _on_param(self, msg: Any, kind: str) -> None:
        if kind == "PARAM_REQUEST_LIST":
            for name in self._param_order:
                self._send(self._param_msg(name))
            return
        if kind == "PARAM_REQUEST_READ":
            idx = int(msg.param_index)
            name = _param_name(msg.param_id) if idx < 0 else (
                self._param_order[idx] if idx < len(self._param_order) else "")
            if name in self._params:
                self._send(self._param_msg(name))
            else:
                self._ignored["PARAM_REQUEST_READ_UNKNOWN"] += 1
            return
        name = _param_name(msg.param_id)
        spec_ = self._params.get(name)
        if spec_ is None:
            self._ignored["PARAM_SET_UNKNOWN"] += 1
            return
        value = float(msg.param_value)
        result = self._submit(SetParam(name, value)) if spec_.accepts(value) else \
            self._out_of_range()
        if result is CommandResult.ACCEPTED:
            self._param_values[name] = value
        self._cmd_results["PARAM_SET_" + result.name] += 1
        self._send(self._param_msg(name))

    # offboard setpoints

    def _on_position_target(self, msg: Any) -> None:
        if msg.coordinate_frame != M.MAV_FRAME_LOCAL_NED:
            self._sp_results["UNSUPPORTED"] += 1
            return
        mask = int(msg.type_mask)
        pos_given = not mask & 0b111
        yaw_given = not mask & M.POSITION_TARGET_TYPEMASK_YAW_IGNORE
        pos = ned_to_world((float(msg.x), float(msg.y), float(msg.z))) if pos_given else None
        # yaw about NED down is minus the yaw about world z up
        yaw = -float(msg.yaw) if yaw_given else None
        if pos is None and yaw is None:
            self._sp_results["UNSUPPORTED"] += 1
            return
        if (pos is not None and not _within(pos, self.setpoint_range_m)) or (
                yaw is not None and not math.isfinite(yaw)):
            self._sp_results[self._out_of_range().name] += 1
            return
        result = self._submit(PoseSetpoint(pos_w_m=pos, yaw_rad=yaw))
        self._sp_results[result.name] += 1
        if result is CommandResult.ACCEPTED:
            tel = self._latest
            t_ms = messages.time_boot_ms(tel) if tel is not None else 0
            self._send(M.MAVLink_position_target_local_ned_message(
                t_ms, M.MAV_FRAME_LOCAL_NED, mask, msg.x, msg.y, msg.z, 0, 0, 0, 0, 0, 0,
                msg.yaw, 0))

    def _on_attitude_target(self, msg: Any) -> None:
        if int(msg.type_mask) & M.ATTITUDE_TARGET_TYPEMASK_ATTITUDE_IGNORE:
            self._sp_results["UNSUPPORTED"] += 1
            return
        q_in = tuple(float(v) for v in msg.q)
        try:
            q = q_ned_to_world(q_normalized(q_in))  # type: ignore[arg-type]
        except (ValueError, OverflowError, IndexError):
            self._sp_results[self._out_of_range().name] += 1
            return
        result = self._submit(PoseSetpoint(q_wb=q))
        self._sp_results[result.name] += 1

    # tolerated requests

    def _on_ftp(self, msg: Any) -> None:
        req = bytes(msg.payload)
        seq = int.from_bytes(req[0:2], "little")
        session, opcode = req[2], req[3]
        err = FTP_ERR_FILE_NOT_FOUND if opcode in FTP_OPEN_OPCODES else FTP_ERR_UNKNOWN_COMMAND
        payload = bytearray(251)
        payload[0:2] = ((seq + 1) & 0xFFFF).to_bytes(2, "little")
        payload[2] = session
        payload[3] = FTP_OPCODE_NAK
        payload[4] = 1  # size of the data: the error code
        payload[5] = opcode  # req_opcode
        payload[12] = err
        self._send(M.MAVLink_file_transfer_protocol_message(
            0, msg.get_srcSystem(), msg.get_srcComponent(), list(payload)))
        self._ignored["FILE_TRANSFER_PROTOCOL"] += 1


def _within(v: tuple[float, float, float], range_m: float) -> bool:
    return all(math.isfinite(c) for c in v) and math.sqrt(sum(c * c for c in v)) <= range_m


def _type_of(msg: Any) -> str:
    try:
        return str(msg.get_type())
    except Exception:
        return "UNKNOWN"


def _as_int(x: float) -> int | None:
    """``round(x)``, or None for NaN and infinities (a GCS may send anything)."""
    return round(x) if math.isfinite(x) else None


def _param_name(raw: Any) -> str:
    if isinstance(raw, bytes):
        raw = raw.decode("ascii", "replace")
    return str(raw).split("\x00", 1)[0]


__all__ = ["BridgeStats", "MavlinkBridge", "MavlinkConfig", "MavlinkPoseSource"]  # config and
# pose source re-exported: a bridge's users need them together

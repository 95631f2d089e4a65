"""The operator's vocabulary: what a ground-control station sees of the vehicle and may ask of it.

This module is the seam between the flight session (the 500 Hz loop and its state machine) and
every operator surface (the MAVLink bridge, later others). It is a leaf: standard library only,
no I/O, so the drivers and the control process can both import it cheaply.

Telemetry out
    :class:`VehicleTelemetry` is one immutable snapshot handed by the telemetry process to an
    operator surface (``bridge.publish(snapshot)``), at any rate up to the loop rate. Frames are
    the ground station's: world W z up, x forward (the MoCap/vehicle frame of
    ``sim_backend.vehicle``), body B x towards propeller 1, z up along the rotor axes, ``q_wb``
    body -> world as ``(w, x, y, z)``. Conversions to MAVLink's NED/FRD live in the bridge.

Commands in
    Operator commands are frozen dataclasses (:class:`Arm`, :class:`Disarm`, :class:`Takeoff`,
    :class:`Land`, :class:`EmergencyStop`, :class:`SetTilt`, :class:`PoseSetpoint`,
    :class:`SetParam`) submitted through an :class:`OperatorCommandSink`. The sink answers at
    once with a :class:`CommandResult` decided from the *current* flight phase by the pure rule
    :func:`decide` (the table below), then carries the command out asynchronously. The flight
    state machine implements the sink; :class:`RuleBasedCommandSink` is the reference
    implementation (it records commands and moves through the phases the same way).

State rules (:func:`decide`)

=================  ==========================================================================
command            accepted when (otherwise)
=================  ==========================================================================
Arm                PREFLIGHT or DISARMED and the preflight checks pass (TEMPORARILY_REJECTED);
                   already ARMED: accepted, no-op; in flight or CUT: DENIED
Disarm             ARMED, PREFLIGHT, DISARMED, CUT (no-op when already disarmed); in flight
                   (TAKEOFF, MISSION, LANDING): DENIED, use Land or EmergencyStop
Takeoff(alt_m)     ARMED (TEMPORARILY_REJECTED); alt_m outside (0, MAX_TAKEOFF_ALT_M]: DENIED
Land               TAKEOFF, MISSION, LANDING (TEMPORARILY_REJECTED)
EmergencyStop      always (motors cut; phase CUT)
SetTilt(tilt_rad)  any phase but CUT (DENIED); tilt outside [0, max_tilt_rad]: DENIED
PoseSetpoint       MISSION (TEMPORARILY_REJECTED); non-finite values: DENIED
SetParam           any phase but CUT (DENIED); the value range is checked by the surface's
                   parameter table (:class:`ParamSpec`) before submission
=================  ==========================================================================
"""

from __future__ import annotations

import enum
import math
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

Vec3 = tuple[float, float, float]
Quat = tuple[float, float, float, float]

__all__ = [
    "MAX_TAKEOFF_ALT_M",
    "MAX_TILT_RAD",
    "STATUS_BATTERY",
    "STATUS_PREFLIGHT",
    "STATUS_SIZE",
    "STATUS_STATE",
    "STATUS_TRANSITIONS",
    "TRANSITION_RING",
    "Arm",
    "CommandResult",
    "Disarm",
    "EmergencyStop",
    "FlightPhase",
    "Land",
    "OperatorCommand",
    "OperatorCommandSink",
    "ParamSpec",
    "PoseSetpoint",
    "RuleBasedCommandSink",
    "SensorHealth",
    "SetParam",
    "SetTilt",
    "Severity",
    "StatusEvent",
    "Takeoff",
    "VehicleTelemetry",
    "decide",
    "next_phase",
    "operator_params",
    "post_transition",
    "transitions_since",
]

#: Mechanical tilt range of the FAST-Hex (paper: 0..35 deg).
MAX_TILT_RAD = math.radians(35.0)
#: Highest take-off altitude an operator may ask for (m above the world origin); a lab cage.
MAX_TAKEOFF_ALT_M = 5.0


class FlightPhase(enum.IntEnum):
    """The flight session's phases. The value is MAVLink's HEARTBEAT ``custom_mode``."""

    PREFLIGHT = 0  # disarmed, preflight checks running or done
    ARMED = 1  # motors at idle on the ground
    TAKEOFF = 2
    MISSION = 3  # flying; the mission or offboard setpoints drive the reference
    LANDING = 4  # includes failsafe landings (the reason goes out as a status event)
    DISARMED = 5  # landed and motors stopped; may arm again
    CUT = 6  # emergency stop: motors cut, session over

    @property
    def armed(self) -> bool:
        return self in (FlightPhase.ARMED, FlightPhase.TAKEOFF, FlightPhase.MISSION,
                        FlightPhase.LANDING)

    @property
    def flying(self) -> bool:
        return self in (FlightPhase.TAKEOFF, FlightPhase.MISSION, FlightPhase.LANDING)


class Severity(enum.IntEnum):
    """Status event severity, numerically equal to MAVLink's MAV_SEVERITY (RFC 5424)."""

    EMERGENCY = 0
    ALERT = 1
    CRITICAL = 2
    ERROR = 3
    WARNING = 4
    NOTICE = 5
    INFO = 6
    DEBUG = 7


@dataclass(frozen=True, slots=True)
class StatusEvent:
    """A human-readable event: a state transition with its reason, a fault, a failsafe."""

    t_s: float
    text: str
    severity: Severity = Severity.INFO


@dataclass(frozen=True, slots=True)
class SensorHealth:
    """Per-device health as judged by the session's checks (True = healthy)."""

    imu_ok: bool = True  # Flight-Ctrl IMU stream at rate and fresh
    mocap_ok: bool = True  # MoCap body seen at rate and fresh
    estimator_ok: bool = True  # UKF converged, covariance bounded
    motors_ok: bool = True  # BL-Ctrls answering, rotor speeds as commanded
    servo_ok: bool = True  # tilt servo answering, angle agrees with the command
    battery_ok: bool = True  # above the minimum voltage
    geofence_ok: bool = True  # inside the session's geofence box
    preflight_ok: bool = False  # every preflight check passed: arming allowed


@dataclass(frozen=True, slots=True)
class VehicleTelemetry:
    """One snapshot of the vehicle for operator surfaces (world z-up frame, SI units).

    ``events`` are the status events raised since the previous snapshot; a surface forwards
    each exactly once (the bridge queues them at :meth:`publish` time, so a snapshot that is
    overwritten before being sent does not lose its events).
    """

    t_s: float  # session time (s since the session started)
    phase: FlightPhase
    armed: bool
    pos_w_m: Vec3
    vel_w_m_s: Vec3
    q_wb: Quat  # (w, x, y, z) body -> world
    omega_b_rad_s: Vec3  # body angular rate, body frame (x to propeller 1, z up)
    rotor_speeds_hz: tuple[float, float, float, float, float, float]
    tilt_rad: float  # measured synchronised tilt alpha
    battery_v: float  # NaN if unknown
    health: SensorHealth = field(default_factory=SensorHealth)
    events: tuple[StatusEvent, ...] = ()


class CommandResult(enum.IntEnum):
    """The answer to an operator command, numerically equal to MAVLink's MAV_RESULT."""

    ACCEPTED = 0
    TEMPORARILY_REJECTED = 1  # valid, but not in the current phase; may succeed later
    DENIED = 2  # invalid parameters, or never allowed in this phase
    UNSUPPORTED = 3
    FAILED = 4  # accepted by the rules but the executor could not carry it out


@dataclass(frozen=True, slots=True)
class Arm:
    pass


@dataclass(frozen=True, slots=True)
class Disarm:
    pass


@dataclass(frozen=True, slots=True)
class Takeoff:
    alt_m: float  # height of the hover point above the world origin (z up)


@dataclass(frozen=True, slots=True)
class Land:
    pass


@dataclass(frozen=True, slots=True)
class EmergencyStop:
    reason: str = "operator"


@dataclass(frozen=True, slots=True)
class SetTilt:
    tilt_rad: float  # target synchronised tilt alpha; the tilt planner rate-limits it


@dataclass(frozen=True, slots=True)
class PoseSetpoint:
    """An offboard reference: position and/or attitude in the world frame; None = keep."""

    pos_w_m: Vec3 | None = None
    yaw_rad: float | None = None  # heading about world z (ignored when q_wb is given)
    q_wb: Quat | None = None  # full attitude (a fully-actuated vehicle can hold any)


@dataclass(frozen=True, slots=True)
class SetParam:
    name: str  # one of the ParamSpec names, <= 16 characters
    value: float


OperatorCommand = Arm | Disarm | Takeoff | Land | EmergencyStop | SetTilt | PoseSetpoint | SetParam


@runtime_checkable
class OperatorCommandSink(Protocol):
    """Where operator surfaces send commands. Thread-safe; ``submit`` never blocks for long:
    it decides with :func:`decide` from the current phase and queues the command."""

    def submit(self, cmd: OperatorCommand) -> CommandResult: ...


def _finite(values: Sequence[float]) -> bool:
    return all(math.isfinite(v) for v in values)


def decide(cmd: OperatorCommand, phase: FlightPhase, *, preflight_ok: bool = True,
           max_tilt_rad: float = MAX_TILT_RAD) -> CommandResult:
    """The result of ``cmd`` in ``phase`` (the module docstring's table). Pure."""
    R = CommandResult
    P = FlightPhase
    if isinstance(cmd, EmergencyStop):
        return R.ACCEPTED
    if isinstance(cmd, Arm):
        if phase is P.ARMED:
            return R.ACCEPTED
        if phase in (P.PREFLIGHT, P.DISARMED):
            return R.ACCEPTED if preflight_ok else R.TEMPORARILY_REJECTED
        return R.DENIED
    if isinstance(cmd, Disarm):
        return R.DENIED if phase.flying else R.ACCEPTED
    if isinstance(cmd, Takeoff):
        if not (math.isfinite(cmd.alt_m) and 0.0 < cmd.alt_m <= MAX_TAKEOFF_ALT_M):
            return R.DENIED
        return R.ACCEPTED if phase is P.ARMED else R.TEMPORARILY_REJECTED
    if isinstance(cmd, Land):
        return R.ACCEPTED if phase.flying else R.TEMPORARILY_REJECTED
    if phase is P.CUT:
        return R.DENIED
    if isinstance(cmd, SetTilt):
        ok = math.isfinite(cmd.tilt_rad) and 0.0 <= cmd.tilt_rad <= max_tilt_rad
        return R.ACCEPTED if ok else R.DENIED
    if isinstance(cmd, PoseSetpoint):
        parts = [*(cmd.pos_w_m or ()), *(cmd.q_wb or ())]
        if cmd.yaw_rad is not None:
            parts.append(cmd.yaw_rad)
        if not _finite(parts) or (cmd.pos_w_m is None and cmd.q_wb is None
                                  and cmd.yaw_rad is None):
            return R.DENIED
        return R.ACCEPTED if phase is P.MISSION else R.TEMPORARILY_REJECTED
    if isinstance(cmd, SetParam):
        return R.ACCEPTED if math.isfinite(cmd.value) else R.DENIED
    return R.UNSUPPORTED


def next_phase(cmd: OperatorCommand, phase: FlightPhase) -> FlightPhase:
    """The phase an *accepted* command leads to (what the state machine does first)."""
    if isinstance(cmd, EmergencyStop):
        return FlightPhase.CUT
    if isinstance(cmd, Arm):
        return FlightPhase.ARMED
    if isinstance(cmd, Disarm):
        return phase if phase in (FlightPhase.CUT, FlightPhase.PREFLIGHT) else FlightPhase.DISARMED
    if isinstance(cmd, Takeoff):
        return FlightPhase.TAKEOFF
    if isinstance(cmd, Land):
        return FlightPhase.LANDING
    return phase


class RuleBasedCommandSink:
    """The reference :class:`OperatorCommandSink`: applies :func:`decide`, records every
    submission, and moves its phase as the state machine would (:func:`next_phase`).

    ``on_change(phase)`` is called (outside the lock) after an accepted command changed the
    phase, e.g. to publish fresh telemetry. Thread-safe.
    """

    def __init__(self, phase: FlightPhase = FlightPhase.PREFLIGHT, *, preflight_ok: bool = True,
                 max_tilt_rad: float = MAX_TILT_RAD,
                 on_change: Callable[[FlightPhase], None] | None = None) -> None:
        self._lock = threading.Lock()
        self._phase = phase
        self.preflight_ok = preflight_ok
        self.max_tilt_rad = max_tilt_rad
        self._on_change = on_change
        self._log: list[tuple[OperatorCommand, CommandResult]] = []
        self._changed = threading.Condition(self._lock)

    @property
    def phase(self) -> FlightPhase:
        with self._lock:
            return self._phase

    def set_phase(self, phase: FlightPhase) -> None:
        """Move the phase from outside (the mission finished, a failsafe fired)."""
        with self._lock:
            self._phase = phase
            self._changed.notify_all()

    @property
    def submissions(self) -> list[tuple[OperatorCommand, CommandResult]]:
        """Every command submitted so far, with its result, in order."""
        with self._lock:
            return list(self._log)

    @property
    def accepted(self) -> list[OperatorCommand]:
        with self._lock:
            return [c for c, r in self._log if r is CommandResult.ACCEPTED]

    def submit(self, cmd: OperatorCommand) -> CommandResult:
        with self._lock:
            before = self._phase
            result = decide(cmd, before, preflight_ok=self.preflight_ok,
                            max_tilt_rad=self.max_tilt_rad)
            if result is CommandResult.ACCEPTED:
                self._phase = next_phase(cmd, before)
            self._log.append((cmd, result))
            after = self._phase
            self._changed.notify_all()
        if after is not before and self._on_change is not None:
            self._on_change(after)
        return result

    def wait_for(self, predicate: Callable[[list[tuple[OperatorCommand, CommandResult]]], bool],
                 timeout_s: float) -> bool:
        """Block until ``predicate(submissions)`` holds or ``timeout_s`` passes (for tests
        and supervisors that wait on operator input without polling)."""
        with self._changed:
            return self._changed.wait_for(lambda: predicate(self._log), timeout_s)


@dataclass(frozen=True, slots=True)
class ParamSpec:
    """One operator-tunable parameter: name (<= 16 chars, MAVLink's limit), range, doc."""

    name: str
    value: float
    min_value: float
    max_value: float
    doc: str = ""

    def __post_init__(self) -> None:
        if not 0 < len(self.name) <= 16 or not self.name.isascii():
            raise ValueError(f"parameter name {self.name!r}: 1..16 ASCII characters")
        if not self.min_value <= self.value <= self.max_value:
            raise ValueError(f"parameter {self.name}: {self.value} outside "
                             f"[{self.min_value}, {self.max_value}]")

    def accepts(self, value: float) -> bool:
        return math.isfinite(value) and self.min_value <= value <= self.max_value


def operator_params(*, kp_pos: Vec3, kv_pos: Vec3, ki_pos: Vec3, kr_att: Vec3, kw_att: Vec3,
                    max_tilt_deg: float, max_tilt_rate_deg_s: float,
                    gain_scale_max: float = 3.0) -> tuple[ParamSpec, ...]:
    """The safe subset exposed to operators, built from the controller and tilt parameters.

    Gains are split into horizontal (x, y share one value) and vertical/yaw parts; each may be
    set between 0 and ``gain_scale_max`` times its configured value. The tilt limit may only be
    lowered, never raised above the configured (mechanical) one. Names and units:

    ``KP_POS_XY``/``KP_POS_Z`` N/m, ``KV_POS_XY``/``KV_POS_Z`` N s/m, ``KI_POS_XY``/``KI_POS_Z``
    N/(m s), ``KR_ATT_RP``/``KR_ATT_Y`` N m/rad, ``KW_ATT_RP``/``KW_ATT_Y`` N m s/rad,
    ``TILT_MAX_DEG`` deg, ``TILT_RATE_DPS`` deg/s.
    """
    def gain(name: str, value: float, doc: str) -> ParamSpec:
        return ParamSpec(name, value, 0.0, max(gain_scale_max * value, 1e-9), doc)

    return (
        gain("KP_POS_XY", kp_pos[0], "position gain K_p, x and y (N/m)"),
        gain("KP_POS_Z", kp_pos[2], "position gain K_p, z (N/m)"),
        gain("KV_POS_XY", kv_pos[0], "velocity gain K_v, x and y (N s/m)"),
        gain("KV_POS_Z", kv_pos[2], "velocity gain K_v, z (N s/m)"),
        gain("KI_POS_XY", ki_pos[0], "position integral gain K_pi, x and y (N/(m s))"),
        gain("KI_POS_Z", ki_pos[2], "position integral gain K_pi, z (N/(m s))"),
        gain("KR_ATT_RP", kr_att[0], "attitude gain K_R, roll and pitch (N m/rad)"),
        gain("KR_ATT_Y", kr_att[2], "attitude gain K_R, yaw (N m/rad)"),
        gain("KW_ATT_RP", kw_att[0], "rate gain K_w, roll and pitch (N m s/rad)"),
        gain("KW_ATT_Y", kw_att[2], "rate gain K_w, yaw (N m s/rad)"),
        ParamSpec("TILT_MAX_DEG", max_tilt_deg, 0.0, max_tilt_deg,
                  "largest tilt alpha the planner may command (deg); may only be lowered"),
        ParamSpec("TILT_RATE_DPS", max_tilt_rate_deg_s, 0.0, max_tilt_rate_deg_s,
                  "tilt rate limit (deg/s); may only be lowered"),
    )


# -- the status block a flight loop shares with its operator surfaces -------------------------
#: Layout of the shared float array (``multiprocessing.Array("d", STATUS_SIZE)``) the loop
#: writes and the telemetry process reads: the phase now, the preflight verdict, the battery
#: voltage, then every phase change as it happens: a counter and a ring of the newest
#: ``TRANSITION_RING`` (time s, new phase) pairs. A phase shorter than a reader's pass (a CUT
#: of one tick, a lockstep mission, a starved telemetry process) is still seen, in order.
STATUS_STATE, STATUS_PREFLIGHT, STATUS_BATTERY, STATUS_TRANSITIONS = 0, 1, 2, 3
TRANSITION_RING = 16
_RING0 = 4
STATUS_SIZE = _RING0 + 2 * TRANSITION_RING


def post_transition(status: Any, t_s: float, phase: int) -> None:
    """The loop's side of a phase change: the ring entry, then the phase, then the counter
    (in this order, so a reader never finds a counter ahead of its entry)."""
    n = int(status[STATUS_TRANSITIONS])
    i = _RING0 + 2 * (n % TRANSITION_RING)
    status[i] = t_s
    status[i + 1] = float(phase)
    status[STATUS_STATE] = float(phase)
    status[STATUS_TRANSITIONS] = float(n + 1)


def transitions_since(status: Any, seen: int) -> tuple[list[tuple[float, FlightPhase]], int]:
    """The reader's side: the phase changes after the first ``seen`` ones, oldest first (the
    newest ``TRANSITION_RING`` of them if more came), and the new count to pass next time."""
    n = int(status[STATUS_TRANSITIONS])
    out = []
    for k in range(max(seen, n - TRANSITION_RING), n):
        i = _RING0 + 2 * (k % TRANSITION_RING)
        try:
            out.append((float(status[i]), FlightPhase(int(status[i + 1]))))
        except ValueError:  # not a phase: skipped, never a crash of the reader
            continue
    return out, n

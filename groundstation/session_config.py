"""Flight-session files (``config/sessions/*.yaml``, schema ``fasthex.session``).

A session names the vehicle and the mission, picks the backend (real hardware with its device
URIs, or the emulated vehicle with its clock and seed), and sets the estimator, the safety limits
and the telemetry outputs. It is validated completely, including the files it refers to, before
any port is opened: :func:`load_session` reads the session, resolves the vehicle, mission and
disturbance references (a missing one is reported at the session's line of the key), validates
each file on its own, then across files: the mission against the vehicle (tilt range) and
against the geofence (every reference position inside it by :data:`GEOFENCE_MARGIN_M`), the
emulated MoCap against the session's timeouts, and an emulated session's scenario
(``backend.scenario``, :mod:`sim_backend.scenario`) against the vehicle and the mission.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Literal

from config import available, find_config
from config.schema import ConfigError, ConfigValueError, line_of, load_config, spec
from estimator.config import EstimatorConfig
from groundstation.flight import SafetyLimits

SESSION_SCHEMA = "fasthex.session"

Vec3 = tuple[float, float, float]

#: every reference position stays this far inside the geofence (m): the tracking error of a
#: gust (a few cm) must not trip the fence on a mission that touches it
GEOFENCE_MARGIN_M = 0.1
#: |x|, |y|, |z| of a geofence corner (m): the sane workspace of the missions
WORKSPACE_M = 100.0
#: the largest seed of the emulated vehicle (and of ``--seed``): numpy seeds are 32-bit
SEED_MAX = 2**32 - 1


@dataclass(frozen=True, kw_only=True)
class HardwareBackend:
    """The lab: real devices, named by URI (see the README for the URI forms)."""

    kind: Literal["hardware"]
    flight_ctrl_uri: str = spec(doc="e.g. serial:///dev/ttyUSB0?baud=500000")
    servo_uri: str = spec(doc="e.g. serial:///dev/ttyUSB1?baud=1000000&id=1")
    mocap_uri: str = spec(doc="e.g. natnet://192.168.1.10?local=192.168.1.2&body=fasthex")
    # the tk3 streams 100 Hz .. 2 kHz; the loop and its 500 Hz paper rate sit inside
    imu_rate_hz: float = spec(500.0, ge=100.0, le=2000.0)
    # the MX-28T's multi-turn Present Position range; `fasthex servo home` prints the value
    servo_zero_offset_steps: int = spec(0, ge=-28672, le=28672,
                                        doc="servo Present Position (steps) at tilt 0, as "
                                        "`fasthex servo home` prints it")

    def __post_init__(self) -> None:
        for key in ("flight_ctrl_uri", "servo_uri", "mocap_uri"):
            if "://" not in getattr(self, key):
                raise ConfigValueError(key, "expected a device URI (SCHEME://...), got "
                                       f"{getattr(self, key)!r}")
        # each driver's own URI parser, which opens nothing: a malformed URI is an error at
        # its line before any device opens, not a traceback halfway through start-up
        from drivers.dynamixel.device import parse_servo_uri
        from drivers.errors import TransportUriError
        from drivers.mocap.uri import MocapUriError, parse_uri
        from drivers.transport import check_transport_uri

        checks: tuple[tuple[str, Callable[[str], object]], ...] = (
            ("flight_ctrl_uri", check_transport_uri), ("servo_uri", parse_servo_uri),
            ("mocap_uri", parse_uri))
        for key, check in checks:
            try:
                check(getattr(self, key))
            except TransportUriError as exc:
                raise ConfigValueError(key, str(exc)) from None
            except MocapUriError as exc:
                raise ConfigValueError(key, str(exc)) from None


@dataclass(frozen=True, kw_only=True)
class EmulatedBackend:
    """The emulated vehicle in a child process, reached through ptys and UDP loopback."""

    kind: Literal["emulated"]
    clock: Literal["realtime", "lockstep"] = spec("lockstep")
    seed: int = spec(1, ge=0, le=SEED_MAX, doc="numpy seeds are 32-bit")
    disturbances: str = spec("paper-calibrated", doc="simulator preset (disturbances, sensor "
                             "noise, MoCap rate and latency): name or file")
    imu_rate_hz: float = spec(500.0, ge=100.0, le=2000.0, doc="IMU stream rate requested")
    faults: tuple[str, ...] = spec((), doc="faults to rehearse, KIND@T[:VALUE], T in simulated "
                                   "seconds: mocap-dropout:S, fc-disconnect, servo-silent, "
                                   "battery-sag:V, tilt-kick:DEG_S, imu-rate:FRACTION, "
                                   "imu-gap:S, mocap-jump:M, rotor-thrust:SCALE[:ROTOR], "
                                   "mocap-freeze, mocap-latency:S")
    corrupt_prob: float = spec(0.0, ge=0.0, le=0.1,
                               doc="byte corruption probability on the Flight-Ctrl link")
    # clock errors to rehearse the time base on (realtime; lockstep: see the emulator)
    board_clock_ppm: float = spec(0.0, ge=-50_000.0, le=50_000.0,
                                  doc="rate error of the board's sample clock (-12000: 1.2 % "
                                  "slow)")
    mocap_clock_offset_s: float = spec(0.0, ge=0.0, le=1e6,
                                       doc="the MoCap server's clock minus the emulator's")
    mocap_clock_ppm: float = spec(0.0, ge=-50_000.0, le=50_000.0,
                                  doc="rate error of the MoCap server's clock")
    mocap: Literal["natnet", "qtm"] = spec("natnet", doc="emulated MoCap server: natnet "
                                           "(Motive, UDP) or qtm (Qualisys QTM RT, TCP)")
    scenario: str = spec("", doc="scenario (plant overrides, scheduled disturbances and faults "
                         "in mission seconds): name or file; empty: none")

    def __post_init__(self) -> None:
        from sim_backend.faults import ScheduledFault

        for i, text in enumerate(self.faults):
            try:
                ScheduledFault.parse(text)
            except ValueError as exc:
                raise ConfigValueError(f"faults[{i}]", str(exc)) from None


@dataclass(frozen=True, kw_only=True)
class SafetyConfig:
    geofence_min_m: Vec3 = spec((-3.0, -3.0, -0.5), ge=-WORKSPACE_M, le=WORKSPACE_M)
    geofence_max_m: Vec3 = spec((3.0, 3.0, 3.0), ge=-WORKSPACE_M, le=WORKSPACE_M)
    # below 5 deg the paper's own 6 deg roll sine would trip it
    max_body_tilt_deg: float = spec(45.0, ge=5.0, le=90.0)
    # two frames of a 100 Hz MoCap at least; beyond 10 s the vehicle drifts metres blind
    mocap_timeout_s: float = spec(1.0, ge=0.02, le=10.0, doc="MoCap lost this long -> land")
    # >= 2 IMU periods (checked against the backend's rate); > 1 s is far past the board's
    # own watchdog
    imu_timeout_s: float = spec(0.05, ge=1e-3, le=1.0, doc="IMU silent this long -> motors stop")
    # 0 switches the check off (emulated); 60 V is a 14S pack, above any lab multirotor's
    min_battery_v: float = spec(13.2, ge=0.0, le=60.0)
    failsafe_action: Literal["land", "cut"] = spec("land")
    servo_fault_action: Literal["hold", "land"] = spec("hold")
    spin_up_s: float = spec(1.0, ge=0.0, le=10.0, doc="idle spin before takeoff")
    # the shipped take-offs leave the ground within ~1 s; 0.5 s is too short for a rotor
    # spin-up on a heavy vehicle, beyond 30 s the integrators have wound up on the ground
    liftoff_timeout_s: float = spec(5.0, ge=0.5, le=30.0, doc="take-off without lift-off "
                                    "this long -> abort, idle, disarm")
    takeoff_settle_timeout_s: float = spec(10.0, ge=1.0, le=60.0, doc="planned take-off "
                                           "over, take-off height not reached this long -> land")
    # a battery lasts minutes; a day is a typo. Past it: land on the estimate, and a landing
    # without touchdown TIME_LIMIT_CUT_S later is cut
    session_time_limit_s: float = spec(3600.0, ge=10.0, le=86400.0, doc="session time from "
                                       "the first IMU sample (preflight included) -> land")

    def __post_init__(self) -> None:
        for axis, (lo, hi) in enumerate(zip(self.geofence_min_m, self.geofence_max_m,
                                            strict=True)):
            if lo >= hi:
                raise ConfigValueError(f"geofence_min_m[{axis}]",
                                       f"must be below geofence_max_m[{axis}] ({hi:g} m)")
            # the fence must hold the vehicle plus the margin on both sides
            if hi - lo < 0.5:
                raise ConfigValueError(f"geofence_max_m[{axis}]",
                                       f"a fence {hi - lo:g} m wide leaves no room to fly; "
                                       "expected >= 0.5 m")

    def limits(self) -> SafetyLimits:
        return SafetyLimits(
            geofence_min_m=self.geofence_min_m, geofence_max_m=self.geofence_max_m,
            max_body_tilt_deg=self.max_body_tilt_deg, mocap_timeout_s=self.mocap_timeout_s,
            imu_timeout_s=self.imu_timeout_s, min_battery_v=self.min_battery_v,
            failsafe_action=self.failsafe_action, servo_fault_action=self.servo_fault_action,
            spin_up_s=self.spin_up_s, liftoff_timeout_s=self.liftoff_timeout_s,
            takeoff_settle_timeout_s=self.takeoff_settle_timeout_s,
        )


#: the placeholders ``telemetry.record`` may hold (``fly``'s record_path replaces them)
RECORD_PLACEHOLDERS = ("session", "time")


@dataclass(frozen=True, kw_only=True)
class TelemetryConfig:
    record: str = spec("", doc="flight-record path, relative to the session file; {session} "
                       "and {time} are replaced; empty: flights/<session>-<time>.fhr under "
                       "the working directory; fly --record overrides it")
    rerun: Literal["off", "save", "serve", "spawn", "auto"] = spec(
        "auto", doc="auto: spawn a viewer when a display exists, else none (save writes "
        "RECORD.rrd; fasthex replay makes one later)")
    mavlink: str = spec("", doc="MAVLink endpoint URI, e.g. udpout:127.0.0.1:14550; empty: off")
    # MAVLink signing: a key FILE (never the key itself); see groundstation.gcs for precedence
    mavlink_key_file: str | None = spec(None, doc="file holding the MAVLink signing key (64 hex "
                                        "digits or a passphrase); --mavlink-key-file and "
                                        "$FASTHEX_MAVLINK_KEY are the other sources")
    mavlink_allow_unsigned: bool = spec(False, doc="without a key, accept flight-changing "
                                        "MAVLink commands anyway (a warning says so)")

    def __post_init__(self) -> None:
        for name in re.findall(r"\{([^{}]*)\}", self.record):
            if name not in RECORD_PLACEHOLDERS:  # it would stay in the file name as written
                known = " and ".join(f"{{{p}}}" for p in RECORD_PLACEHOLDERS)
                raise ConfigValueError("record", f"unknown placeholder {{{name}}}; expected "
                                       f"{known}")
        if self.mavlink:  # the link's own parser: a bad URI must not wait for the flight
            from drivers.errors import TransportUriError
            from drivers.mavlink.link import parse_mavlink_uri

            try:
                parse_mavlink_uri(self.mavlink)
            except TransportUriError as exc:
                raise ConfigValueError("mavlink", f"{self.mavlink}: {exc.message}") from None


@dataclass(frozen=True, kw_only=True)
class SessionConfig:
    name: str
    description: str = spec("")
    vehicle: str = spec("fasthex", doc="vehicle name or file")
    mission: str = spec(doc="mission name or file")
    backend: HardwareBackend | EmulatedBackend = spec()
    estimator: EstimatorConfig = field(default_factory=EstimatorConfig)
    safety: SafetyConfig = field(default_factory=SafetyConfig)
    telemetry: TelemetryConfig = field(default_factory=TelemetryConfig)

    def __post_init__(self) -> None:
        rate_hz = self.backend.imu_rate_hz
        if self.safety.imu_timeout_s < 2.0 / rate_hz:
            raise ConfigValueError(
                "safety.imu_timeout_s", f"expected >= two IMU periods at {rate_hz:g} Hz "
                f"({2.0 / rate_hz:g} s), got {self.safety.imu_timeout_s:g}")


def load_session(name_or_path: str | Path) -> SessionConfig:
    """A shipped session by name or a session file, with every file it refers to, validated
    on its own and across files (module docstring). Errors name the file and line at fault:
    a missing reference the session's line, a broken referenced file its own line.

    The vehicle, and a disturbance preset or a scenario given as a file, are returned resolved
    against the session file (as the mission is), so that the emulator, another process, reads
    the file that was validated.
    """
    from groundstation.configs import (
        check_mission_against_vehicle,
        load_disturbances,
        load_mission,
        load_vehicle,
    )

    path = find_config("sessions", name_or_path)
    lines: dict[str, int] = {}
    session = load_config(path, SessionConfig, schema=SESSION_SCHEMA, versions=(1,), lines=lines)
    vehicle_path = _reference(path, lines, "vehicle", "vehicles", session.vehicle)
    mission_path = _reference(path, lines, "mission", "missions", session.mission)
    params = load_vehicle(vehicle_path)
    # the emulator (another process, whatever its working directory) flies the file that was
    # validated here: a relative file name meant the session's folder to this loader only
    session = replace(session, vehicle=str(vehicle_path))
    mission_lines: dict[str, int] = {}
    mission = load_mission(mission_path, lines=mission_lines)
    check_mission_against_vehicle(mission, params, str(mission_path), mission_lines)
    _check_geofence(mission, session.safety, str(mission_path), mission_lines, path, lines)
    _check_time_limit(mission, session.safety, path, lines)
    backend = session.backend
    if isinstance(backend, HardwareBackend):
        _check_servo_zero(backend, params.tilt.max_tilt_deg, params.tilt.worm_ratio, path, lines)
    if isinstance(backend, EmulatedBackend):
        preset_path = _reference(path, lines, "backend.disturbances", "disturbances",
                                 backend.disturbances)
        preset = load_disturbances(preset_path)
        _check_emulated_mocap(preset, session, str(preset_path), path, lines)
        if Path(backend.disturbances).suffix in (".yaml", ".yml"):
            session = replace(session, backend=replace(backend, disturbances=str(preset_path)))
        if backend.scenario:
            from controller.missions import Mission
            from groundstation.configs import load_scenario

            scenario_path = _reference(path, lines, "backend.scenario", "scenarios",
                                       backend.scenario)
            load_scenario(scenario_path, vehicle=params,
                          mission_duration_s=Mission(mission).duration_s)
            # the emulator reads the file validated here, whatever its working directory
            emulated = session.backend
            assert isinstance(emulated, EmulatedBackend)
            session = replace(session, backend=replace(emulated, scenario=str(scenario_path)))
    key_file = session.telemetry.mavlink_key_file
    if key_file:  # relative to the session file, like its other references; it must exist
        key_path = Path(key_file).expanduser()
        if not key_path.is_absolute():
            key_path = path.parent / key_path
        if not key_path.is_file():
            raise ConfigError(str(path), line_of(lines, "telemetry.mavlink_key_file"),
                              "telemetry.mavlink_key_file",
                              f"no such key file {key_file!r} (relative to the session file)")
        session = replace(session, telemetry=replace(session.telemetry,
                                                     mavlink_key_file=str(key_path)))
    return session


def _reference(session_path: Path, lines: dict[str, int], key: str, kind: str, ref: str) -> Path:
    """The file a session's reference names; a missing one is the session's error."""
    try:
        return find_config(kind, resolve_reference(session_path, ref))
    except ConfigError:
        pass
    line = line_of(lines, key)
    if Path(ref).suffix in (".yaml", ".yml") or "/" in ref:
        message = f"no such file {ref!r} (relative to the session file)"
    else:
        message = (f"no such {kind[:-1]} {ref!r} (shipped: "
                   f"{', '.join(available(kind)) or 'none'})")
    raise ConfigError(str(session_path), line, key, message) from None


def _check_time_limit(mission: object, safety: SafetyConfig, path: Path,
                      lines: dict[str, int]) -> None:
    """The session time limit leaves room for the whole mission after the shortest preflight
    (1 s) and the spin-up: otherwise every flight would end in the limit's failsafe."""
    from controller.missions import Mission, MissionSpec

    assert isinstance(mission, MissionSpec)
    start_s = 1.0 + safety.spin_up_s
    need_s = start_s + Mission(mission).duration_s
    if safety.session_time_limit_s < need_s:
        key = "safety.session_time_limit_s"
        raise ConfigError(str(path), line_of(lines, key), key,
                          f"{safety.session_time_limit_s:g} s ends the session before its "
                          f"mission ({Mission(mission).duration_s:g} s after {start_s:g} s of "
                          f"preflight and spin-up): expected >= {need_s:g} s")


def _check_geofence(mission: object, safety: SafetyConfig, mission_file: str,
                    mission_lines: dict[str, int], session_path: Path,
                    session_lines: dict[str, int]) -> None:
    """Every reference position of the mission inside the geofence, less the margin."""
    fence = (f"the geofence of {session_path} (line "
             f"{line_of(session_lines, 'safety.geofence_min_m')})")
    check_mission_in_box(mission, safety.geofence_min_m, safety.geofence_max_m, fence,
                         mission_file, mission_lines)


def check_mission_in_box(mission: object, box_min_m: Vec3, box_max_m: Vec3, box: str,
                         mission_file: str, mission_lines: dict[str, int]) -> None:
    """Every reference position of the mission inside the box (``box`` names it), less
    GEOFENCE_MARGIN_M: a ConfigError at the mission's line otherwise."""
    from controller.missions import MissionSpec, segment_extents_w_m

    assert isinstance(mission, MissionSpec)
    lo_fence = tuple(v + GEOFENCE_MARGIN_M for v in box_min_m)
    hi_fence = tuple(v - GEOFENCE_MARGIN_M for v in box_max_m)
    fence = f"{box} less {GEOFENCE_MARGIN_M:g} m"
    checks: list[tuple[str, Vec3, Vec3]] = [
        ("start_pos_w_m", mission.start_pos_w_m, mission.start_pos_w_m)]
    for i, (seg, (lo, hi)) in enumerate(zip(mission.segments, segment_extents_w_m(mission),
                                            strict=True)):
        field_name = {"takeoff": "height_m", "sine": "amplitude_m", "land": "sink_m"}.get(
            seg.kind, "pos_w_m")
        checks.append((f"segments[{i}].{field_name}", lo, hi))
    for key, lo, hi in checks:
        for axis in range(3):
            if lo[axis] < lo_fence[axis] or hi[axis] > hi_fence[axis]:
                value = lo[axis] if lo[axis] < lo_fence[axis] else hi[axis]
                raise ConfigError(
                    mission_file, line_of(mission_lines, key), key,
                    f"reaches {'xyz'[axis]} = {value:g} m, outside {fence} "
                    f"({lo_fence[axis]:g}..{hi_fence[axis]:g} m)")


def _check_servo_zero(backend: HardwareBackend, max_tilt_deg: float, gear_ratio: float,
                      session_path: Path, lines: dict[str, int]) -> None:
    """The whole tilt range, from the zero offset up, must lie in the servo's multi-turn range."""
    from drivers.dynamixel.device import tilt_range_problem

    problem = tilt_range_problem(backend.servo_zero_offset_steps, max_tilt_deg, gear_ratio)
    if problem:
        key = "backend.servo_zero_offset_steps"
        raise ConfigError(str(session_path), line_of(lines, key), key, problem)


def _check_emulated_mocap(preset: object, session: SessionConfig, preset_file: str,
                          session_path: Path, lines: dict[str, int]) -> None:
    """The emulated MoCap must be able to keep the session's timeouts quiet."""
    from sim_backend.disturbances import DisturbancePreset

    assert isinstance(preset, DisturbancePreset)
    period_s = 1.0 / preset.mocap_rate_hz
    for key, timeout_s in (("safety.mocap_timeout_s", session.safety.mocap_timeout_s),
                           ("estimator.mocap_stale_s", session.estimator.mocap_stale_s)):
        if period_s >= timeout_s:
            raise ConfigError(
                str(session_path), line_of(lines, key), key,
                f"{timeout_s:g} s is within one frame of the emulated MoCap "
                f"({preset.mocap_rate_hz:g} Hz in {preset_file}); expected > {period_s:g} s")
    if preset.mocap_latency_s >= session.estimator.history_s:
        raise ConfigError(
            str(session_path), line_of(lines, "estimator.history_s"), "estimator.history_s",
            f"{session.estimator.history_s:g} s cannot fuse poses {preset.mocap_latency_s:g} s "
            f"late (mocap_latency_s in {preset_file}); expected more")


def resolve_reference(session_path: Path, ref: str) -> str | Path:
    """A file reference in a session is relative to the session file; a bare name is shipped."""
    if ref.endswith((".yaml", ".yml")) and not Path(ref).is_absolute():
        return session_path.parent / ref
    return ref

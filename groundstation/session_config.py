"""Flight-session files (``config/sessions/*.yaml``, schema ``fasthex.session``).

A session names the vehicle and the mission, picks the backend (real hardware with its device
URIs, or the emulated vehicle with its clock and seed), and sets the estimator, the safety limits
and the telemetry outputs. It is validated completely, including the files it refers to, before
any port is opened.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from config import find_config
from config.schema import ConfigValueError, load_config, spec
from estimator.config import EstimatorConfig
from groundstation.flight import SafetyLimits

SESSION_SCHEMA = "fasthex.session"

Vec3 = tuple[float, float, float]


@dataclass(frozen=True, kw_only=True)
class HardwareBackend:
    """The lab: real devices, named by URI (see the README for the URI forms)."""

    kind: Literal["hardware"]
    flight_ctrl_uri: str = spec(doc="e.g. serial:///dev/ttyUSB0?baud=500000")
    servo_uri: str = spec(doc="e.g. serial:///dev/ttyUSB1?baud=1000000&id=1")
    mocap_uri: str = spec(doc="e.g. natnet://192.168.1.10?local=192.168.1.2&body=fasthex")
    imu_rate_hz: float = spec(500.0, ge=100.0, le=2000.0)


@dataclass(frozen=True, kw_only=True)
class EmulatedBackend:
    """The emulated vehicle in a child process, reached through ptys and UDP loopback."""

    kind: Literal["emulated"]
    clock: Literal["realtime", "lockstep"] = spec("lockstep")
    seed: int = spec(1, ge=0)
    disturbances: str = spec("paper-calibrated", doc="simulator preset (disturbances, sensor "
                             "noise, MoCap rate and latency): name or file")
    imu_rate_hz: float = spec(500.0, ge=100.0, le=2000.0, doc="IMU stream rate requested")
    faults: tuple[str, ...] = spec((), doc="faults to rehearse, KIND@T[:DURATION] in simulated "
                                   "seconds: mocap-dropout, fc-disconnect, servo-silent")
    corrupt_prob: float = spec(0.0, ge=0.0, le=0.1,
                               doc="byte corruption probability on the Flight-Ctrl link")

    def __post_init__(self) -> None:
        from sim_backend.backend import ScheduledFault

        for i, text in enumerate(self.faults):
            try:
                ScheduledFault.parse(text)
            except ValueError as exc:
                raise ConfigValueError(f"faults[{i}]", str(exc)) from None


@dataclass(frozen=True, kw_only=True)
class SafetyConfig:
    geofence_min_m: Vec3 = spec((-3.0, -3.0, -0.5))
    geofence_max_m: Vec3 = spec((3.0, 3.0, 3.0))
    max_body_tilt_deg: float = spec(45.0, gt=0.0, le=90.0)
    mocap_timeout_s: float = spec(1.0, gt=0.0, le=10.0, doc="MoCap lost this long -> land")
    imu_timeout_s: float = spec(0.05, gt=0.0, le=1.0, doc="IMU silent this long -> motors stop")
    min_battery_v: float = spec(13.2, ge=0.0, le=60.0)
    failsafe_action: Literal["land", "cut"] = spec("land")
    servo_fault_action: Literal["hold", "land"] = spec("hold")
    spin_up_s: float = spec(1.0, ge=0.0, le=10.0, doc="idle spin before takeoff")

    def __post_init__(self) -> None:
        for axis, (lo, hi) in enumerate(zip(self.geofence_min_m, self.geofence_max_m,
                                            strict=True)):
            if lo >= hi:
                raise ConfigValueError(f"geofence_min_m[{axis}]",
                                       f"must be below geofence_max_m[{axis}] ({hi:g} m)")

    def limits(self) -> SafetyLimits:
        return SafetyLimits(
            geofence_min_m=self.geofence_min_m, geofence_max_m=self.geofence_max_m,
            max_body_tilt_deg=self.max_body_tilt_deg, mocap_timeout_s=self.mocap_timeout_s,
            imu_timeout_s=self.imu_timeout_s, min_battery_v=self.min_battery_v,
            failsafe_action=self.failsafe_action, servo_fault_action=self.servo_fault_action,
            spin_up_s=self.spin_up_s,
        )


@dataclass(frozen=True, kw_only=True)
class TelemetryConfig:
    record: str = spec("", doc="flight-record path; empty: flights/<session>-<time>.fhr")
    rerun: Literal["off", "save", "serve", "spawn", "auto"] = spec(
        "auto", doc="auto: spawn a viewer when a display exists, else save a .rrd")
    mavlink: str = spec("", doc="MAVLink endpoint URI, e.g. udpout:127.0.0.1:14550; empty: off")


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


def load_session(name_or_path: str | Path) -> SessionConfig:
    """A shipped session by name or a session file; the vehicle and mission it names are
    resolved and validated too (their errors name their own files)."""
    from groundstation.configs import load_mission, load_vehicle

    path = find_config("sessions", name_or_path)
    session = load_config(path, SessionConfig, schema=SESSION_SCHEMA, versions=(1,))
    load_vehicle(resolve_reference(path, session.vehicle))
    load_mission(resolve_reference(path, session.mission))
    return session


def resolve_reference(session_path: Path, ref: str) -> str | Path:
    """A file reference in a session is relative to the session file; a bare name is shipped."""
    if ref.endswith((".yaml", ".yml")) and not Path(ref).is_absolute():
        return session_path.parent / ref
    return ref

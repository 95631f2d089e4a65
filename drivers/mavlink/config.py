"""The MAVLink link's settings: endpoint, ids, telemetry rates, signing key source.

Pure data (a YAML ``mavlink:`` block, validated by :mod:`config.schema`). No key material: the
key itself comes from a file or an environment variable (:mod:`drivers.mavlink.signing`).
"""

from __future__ import annotations

from dataclasses import dataclass

from config.schema import ConfigValueError, spec
from drivers.mavlink.link import parse_mavlink_uri


@dataclass(frozen=True)
class MavlinkConfig:
    """The bridge's settings (a session YAML's ``mavlink:`` block). No key material here."""

    uri: str = spec("udpout:127.0.0.1:14550", doc="udpout:HOST:PORT or udpin:HOST:PORT")
    sysid: int = spec(1, ge=1, le=255, doc="our MAVLink system id")
    compid: int = spec(1, ge=1, le=255, doc="our component id (1 = autopilot)")
    heartbeat_hz: float = spec(1.0, ge=0.0, le=50.0, doc="HEARTBEAT rate")
    sys_status_hz: float = spec(2.0, ge=0.0, le=50.0, doc="SYS_STATUS rate")
    extended_sys_state_hz: float = spec(1.0, ge=0.0, le=50.0,
                                        doc="EXTENDED_SYS_STATE (landed state) rate")
    attitude_hz: float = spec(50.0, ge=0.0, le=500.0, doc="ATTITUDE rate")
    attitude_quaternion_hz: float = spec(50.0, ge=0.0, le=500.0, doc="ATTITUDE_QUATERNION rate")
    local_position_hz: float = spec(20.0, ge=0.0, le=500.0, doc="LOCAL_POSITION_NED rate")
    odometry_hz: float = spec(20.0, ge=0.0, le=500.0, doc="ODOMETRY rate")
    actuator_output_hz: float = spec(10.0, ge=0.0, le=500.0, doc="ACTUATOR_OUTPUT_STATUS rate")
    signing: bool = spec(False, doc="require signed commands and sign telemetry")
    key_file: str | None = spec(None, doc="file holding the key (hex or passphrase)")
    key_env: str = spec("FASTHEX_MAVLINK_KEY", doc="environment variable holding the key")
    link_id: int = spec(0, ge=0, le=255, doc="signing link id of our outgoing stream")
    allow_unsigned_ids: tuple[int, ...] = spec((109, 166), ge=0,
                                               doc="message ids accepted unsigned")
    gcs_timeout_s: float = spec(3.0, gt=0.0, doc="GCS heartbeat age counted as link lost")
    mocap_latency_s: float = spec(0.0, ge=0.0, le=1.0, doc="assumed age of MAVLink MoCap poses")

    def __post_init__(self) -> None:
        try:
            parse_mavlink_uri(self.uri)
        except ValueError as exc:
            raise ConfigValueError("uri", str(exc)) from None

    def rates_hz(self) -> dict[str, float]:
        return {
            "HEARTBEAT": self.heartbeat_hz,
            "SYS_STATUS": self.sys_status_hz,
            "EXTENDED_SYS_STATE": self.extended_sys_state_hz,
            "ATTITUDE": self.attitude_hz,
            "ATTITUDE_QUATERNION": self.attitude_quaternion_hz,
            "LOCAL_POSITION_NED": self.local_position_hz,
            "ODOMETRY": self.odometry_hz,
            "ACTUATOR_OUTPUT_STATUS": self.actuator_output_hz,
        }

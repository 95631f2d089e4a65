"""Telemetry snapshot -> MAVLink messages, decoded back by an independent pymavlink parser."""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import pytest
from pymavlink.dialects.v20 import common as mavlink2

from drivers.errors import TransportUriError
from drivers.mavlink.frames import q_from_euler
from drivers.mavlink.link import MavlinkCodec, parse_mavlink_uri
from groundstation import mavlink_messages as messages
from groundstation.operator import (
    FlightPhase,
    SensorHealth,
    Severity,
    StatusEvent,
    VehicleTelemetry,
)

M = mavlink2
ROLL, PITCH, YAW = math.radians(5.0), math.radians(-3.0), math.radians(30.0)
TEL = VehicleTelemetry(
    t_s=12.345, phase=FlightPhase.MISSION, armed=True, pos_w_m=(0.5, -0.2, 1.0),
    vel_w_m_s=(0.1, 0.2, -0.3), q_wb=q_from_euler(ROLL, PITCH, YAW),
    omega_b_rad_s=(0.01, 0.02, 0.03), rotor_speeds_hz=(60.0, 61.0, 62.0, 63.0, 64.0, 65.0),
    tilt_rad=math.radians(20.0), battery_v=15.7,
    health=SensorHealth(mocap_ok=False, preflight_ok=True))


def _roundtrip(msg: Any) -> Any:
    frame = MavlinkCodec(1, 1).encode(msg)
    out = MavlinkCodec(255, 190).decode(frame)
    assert len(out) == 1
    return out[0]


def test_that_the_heartbeat_says_hexarotor_armed_and_the_phase() -> None:
    hb = _roundtrip(messages.heartbeat(TEL))
    assert hb.type == M.MAV_TYPE_HEXAROTOR
    assert hb.base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED
    assert hb.custom_mode == FlightPhase.MISSION
    assert hb.system_status == M.MAV_STATE_ACTIVE
    boot = _roundtrip(messages.heartbeat(None))
    assert not boot.base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED
    assert boot.system_status == M.MAV_STATE_BOOT


def test_that_attitude_is_reported_in_ned_with_frd_rates() -> None:
    att = _roundtrip(messages.attitude(TEL))
    assert att.time_boot_ms == 12345
    assert math.isclose(att.roll, ROLL, abs_tol=1e-6)
    assert math.isclose(att.pitch, -PITCH, abs_tol=1e-6)
    assert math.isclose(att.yaw, -YAW, abs_tol=1e-6)
    assert (att.rollspeed, att.pitchspeed, att.yawspeed) == pytest.approx((0.01, -0.02, -0.03))
    aq = _roundtrip(messages.attitude_quaternion(TEL))
    w, x, y, z = TEL.q_wb
    assert (aq.q1, aq.q2, aq.q3, aq.q4) == pytest.approx((w, x, -y, -z), abs=1e-6)


def test_that_positions_and_velocities_are_ned_and_odometry_velocity_is_body_frd() -> None:
    lp = _roundtrip(messages.local_position_ned(TEL))
    assert (lp.x, lp.y, lp.z) == pytest.approx((0.5, 0.2, -1.0))
    assert (lp.vx, lp.vy, lp.vz) == pytest.approx((0.1, -0.2, 0.3))
    od = _roundtrip(messages.odometry(TEL))
    assert (od.frame_id, od.child_frame_id) == (18, M.MAV_FRAME_BODY_NED)  # ESTIM_NED
    assert od.time_usec == 12_345_000
    # |v| is frame independent; the body-frame velocity rotated back gives the NED one
    assert math.hypot(od.vx, od.vy, od.vz) == pytest.approx(math.hypot(0.1, 0.2, 0.3), rel=1e-5)
    assert math.isnan(od.pose_covariance[0])


def test_that_actuator_status_carries_six_spin_rates_and_the_tilt() -> None:
    ao = _roundtrip(messages.actuator_output_status(TEL))
    assert ao.active == 0x7F
    assert ao.actuator[:6] == pytest.approx([60.0, 61.0, 62.0, 63.0, 64.0, 65.0])
    assert ao.actuator[6] == pytest.approx(math.radians(20.0), rel=1e-6)


def test_that_sys_status_reports_battery_millivolts_and_unhealthy_mocap() -> None:
    ss = _roundtrip(messages.sys_status(TEL))
    assert ss.voltage_battery == 15700
    vision = M.MAV_SYS_STATUS_SENSOR_VISION_POSITION
    assert ss.onboard_control_sensors_present & vision
    assert not ss.onboard_control_sensors_health & vision
    assert ss.onboard_control_sensors_health & M.MAV_SYS_STATUS_SENSOR_3D_GYRO
    unknown = _roundtrip(messages.sys_status(dataclasses.replace(TEL, battery_v=math.nan)))
    assert unknown.voltage_battery == 0xFFFF


def test_that_a_long_status_text_is_split_into_chunks_sharing_an_id() -> None:
    text = "MoCap lost for 3.0 s: landing on the estimate (failsafe land, reason mocap_timeout)"
    msgs = [_roundtrip(m) for m in messages.statustext(StatusEvent(1.0, text, Severity.CRITICAL),
                                                       chunk_id=7)]
    assert len(msgs) == 2
    assert {m.id for m in msgs} == {7} and [m.chunk_seq for m in msgs] == [0, 1]
    assert "".join(m.text for m in msgs) == text
    assert all(m.severity == M.MAV_SEVERITY_CRITICAL for m in msgs)
    short = _roundtrip(messages.statustext(StatusEvent(1.0, "ARMED -> TAKEOFF"), chunk_id=8)[0])
    assert (short.text, short.id) == ("ARMED -> TAKEOFF", 0)


def test_that_a_malformed_link_uri_says_what_is_expected() -> None:
    assert str(parse_mavlink_uri("udpout:127.0.0.1:14550")) == "udpout:127.0.0.1:14550"
    for bad in ("udp:127.0.0.1:14550", "udpout:127.0.0.1", "udpin:host:port", "udpout:h:0"):
        with pytest.raises(TransportUriError, match="udpout:HOST:PORT"):
            parse_mavlink_uri(bad)

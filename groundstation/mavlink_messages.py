"""Telemetry snapshots -> MAVLink messages. Pure: builds pymavlink message objects, no I/O.

A ground-station module (it knows the flight phases); the wire layer is :mod:`drivers.mavlink`.

What each message carries (frames: :mod:`drivers.mavlink.frames`; world x = north):

HEARTBEAT
    ``type`` MAV_TYPE_HEXAROTOR, ``autopilot`` MAV_AUTOPILOT_GENERIC, ``base_mode``
    CUSTOM_MODE_ENABLED | SAFETY_ARMED when armed, ``custom_mode`` = the flight phase
    (:class:`groundstation.operator.FlightPhase` value), ``system_status`` STANDBY when disarmed,
    ACTIVE when armed, CRITICAL while landing with a fault, EMERGENCY after an emergency stop.
SYS_STATUS
    battery voltage (mV; UINT16_MAX when unknown), and per sensor present/enabled/health bits:
    IMU -> 3D_GYRO | 3D_ACCEL, MoCap -> VISION_POSITION, UKF -> AHRS, BL-Ctrls ->
    MOTOR_OUTPUTS, tilt servo -> PROPULSION, battery -> BATTERY, geofence -> GEOFENCE,
    preflight -> PREARM_CHECK.
EXTENDED_SYS_STATE
    ``landed_state`` from the phase (:func:`landed_state`): PREFLIGHT, ARMED, DISARMED and CUT
    ON_GROUND, TAKEOFF TAKEOFF, MISSION IN_AIR, LANDING LANDING; ``vtol_state`` UNDEFINED.
ATTITUDE / ATTITUDE_QUATERNION
    body FRD -> NED attitude; roll/pitch/yaw (ZYX) and the quaternion; body rates in FRD.
LOCAL_POSITION_NED
    position and velocity in NED (m, m/s).
ODOMETRY
    ``frame_id`` ESTIM_NED (an estimate's local NED frame; world x taken as north),
    ``child_frame_id`` BODY_NED (for velocities MAVLink defines it as body FRD). These two are
    what MAVSDK maps: its ``Telemetry.Odometry.MavFrame`` knows UNDEF, BODY_NED, VISION_NED
    and ESTIM_NED only, and reports the newer LOCAL_FRD / LOCAL_NED / BODY_FRD as UNDEF
    (checked with MAVSDK 4.1.0). Position, attitude quaternion,
    velocity expressed in body FRD (the child frame, as MAVLink defines it), body rates;
    covariances unknown (first element NaN); ``estimator_type`` VIO-less MOCAP.
ACTUATOR_OUTPUT_STATUS
    ``actuator[0..5]`` the six measured rotor spin rates in Hz (propeller order of the paper),
    ``actuator[6]`` the measured tilt alpha in rad; ``active`` = 0x7F.
STATUSTEXT
    one per event; texts longer than 50 characters go out in chunks sharing one ``id``.
"""

from __future__ import annotations

import math
from typing import Any

from pymavlink.dialects.v20 import common as mavlink2

from drivers.mavlink.frames import (
    flu_to_frd,
    q_to_euler,
    q_world_to_ned,
    rotate_inverse,
    world_to_ned,
)
from groundstation.operator import FlightPhase, SensorHealth, StatusEvent, VehicleTelemetry

M = mavlink2
STATUSTEXT_LEN = 50
#: MAV_FRAME 18, ESTIM_NED: deprecated in MAVLink (pymavlink's common calls it RESERVED_18), yet
#: the only estimator frame MAVSDK's odometry maps (see ODOMETRY above)
MAV_FRAME_ESTIM_NED = 18
UINT16_MAX = 0xFFFF

SENSOR_BITS: tuple[tuple[str, int], ...] = (
    ("imu_ok", M.MAV_SYS_STATUS_SENSOR_3D_GYRO | M.MAV_SYS_STATUS_SENSOR_3D_ACCEL),
    ("mocap_ok", M.MAV_SYS_STATUS_SENSOR_VISION_POSITION),
    ("estimator_ok", M.MAV_SYS_STATUS_AHRS),
    ("motors_ok", M.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS),
    ("servo_ok", M.MAV_SYS_STATUS_SENSOR_PROPULSION),
    ("battery_ok", M.MAV_SYS_STATUS_SENSOR_BATTERY),
    ("geofence_ok", M.MAV_SYS_STATUS_GEOFENCE),
    ("preflight_ok", M.MAV_SYS_STATUS_PREARM_CHECK),
)
SENSORS_PRESENT = 0
for _name, _bits in SENSOR_BITS:
    SENSORS_PRESENT |= _bits


def time_boot_ms(tel: VehicleTelemetry) -> int:
    return max(0, round(tel.t_s * 1000.0)) & 0xFFFFFFFF


def time_usec(tel: VehicleTelemetry) -> int:
    return max(0, round(tel.t_s * 1e6))


def health_bits(health: SensorHealth) -> int:
    bits = 0
    for name, b in SENSOR_BITS:
        if getattr(health, name):
            bits |= b
    return bits


def system_status(tel: VehicleTelemetry) -> int:
    if tel.phase is FlightPhase.CUT:
        return int(M.MAV_STATE_EMERGENCY)
    if not tel.armed:
        return int(M.MAV_STATE_STANDBY)
    h = tel.health
    if tel.phase is FlightPhase.LANDING and not (h.imu_ok and h.mocap_ok and h.estimator_ok
                                                  and h.motors_ok and h.battery_ok
                                                  and h.geofence_ok):
        return int(M.MAV_STATE_CRITICAL)
    return int(M.MAV_STATE_ACTIVE)


def heartbeat(tel: VehicleTelemetry | None) -> Any:
    """HEARTBEAT; before the first snapshot the vehicle says BOOT, disarmed, PREFLIGHT."""
    if tel is None:
        return M.MAVLink_heartbeat_message(
            M.MAV_TYPE_HEXAROTOR, M.MAV_AUTOPILOT_GENERIC, M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
            int(FlightPhase.PREFLIGHT), M.MAV_STATE_BOOT, 3)
    base = M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    if tel.armed:
        base |= M.MAV_MODE_FLAG_SAFETY_ARMED
    return M.MAVLink_heartbeat_message(M.MAV_TYPE_HEXAROTOR, M.MAV_AUTOPILOT_GENERIC, base,
                                       int(tel.phase), system_status(tel), 3)


_LANDED_STATE = {
    FlightPhase.PREFLIGHT: M.MAV_LANDED_STATE_ON_GROUND,
    FlightPhase.ARMED: M.MAV_LANDED_STATE_ON_GROUND,
    FlightPhase.TAKEOFF: M.MAV_LANDED_STATE_TAKEOFF,
    FlightPhase.MISSION: M.MAV_LANDED_STATE_IN_AIR,
    FlightPhase.LANDING: M.MAV_LANDED_STATE_LANDING,
    FlightPhase.DISARMED: M.MAV_LANDED_STATE_ON_GROUND,
    # motors cut: the session is over and the vehicle is down (caught, or on the floor)
    FlightPhase.CUT: M.MAV_LANDED_STATE_ON_GROUND,
}


def landed_state(phase: FlightPhase) -> int:
    return int(_LANDED_STATE[phase])


def extended_sys_state(tel: VehicleTelemetry | None) -> Any:
    """EXTENDED_SYS_STATE; before the first snapshot the vehicle is on the ground."""
    phase = FlightPhase.PREFLIGHT if tel is None else tel.phase
    return M.MAVLink_extended_sys_state_message(M.MAV_VTOL_STATE_UNDEFINED, landed_state(phase))


def sys_status(tel: VehicleTelemetry) -> Any:
    volt = tel.battery_v
    voltage_mv = UINT16_MAX if not math.isfinite(volt) else max(0, min(UINT16_MAX - 1,
                                                                      round(volt * 1000)))
    return M.MAVLink_sys_status_message(
        SENSORS_PRESENT, SENSORS_PRESENT, health_bits(tel.health), 0, voltage_mv, -1, -1,
        0, 0, 0, 0, 0, 0)


def _attitude_parts(tel: VehicleTelemetry) -> tuple[tuple[float, float, float, float],
                                                    tuple[float, float, float]]:
    return q_world_to_ned(tel.q_wb), flu_to_frd(tel.omega_b_rad_s)


def attitude(tel: VehicleTelemetry) -> Any:
    q, w = _attitude_parts(tel)
    roll, pitch, yaw = q_to_euler(q)
    return M.MAVLink_attitude_message(time_boot_ms(tel), roll, pitch, yaw, w[0], w[1], w[2])


def attitude_quaternion(tel: VehicleTelemetry) -> Any:
    q, w = _attitude_parts(tel)
    return M.MAVLink_attitude_quaternion_message(time_boot_ms(tel), q[0], q[1], q[2], q[3],
                                                 w[0], w[1], w[2], [1.0, 0.0, 0.0, 0.0])


def local_position_ned(tel: VehicleTelemetry) -> Any:
    p = world_to_ned(tel.pos_w_m)
    v = world_to_ned(tel.vel_w_m_s)
    return M.MAVLink_local_position_ned_message(time_boot_ms(tel), p[0], p[1], p[2],
                                                v[0], v[1], v[2])


def odometry(tel: VehicleTelemetry) -> Any:
    q, w = _attitude_parts(tel)
    p = world_to_ned(tel.pos_w_m)
    v_body = rotate_inverse(q, world_to_ned(tel.vel_w_m_s))
    unknown = [math.nan] + [0.0] * 20
    return M.MAVLink_odometry_message(
        time_usec(tel), MAV_FRAME_ESTIM_NED, M.MAV_FRAME_BODY_NED, p[0], p[1], p[2], list(q),
        v_body[0], v_body[1], v_body[2], w[0], w[1], w[2], unknown, unknown, 0,
        M.MAV_ESTIMATOR_TYPE_MOCAP, 100)


def actuator_output_status(tel: VehicleTelemetry) -> Any:
    values = [float(s) for s in tel.rotor_speeds_hz[:6]]
    values += [0.0] * (6 - len(values))
    values.append(float(tel.tilt_rad))
    values += [0.0] * (32 - len(values))
    return M.MAVLink_actuator_output_status_message(time_usec(tel), 0x7F, values)


def statustext(event: StatusEvent, chunk_id: int) -> list[Any]:
    """STATUSTEXT message(s) for one event; ``chunk_id`` (1..65535) is used only when the text
    needs more than one message."""
    raw = event.text.encode("utf-8", "replace")
    sev = int(event.severity)
    if len(raw) <= STATUSTEXT_LEN:
        return [M.MAVLink_statustext_message(sev, raw, 0, 0)]
    chunks = [raw[i:i + STATUSTEXT_LEN] for i in range(0, len(raw), STATUSTEXT_LEN)]
    return [M.MAVLink_statustext_message(sev, c, chunk_id, n) for n, c in enumerate(chunks)]

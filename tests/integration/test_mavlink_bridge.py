"""The MAVLink bridge against a second, independent pymavlink endpoint (mavutil) on loopback.

The bridge is driven in lockstep (``bridge.step(t)`` with a simulated session time), so rates
are checked in simulated time and nothing depends on the machine's load. Waiting on the peer
uses generous deadlines; a "nothing happened" check is closed by a harmless signed command
whose ACK proves every earlier datagram was processed (UDP on loopback keeps the order of one
socket's datagrams and the bridge handles them in order).
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
import os
import socket
import threading
import time
from collections import Counter, deque
from collections.abc import Iterator
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

os.environ["MAVLINK20"] = "1"  # before mavutil is imported (the v1 dialect would lose signing)
import itertools

from pymavlink import mavutil
from pymavlink.dialects.v20 import common as mavlink2

from drivers.mavlink import MavlinkConfig
from drivers.mavlink.frames import q_from_euler
from drivers.mavlink.signing import signing_timestamp_now
from groundstation.mavlink_bridge import MavlinkBridge
from groundstation.operator import (
    Arm,
    CommandResult,
    Disarm,
    EmergencyStop,
    FlightPhase,
    Land,
    PoseSetpoint,
    RuleBasedCommandSink,
    SensorHealth,
    SetParam,
    SetTilt,
    Severity,
    StatusEvent,
    Takeoff,
    VehicleTelemetry,
    operator_params,
)

mavutil.set_dialect("common")
M = mavlink2
KEY = hashlib.sha256(b"labpass").digest()
WRONG_KEY = hashlib.sha256(b"guess").digest()
TIMEOUT_S = 30.0
ROLL, PITCH, YAW = math.radians(5.0), math.radians(-3.0), math.radians(30.0)
RATES = dict(heartbeat_hz=1.0, sys_status_hz=2.0, attitude_hz=50.0, attitude_quaternion_hz=25.0,
             local_position_hz=20.0, odometry_hz=10.0, actuator_output_hz=5.0)
PARAMS = operator_params(kp_pos=(10.0, 10.0, 20.0), kv_pos=(5.0, 5.0, 8.0),
                         ki_pos=(1.0, 1.0, 2.0), kr_att=(3.0, 3.0, 1.0), kw_att=(0.5, 0.5, 0.2),
                         max_tilt_deg=35.0, max_tilt_rate_deg_s=10.0)


def hover(t_s: float, phase: FlightPhase = FlightPhase.PREFLIGHT) -> VehicleTelemetry:
    """A scripted hover: fixed attitude, 5 cm / 0.5 Hz sway along x at 1 m height."""
    x = 0.05 * math.sin(2 * math.pi * 0.5 * t_s)
    vx = 0.05 * 2 * math.pi * 0.5 * math.cos(2 * math.pi * 0.5 * t_s)
    return VehicleTelemetry(
        t_s=t_s, phase=phase, armed=phase.armed, pos_w_m=(x, 0.2, 1.0), vel_w_m_s=(vx, 0.0, 0.0),
        q_wb=q_from_euler(ROLL, PITCH, YAW), omega_b_rad_s=(0.0, 0.0, 0.1),
        rotor_speeds_hz=(55.0, 56.0, 57.0, 58.0, 59.0, 60.0), tilt_rad=math.radians(15.0),
        battery_v=15.2, health=SensorHealth(preflight_ok=True))


class Rig:
    """A bridge (vehicle side, udpout) and a mavutil GCS (udpin) on loopback, in lockstep."""

    def __init__(self, key: bytes | None = None, peer_key: bytes | None = None,
                 phase: FlightPhase = FlightPhase.PREFLIGHT, allow_unsigned: bool = True
                 ) -> None:
        self.gcs = mavutil.mavlink_connection("udpin:127.0.0.1:0", source_system=255,
                                              source_component=190)
        if peer_key is not None:
            self.gcs.setup_signing(peer_key, sign_outgoing=True)
        port = self.gcs.port.getsockname()[1]
        self.t = 0.0
        self.inbox: dict[str, deque[Any]] = {}
        self.sink = RuleBasedCommandSink(phase, on_change=lambda ph: self.bridge.publish(
            hover(self.t, ph)))
        cfg = MavlinkConfig(uri=f"udpout:127.0.0.1:{port}", signing=key is not None, **RATES)
        # unsigned commands allowed explicitly: these tests are about what commands do (the
        # secure default, refusing them, has its own tests below)
        self.bridge = MavlinkBridge(cfg, self.sink, params=PARAMS, key=key,
                                    allow_unsigned_commands=allow_unsigned)
        self.bridge.publish(hover(0.0, phase))
        self.bridge.step(0.0)
        # the GCS learns the vehicle's address from its first datagram
        assert self.recv("HEARTBEAT") is not None
        self.vehicle_addr = ("127.0.0.1", self.bridge.local_address[1])

    def _pull(self, timeout_s: float) -> bool:
        if timeout_s > 0:
            msg = self.gcs.recv_match(blocking=True, timeout=timeout_s)
        else:
            msg = self.gcs.recv_match(blocking=False)
        if msg is None or msg.get_type() == "BAD_DATA":
            return False
        self.inbox.setdefault(msg.get_type(), deque()).append(msg)
        return True

    def recv(self, kind: str) -> Any:
        """The oldest unread ``kind`` message; simulated time moves on 10 ms per idle poll."""
        deadline = time.monotonic() + TIMEOUT_S
        while time.monotonic() < deadline:
            if self.inbox.get(kind):
                return self.inbox[kind].popleft()
            # in lockstep every reply is sent from this thread: what is not there yet will
            # only come with a later step
            if not self._pull(0.0):
                self.t += 0.01
                self.bridge.publish(hover(self.t, self.sink.phase))
                self.bridge.step(self.t)
        raise AssertionError(f"no {kind} within {TIMEOUT_S} s")

    def drain(self, n: int) -> dict[str, list[Any]]:
        """Everything received so far plus ``n`` more messages, by type (time stands still)."""
        for _ in range(n):
            assert self._pull(TIMEOUT_S)
        while self._pull(0.0):
            pass
        out = {k: list(v) for k, v in self.inbox.items()}
        self.inbox.clear()
        return out

    def serve_until_ack(self, command: int) -> Any:
        deadline = time.monotonic() + TIMEOUT_S
        while time.monotonic() < deadline:
            acks = self.inbox.get("COMMAND_ACK")
            while acks:
                ack = acks.popleft()
                if ack.command == command:
                    return ack
            self.bridge.step(self.t, wait_s=0.05)
            while self._pull(0.0):
                pass
        raise AssertionError(f"no COMMAND_ACK for {command}")

    def command(self, command: int, *params: float) -> int:
        p = [*params, *[0.0] * (7 - len(params))]
        self.gcs.mav.command_long_send(1, 1, command, 0, *p)
        return int(self.serve_until_ack(command).result)

    def send_raw(self, frame: bytes) -> None:
        self.gcs.port.sendto(frame, self.vehicle_addr)

    def sync(self) -> None:
        """Returns once every datagram sent before it has been handled by the bridge."""
        self.command(M.MAV_CMD_REQUEST_MESSAGE, M.MAVLINK_MSG_ID_HEARTBEAT)

    def close(self) -> None:
        self.bridge.close()
        self.gcs.close()


@pytest.fixture
def rig() -> Iterator[Rig]:
    r = Rig()
    yield r
    r.close()


def _frame(key: bytes | None, msg: Any, timestamp: int | None = None, sysid: int = 255) -> bytes:
    """One frame encoded by a plain pymavlink encoder, signed with ``key`` if given."""
    out: list[bytes] = []

    class _W:
        def write(self, b: bytes) -> None:
            out.append(bytes(b))

    mav = M.MAVLink(_W(), srcSystem=sysid, srcComponent=190)
    if key is not None:
        mav.signing.secret_key = key
        mav.signing.sign_outgoing = True
        mav.signing.link_id = 7
        mav.signing.timestamp = signing_timestamp_now() if timestamp is None else timestamp
    mav.send(msg)
    return out[0]


def _arm_msg(arm: bool = True) -> Any:
    return M.MAVLink_command_long_message(1, 1, M.MAV_CMD_COMPONENT_ARM_DISARM, 0,
                                          1.0 if arm else 0.0, 0, 0, 0, 0, 0, 0)


def test_that_a_scripted_hover_arrives_at_the_configured_rates_with_correct_values(
        rig: Rig) -> None:
    # Fixture: 2 s of 500 Hz snapshots in lockstep (the first step at t = 0 already ran)
    dt, n = 0.002, 1000
    # Test
    got: dict[str, list[Any]] = {}

    def collect() -> int:
        for kind, msgs in rig.drain(0).items():
            got.setdefault(kind, []).extend(msgs)
        return sum(len(v) for v in got.values())

    for k in range(1, n):
        rig.t = k * dt
        rig.bridge.publish(hover(rig.t))
        rig.bridge.step(rig.t)
        collect()  # keeps the GCS socket's receive buffer from overflowing
    sent = sum(rig.bridge.stats().messages_out.values()) - 1  # the fixture read 1 HEARTBEAT
    while collect() < sent:
        assert rig._pull(TIMEOUT_S), f"{sent - collect()} messages never arrived"
    # Assert: counts over [0, 2 s) at each configured rate
    expected = {"HEARTBEAT": 1.0, "SYS_STATUS": 2.0, "EXTENDED_SYS_STATE": 1.0, "ATTITUDE": 50.0,
                "ATTITUDE_QUATERNION": 25.0, "LOCAL_POSITION_NED": 20.0, "ODOMETRY": 10.0,
                "ACTUATOR_OUTPUT_STATUS": 5.0}
    for kind, hz in expected.items():
        received = len(got.get(kind, [])) + (1 if kind == "HEARTBEAT" else 0)
        assert abs(received - hz * 2.0) <= 1, (kind, received)
    stamps = [m.time_boot_ms for m in got["ATTITUDE"]]
    assert all(abs((b - a) - 20) <= 2 for a, b in itertools.pairwise(stamps))
    # values: attitude in NED, position NED following the scripted sway
    for att in got["ATTITUDE"]:
        assert att.roll == pytest.approx(ROLL, abs=1e-6)
        assert att.pitch == pytest.approx(-PITCH, abs=1e-6)
        assert att.yaw == pytest.approx(-YAW, abs=1e-6)
    for lp in got["LOCAL_POSITION_NED"]:
        t = lp.time_boot_ms / 1000.0
        assert lp.x == pytest.approx(0.05 * math.sin(math.pi * t), abs=2e-4)
        assert (lp.y, lp.z) == pytest.approx((-0.2, -1.0), abs=1e-6)
    for ao in got["ACTUATOR_OUTPUT_STATUS"]:
        assert ao.actuator[:7] == pytest.approx([55, 56, 57, 58, 59, 60, math.radians(15)],
                                                abs=1e-6)
    assert got["SYS_STATUS"][0].voltage_battery == 15200
    assert rig.bridge.stats().signing is None


def test_that_arm_takeoff_land_disarm_and_emergency_stop_are_acked_by_state(rig: Rig) -> None:
    R = CommandResult
    # Test / Assert: each command answered with the result of the state rules
    assert rig.command(M.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 1.0) == R.TEMPORARILY_REJECTED
    assert rig.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 1) == R.ACCEPTED
    hb = rig.recv("HEARTBEAT")
    assert hb.base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED and hb.custom_mode == FlightPhase.ARMED
    assert rig.recv("STATUSTEXT").text == "PREFLIGHT -> ARMED"
    assert rig.command(M.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 1.0) == R.ACCEPTED
    assert rig.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 0) == R.DENIED  # disarm in flight
    assert rig.command(M.MAV_CMD_USER_1, 20.0) == R.ACCEPTED  # tilt 20 deg
    assert rig.command(M.MAV_CMD_USER_1, 50.0) == R.DENIED  # beyond 35 deg
    assert rig.command(M.MAV_CMD_NAV_LAND) == R.ACCEPTED
    rig.sink.set_phase(FlightPhase.DISARMED)
    assert rig.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 0) == R.ACCEPTED
    assert rig.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 0, 21196) == R.ACCEPTED  # force: stop
    assert rig.sink.accepted == [Arm(), Takeoff(1.0), SetTilt(math.radians(20.0)), Land(),
                                 Disarm(), EmergencyStop("force disarm")]
    # (the phase changes before it each sent a heartbeat of their own at once)
    assert any(rig.recv("HEARTBEAT").system_status == M.MAV_STATE_EMERGENCY for _ in range(4))
    assert rig.command(M.MAV_CMD_DO_FLIGHTTERMINATION, 1) == R.ACCEPTED
    assert rig.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 1) == R.DENIED  # no re-arm after a cut


def test_that_a_phase_change_goes_out_in_a_heartbeat_at_once_then_the_cadence_resumes(
        rig: Rig) -> None:
    # Fixture: the 1 Hz heartbeat; the rig's first one went out at t = 0
    got: list[tuple[float, int]] = []

    def serve_until(t_end: float, phase: FlightPhase) -> None:
        while rig.t < t_end - 1e-9:
            rig.t = round(rig.t + 0.01, 6)
            rig.bridge.publish(hover(rig.t, phase))
            rig.bridge.step(rig.t)
            time.sleep(0.001)
            while rig._pull(0.0):
                pass
            for hb in rig.inbox.pop("HEARTBEAT", []):
                got.append((rig.t, hb.custom_mode))

    # Test: a phase that lasts 0.3 s, between two periodic heartbeats
    serve_until(0.5, FlightPhase.PREFLIGHT)
    serve_until(0.8, FlightPhase.ARMED)
    serve_until(2.5, FlightPhase.PREFLIGHT)
    # Assert: each change sent one at once (at 0.51 s and 0.81 s, before 1.0 s); the cadence
    # is kept from there (1.81 s), not bunched
    arrivals = [(round(t, 2), mode) for t, mode in got]
    assert (0.51, FlightPhase.ARMED) in arrivals and (0.81, FlightPhase.PREFLIGHT) in arrivals
    assert [t for t, _ in arrivals] == [0.51, 0.81, 1.81], arrivals


def test_that_phases_the_loop_left_before_a_service_pass_each_go_out_in_order(
        rig: Rig) -> None:
    # Fixture: the loop runs through four phases between two passes of the service thread (a
    # loaded machine, a lockstep mission faster than real time)
    rig.drain(0)
    phases = [FlightPhase.ARMED, FlightPhase.TAKEOFF, FlightPhase.MISSION, FlightPhase.LANDING]
    for i, phase in enumerate(phases):
        rig.bridge.publish(hover(0.1 + 0.001 * i, phase))
    # Test: one pass
    rig.bridge.step(0.2)
    got = rig.drain(2 * len(phases))
    # Assert: a HEARTBEAT and an EXTENDED_SYS_STATE of each phase, in the loop's order (not the
    # latest phase four times); the landed state followed: in air from take-off
    assert [hb.custom_mode for hb in got["HEARTBEAT"]] == phases
    assert [bool(hb.base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED) for hb in got["HEARTBEAT"]] == (
        [True] * 4)
    assert [e.landed_state for e in got["EXTENDED_SYS_STATE"]] == [
        M.MAV_LANDED_STATE_ON_GROUND, M.MAV_LANDED_STATE_TAKEOFF, M.MAV_LANDED_STATE_IN_AIR,
        M.MAV_LANDED_STATE_LANDING]
    # then the periodic cadence from this pass: nothing more due before t = 1.2 s
    rig.bridge.step(1.1)
    assert "HEARTBEAT" not in rig.drain(0)


def test_that_signed_commands_are_accepted_and_unsigned_wrong_key_and_replays_rejected() -> None:
    # Fixture: signing on both sides, the GCS with mavutil's own signing
    rig = Rig(key=KEY, peer_key=KEY)
    try:
        hb = rig.recv("HEARTBEAT")
        assert hb._signed and rig.gcs.mav.signing.goodsig_count >= 2  # telemetry is signed
        # Test: unsigned and wrong-key arms, then a sync
        rig.send_raw(_frame(None, _arm_msg()))
        rig.send_raw(_frame(WRONG_KEY, _arm_msg()))
        rig.sync()
        # Assert: nothing was armed, both rejections counted
        assert rig.sink.phase is FlightPhase.PREFLIGHT and rig.sink.submissions == []
        stats = rig.bridge.stats().signing
        assert stats is not None
        assert (stats.unsigned_rejected, stats.bad_signature) == (1, 1)
        # Test: a correctly signed arm from a second signer, then its byte-exact replay
        good = _frame(KEY, _arm_msg(), sysid=254)
        rig.send_raw(good)
        assert rig.serve_until_ack(M.MAV_CMD_COMPONENT_ARM_DISARM).result == CommandResult.ACCEPTED
        rig.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 0)  # disarm through mavutil's signing
        rig.send_raw(good)
        rig.sync()
        # Assert: one arm, one disarm, the replay dropped and counted
        assert [c for c, _ in rig.sink.submissions] == [Arm(), Disarm()]
        stats = rig.bridge.stats().signing
        assert stats is not None
        assert (stats.replayed, stats.unsigned_rejected, stats.bad_signature) == (1, 1, 1)
        assert stats.good >= 4
        # an unsigned RADIO_STATUS is allow-listed (radios cannot sign) but commands nothing
        rig.send_raw(_frame(None, M.MAVLink_radio_status_message(200, 190, 100, 10, 8, 0, 0)))
        rig.sync()
        stats = rig.bridge.stats().signing
        assert stats is not None and stats.unsigned_allowed == 1
    finally:
        rig.close()


def test_that_a_gcs_with_the_wrong_key_sees_nothing_it_can_verify_and_commands_nothing() -> None:
    rig = Rig(key=KEY, peer_key=KEY)
    try:
        bad = mavutil.mavlink_connection("udpin:127.0.0.1:0", source_system=250)
        try:
            bad.setup_signing(WRONG_KEY, sign_outgoing=True)
            bad.port.sendto(_frame(WRONG_KEY, _arm_msg(), sysid=250), rig.vehicle_addr)
            rig.sync()
        finally:
            bad.close()
        assert rig.sink.submissions == []
        assert rig.bridge.stats().signing.bad_signature == 1  # type: ignore[union-attr]
    finally:
        rig.close()


def test_that_parameters_can_be_listed_read_and_set_only_within_their_range(rig: Rig) -> None:
    # Test: list
    rig.gcs.mav.param_request_list_send(1, 1)
    values = {}
    while len(values) < len(PARAMS):
        pv = rig.recv("PARAM_VALUE")
        values[pv.param_id] = (pv.param_value, pv.param_index, pv.param_count)
    # Assert
    assert set(values) == {p.name for p in PARAMS}
    assert values["KP_POS_Z"][0] == pytest.approx(20.0)
    assert all(count == len(PARAMS) for _, _, count in values.values())
    # Test: set within range, set out of range, read by index
    rig.gcs.mav.param_set_send(1, 1, b"KP_POS_Z", 25.0, M.MAV_PARAM_TYPE_REAL32)
    assert rig.recv("PARAM_VALUE").param_value == pytest.approx(25.0)
    rig.gcs.mav.param_set_send(1, 1, b"TILT_MAX_DEG", 40.0, M.MAV_PARAM_TYPE_REAL32)
    echo = rig.recv("PARAM_VALUE")
    assert (echo.param_id, echo.param_value) == ("TILT_MAX_DEG", pytest.approx(35.0))
    rig.gcs.mav.param_request_read_send(1, 1, b"", values["KP_POS_Z"][1])
    assert rig.recv("PARAM_VALUE").param_value == pytest.approx(25.0)
    # Assert: only the valid write reached the sink
    assert rig.sink.accepted == [SetParam("KP_POS_Z", 25.0)]
    assert rig.bridge.param_value("TILT_MAX_DEG") == 35.0


def test_that_what_mavproxy_sends_to_any_vehicle_is_answered_or_ignored(rig: Rig) -> None:
    # FTP: parameter download over FTP is refused, so the GCS falls back to PARAM_REQUEST_LIST
    payload = bytearray(251)
    payload[0:2] = (5).to_bytes(2, "little")
    payload[3] = 4  # OpenFileRO
    name = b"@PARAM/param.pck"
    payload[4] = len(name)
    payload[12:12 + len(name)] = name
    rig.gcs.mav.file_transfer_protocol_send(0, 1, 1, list(payload))
    nak = bytes(rig.recv("FILE_TRANSFER_PROTOCOL").payload)
    assert (int.from_bytes(nak[0:2], "little"), nak[3], nak[5], nak[12]) == (6, 129, 4, 10)
    rig.gcs.mav.mission_request_list_send(1, 1, 0)
    assert rig.recv("MISSION_COUNT").count == 0
    assert rig.command(M.MAV_CMD_GET_HOME_POSITION) == CommandResult.UNSUPPORTED
    rig.gcs.mav.request_data_stream_send(1, 1, 0, 4, 1)
    assert rig.command(M.MAV_CMD_REQUEST_MESSAGE,
                       M.MAVLINK_MSG_ID_AUTOPILOT_VERSION) == CommandResult.ACCEPTED
    caps = rig.recv("AUTOPILOT_VERSION").capabilities
    assert caps & M.MAV_PROTOCOL_CAPABILITY_MAVLINK2
    rig.gcs.mav.timesync_send(0, 123456)
    assert rig.recv("TIMESYNC").ts1 == 123456
    # a GCS slows ATTITUDE down to 10 Hz: 1 s of lockstep then brings 10 of them
    assert rig.command(M.MAV_CMD_SET_MESSAGE_INTERVAL, M.MAVLINK_MSG_ID_ATTITUDE,
                       100_000) == CommandResult.ACCEPTED
    before = rig.bridge.stats().messages_out["ATTITUDE"]
    for k in range(1, 501):
        rig.bridge.step(k * 0.002 + 0.001)
    assert abs(rig.bridge.stats().messages_out["ATTITUDE"] - before - 10) <= 1
    # a heartbeat from the GCS is tracked for link-loss detection
    rig.gcs.mav.heartbeat_send(M.MAV_TYPE_GCS, M.MAV_AUTOPILOT_INVALID, 0, 0, 0)
    rig.sync()
    assert rig.bridge.gcs_link_ok(rig.t)
    assert rig.bridge.stats().ignored.get("REQUEST_DATA_STREAM") == 1


def test_that_offboard_targets_reach_the_sink_in_world_coordinates_only_in_mission() -> None:
    rig = Rig(phase=FlightPhase.TAKEOFF)
    try:
        mask = 0b1001_1111_1000  # position and yaw given; velocity, accel, yaw rate ignored
        rig.gcs.mav.set_position_target_local_ned_send(0, 1, 1, M.MAV_FRAME_LOCAL_NED, mask,
                                                       1.0, 0.5, -1.2, 0, 0, 0, 0, 0, 0, 0.3, 0)
        rig.sync()
        rig.sink.set_phase(FlightPhase.MISSION)
        rig.gcs.mav.set_position_target_local_ned_send(0, 1, 1, M.MAV_FRAME_LOCAL_NED, mask,
                                                       1.0, 0.5, -1.2, 0, 0, 0, 0, 0, 0, 0.3, 0)
        echo = rig.recv("POSITION_TARGET_LOCAL_NED")
        assert (echo.x, echo.y, echo.z) == pytest.approx((1.0, 0.5, -1.2))
        q_ned = q_from_euler(0.1, 0.0, 0.0)
        rig.gcs.mav.set_attitude_target_send(0, 1, 1, 0b0000_0111, list(q_ned), 0, 0, 0, 0.5)
        rig.sync()
        (_sp0, r0), (sp1, r1), (sp2, r2) = rig.sink.submissions[:3]
        assert r0 is CommandResult.TEMPORARILY_REJECTED and r1 is CommandResult.ACCEPTED
        assert isinstance(sp1, PoseSetpoint) and sp1.pos_w_m is not None
        assert sp1.pos_w_m == pytest.approx((1.0, -0.5, 1.2))
        assert sp1.yaw_rad == pytest.approx(-0.3)
        assert isinstance(sp2, PoseSetpoint) and sp2.q_wb is not None
        assert r2 is CommandResult.ACCEPTED
        assert sp2.q_wb == pytest.approx(q_ned, abs=1e-6)  # roll only: same in both frames
    finally:
        rig.close()


def test_that_mocap_poses_over_mavlink_become_world_frame_pose_samples(rig: Rig) -> None:
    assert rig.bridge.mocap.latest() is None
    q_ned = q_from_euler(0.0, 0.0, 0.5)  # yaw 0.5 rad about NED down
    rig.gcs.mav.att_pos_mocap_send(123, list(q_ned), 1.0, 2.0, -1.5)
    rig.sync()
    s = rig.bridge.mocap.latest()
    assert s is not None and s.valid and s.body_name == "ATT_POS_MOCAP"
    assert s.pos_w_m == pytest.approx((1.0, -2.0, 1.5))
    w, x, y, z = s.q_wb
    assert (x, y) == pytest.approx((0.0, 0.0), abs=1e-9)
    assert 2 * math.atan2(z, w) == pytest.approx(-0.5, abs=1e-6)  # yaw about world z up
    rig.gcs.mav.vision_position_estimate_send(456, 0.1, 0.2, -0.3, 0.0, 0.0, 0.0)
    rig.sync()
    s2 = rig.bridge.mocap.latest()
    assert s2 is not None and s2.pos_w_m == pytest.approx((0.1, -0.2, 0.3))
    assert s2.q_wb == pytest.approx((1.0, 0.0, 0.0, 0.0))
    assert rig.bridge.mocap.stats().frames_received == 2


def test_that_the_service_thread_streams_on_the_wall_clock_while_another_thread_publishes(
        ) -> None:
    # Fixture: the vehicle listens (udpin); the GCS sends first (udpout)
    probe = mavutil.mavlink_connection("udpin:127.0.0.1:0")
    port = probe.port.getsockname()[1]
    probe.close()  # a free port number for the vehicle to bind
    sink = RuleBasedCommandSink()
    bridge = MavlinkBridge(MavlinkConfig(uri=f"udpin:127.0.0.1:{port}", attitude_hz=100.0),
                           sink, allow_unsigned_commands=True)
    gcs = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=255)
    stop = threading.Event()

    def publisher() -> None:
        k = 0
        while not stop.is_set():
            bridge.publish(hover(k * 0.01))
            k += 1
            stop.wait(0.01)

    pub = threading.Thread(target=publisher, daemon=True)
    try:
        bridge.start()
        pub.start()
        gcs.mav.heartbeat_send(M.MAV_TYPE_GCS, M.MAV_AUTOPILOT_INVALID, 0, 0, 0)
        # Test: the vehicle answers the address the GCS spoke from
        atts = []
        deadline = time.monotonic() + TIMEOUT_S
        while len(atts) < 20 and time.monotonic() < deadline:
            msg = gcs.recv_match(type="ATTITUDE", blocking=True, timeout=1.0)
            if msg is not None:
                atts.append(msg)
        gcs.mav.command_long_send(1, 1, M.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
        ack = gcs.recv_match(type="COMMAND_ACK", blocking=True, timeout=TIMEOUT_S)
    finally:
        stop.set()
        pub.join()
        bridge.close()
        gcs.close()
    # Assert
    assert len(atts) == 20 and all(a.roll == pytest.approx(ROLL, abs=1e-6) for a in atts)
    assert ack is not None and ack.result == CommandResult.ACCEPTED
    assert sink.accepted == [Arm()]
    assert Counter(type(c).__name__ for c, _ in sink.submissions) == {"Arm": 1}


def test_that_an_unsigned_datagram_cannot_redirect_a_listening_vehicles_telemetry() -> None:
    # Fixture: the vehicle listens (udpin) with signing; the lab GCS and an intruder
    socks = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(3)]
    probe, lab, intruder = socks
    probe.bind(("127.0.0.1", 0))
    port = probe.getsockname()[1]
    probe.close()
    for s in (lab, intruder):
        s.bind(("127.0.0.1", 0))
        s.setblocking(False)
    bridge = MavlinkBridge(MavlinkConfig(uri=f"udpin:127.0.0.1:{port}", signing=True),
                           RuleBasedCommandSink(), key=KEY)
    gcs_hb = M.MAVLink_heartbeat_message(M.MAV_TYPE_GCS, M.MAV_AUTOPILOT_INVALID, 0, 0, 0, 3)
    try:
        bridge.publish(hover(0.0))
        # Test
        lab.sendto(_frame(KEY, gcs_hb), ("127.0.0.1", port))
        bridge.step(0.0, wait_s=TIMEOUT_S)
        intruder.sendto(_frame(None, gcs_hb, sysid=66), ("127.0.0.1", port))
        bridge.step(1.0, wait_s=TIMEOUT_S)  # handles the intruder, then sends telemetry
        # Assert: the lab gets the telemetry (the intruder's share would have come with it)
        lab.settimeout(TIMEOUT_S)
        assert len(lab.recvfrom(65535)[0]) > 0
        with pytest.raises(BlockingIOError):
            intruder.recvfrom(65535)
        signing = bridge.stats().signing
        assert signing is not None and signing.unsigned_rejected == 1
    finally:
        bridge.close()
        for s in socks:
            s.close()


def test_that_faults_and_events_go_out_once_each_even_when_snapshots_are_overwritten(
        rig: Rig) -> None:
    # Fixture: three snapshots published between two service passes
    base = hover(0.5)
    rig.sink.set_phase(FlightPhase.CUT)  # what the rig republishes while it waits
    rig.bridge.publish(dataclasses.replace(
        base, health=SensorHealth(mocap_ok=False, preflight_ok=True),
        events=(StatusEvent(0.5, "MoCap stale 0.31 s", Severity.WARNING),)))
    rig.bridge.publish(dataclasses.replace(base, t_s=0.502))
    rig.bridge.publish(dataclasses.replace(base, t_s=0.504, phase=FlightPhase.CUT))
    # Test
    rig.t = 0.504
    rig.bridge.step(rig.t)
    texts = []
    while len(texts) < 4:
        assert rig._pull(TIMEOUT_S)
        texts = [(m.text, m.severity) for m in rig.inbox.get("STATUSTEXT", [])]
    # Assert: in order, each once
    assert texts == [("fault: mocap", M.MAV_SEVERITY_WARNING),
                     ("MoCap stale 0.31 s", M.MAV_SEVERITY_WARNING),
                     ("ok: mocap", M.MAV_SEVERITY_INFO),
                     ("PREFLIGHT -> CUT", M.MAV_SEVERITY_EMERGENCY)]
    rig.inbox.clear()
    rig.bridge.step(rig.t + 1.0)
    assert rig.recv("HEARTBEAT").custom_mode == FlightPhase.CUT
    assert "STATUSTEXT" not in rig.inbox  # nothing sent twice


def test_that_arbitrary_commands_and_setpoints_are_answered_and_never_break_the_bridge(
        ) -> None:
    rig = Rig(phase=FlightPhase.MISSION)
    f32 = st.floats(width=32)  # NaN and infinities included
    results = {int(r) for r in CommandResult}

    @settings(max_examples=150, deadline=None)
    @given(command=st.one_of(st.sampled_from([22, 21, 185, 400, 410, 511, 512, 520, 31010]),
                             st.integers(0, 65535)),
           params=st.lists(f32, min_size=7, max_size=7),
           target=st.lists(f32, min_size=8, max_size=8),
           name=st.text(max_size=16).map(lambda s: s.encode("utf-8")[:16]))
    def exchange(command: int, params: list[float], target: list[float], name: bytes) -> None:
        rig.gcs.mav.set_position_target_local_ned_send(
            0, 1, 1, M.MAV_FRAME_LOCAL_NED, 0b1001_1111_1000, *target[:3], 0, 0, 0, 0, 0, 0,
            target[3], 0)
        rig.gcs.mav.set_attitude_target_send(0, 1, 1, 0, target[4:8], 0, 0, 0, 0.5)
        rig.gcs.mav.att_pos_mocap_send(0, target[4:8], *target[:3])
        rig.gcs.mav.param_set_send(1, 1, name, params[0], M.MAV_PARAM_TYPE_REAL32)
        rig.gcs.mav.command_long_send(1, 1, command, 0, *params)
        assert int(rig.serve_until_ack(command).result) in results

    try:
        exchange()
        stats = rig.bridge.stats()
        assert not [k for k in stats.ignored if k.startswith("ERROR_")]
        assert sum(stats.command_results.values()) >= 150
    finally:
        rig.close()


# -- secure by default ------------------------------------------------------------------------

FLIGHT_CHANGING = [
    (M.MAV_CMD_COMPONENT_ARM_DISARM, (1.0,)),  # arm
    (M.MAV_CMD_COMPONENT_ARM_DISARM, (0.0,)),  # disarm
    (M.MAV_CMD_COMPONENT_ARM_DISARM, (0.0, 21196.0)),  # force disarm: emergency stop
    (M.MAV_CMD_NAV_TAKEOFF, (0, 0, 0, 0, 0, 0, 1.0)),
    (M.MAV_CMD_NAV_LAND, ()),
    (M.MAV_CMD_DO_FLIGHTTERMINATION, (1.0,)),
    (M.MAV_CMD_USER_1, (20.0,)),  # tilt
]


def test_that_without_a_key_flight_changing_commands_are_refused_and_telemetry_flows() -> None:
    # Fixture: the default bridge, no key, nothing allowed; the vehicle flies its mission
    rig = Rig(phase=FlightPhase.MISSION, allow_unsigned=False)
    try:
        # Test: every flight-changing command, a parameter write and two setpoints
        results = [rig.command(cmd, *p) for cmd, p in FLIGHT_CHANGING]
        rig.gcs.mav.param_set_send(1, 1, b"KP_POS_XY", 12.0, M.MAV_PARAM_TYPE_REAL32)
        value = rig.recv("PARAM_VALUE")
        rig.gcs.mav.set_position_target_local_ned_send(
            0, 1, 1, M.MAV_FRAME_LOCAL_NED, 0b1001_1111_1000, 0.5, 0.0, -1.0, 0, 0, 0, 0, 0, 0,
            0.0, 0)
        rig.gcs.mav.set_attitude_target_send(0, 1, 1, 0, [1.0, 0.0, 0.0, 0.0], 0, 0, 0, 0.5)
        rig.sync()
        # Assert: all denied, nothing reached the flight, every refusal counted
        assert results == [CommandResult.DENIED] * len(FLIGHT_CHANGING)
        assert rig.sink.submissions == []
        assert value.param_value == pytest.approx(PARAMS[0].value)  # unchanged
        stats = rig.bridge.stats()
        assert stats.refused_unsigned == len(FLIGHT_CHANGING) + 1 + 2
        assert stats.setpoint_results == {"DENIED": 2}
        # telemetry and link services still work: the sync above was an accepted
        # REQUEST_MESSAGE, and the stream goes on
        assert stats.command_results["ACCEPTED"] >= 1
        assert rig.recv("ATTITUDE").roll == pytest.approx(ROLL, abs=1e-6)
        assert rig.recv("HEARTBEAT").custom_mode == FlightPhase.MISSION
    finally:
        rig.close()


def test_that_a_stale_signed_frame_is_rejected_and_counted_apart_from_replays() -> None:
    rig = Rig(key=KEY, peer_key=KEY)
    try:
        two_minutes_ago = signing_timestamp_now() - 120 * 100_000
        for k in range(5):
            rig.send_raw(_frame(KEY, _arm_msg(), timestamp=two_minutes_ago + k, sysid=250))
        rig.sync()
        assert rig.sink.submissions == []
        stats = rig.bridge.stats().signing
        assert stats is not None
        assert (stats.stale, stats.replayed, stats.bad_signature) == (5, 0, 0)
    finally:
        rig.close()


def test_that_out_of_range_values_are_refused_and_counted_never_delivered() -> None:
    R = CommandResult
    rig = Rig(phase=FlightPhase.MISSION)
    inf, nan = math.inf, math.nan
    try:
        # Test: commands, setpoints, parameters and poses with unphysical values
        got = [rig.command(M.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 100.0),  # 100 m
               rig.command(M.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, nan),
               rig.command(M.MAV_CMD_USER_1, 36.0),  # beyond the 35 deg mechanism
               rig.command(M.MAV_CMD_USER_1, -1.0),
               rig.command(M.MAV_CMD_USER_1, inf),
               rig.command(M.MAV_CMD_COMPONENT_ARM_DISARM, nan)]
        mask = 0b1001_1111_1000  # position and yaw
        for target in ((1000.0, 0.0, -1.0, 0.0), (0.0, nan, -1.0, 0.0), (0.0, 0.0, -1.0, inf)):
            rig.gcs.mav.set_position_target_local_ned_send(
                0, 1, 1, M.MAV_FRAME_LOCAL_NED, mask, *target[:3], 0, 0, 0, 0, 0, 0,
                target[3], 0)
        rig.gcs.mav.set_attitude_target_send(0, 1, 1, 0, [nan, 0.0, 0.0, 0.0], 0, 0, 0, 0.5)
        rig.gcs.mav.set_attitude_target_send(0, 1, 1, 0, [0.0, 0.0, 0.0, 0.0], 0, 0, 0, 0.5)
        rig.gcs.mav.param_set_send(1, 1, b"KP_POS_XY", nan, M.MAV_PARAM_TYPE_REAL32)
        rig.gcs.mav.param_set_send(1, 1, b"TILT_MAX_DEG", 80.0, M.MAV_PARAM_TYPE_REAL32)
        rig.gcs.mav.vision_position_estimate_send(1, 0.1, 0.2, -0.3, inf, 0.0, 0.0)
        rig.gcs.mav.vision_position_estimate_send(2, 0.1, 0.2, -0.3, 0.0, nan, 0.0)
        rig.gcs.mav.att_pos_mocap_send(3, [1.0, 0.0, 0.0, 0.0], 1000.0, 0.0, -1.0)  # 1 km
        rig.gcs.mav.att_pos_mocap_send(4, [nan, 0.0, 0.0, 0.0], 0.0, 0.0, -1.0)
        rig.sync()
        # Assert: every one refused, counted, none handed on, nothing raised
        assert got == [R.DENIED] * 6
        assert rig.sink.submissions == []
        assert rig.bridge.mocap.latest() is None
        stats = rig.bridge.stats()
        assert stats.refused_out_of_range == 6 + 5 + 2 + 4
        assert stats.setpoint_results == {"DENIED": 5}
        assert stats.handler_errors == 0
        assert rig.bridge.param_value("TILT_MAX_DEG") == pytest.approx(35.0)
        # the vehicle's own range is the limit: 35 deg exactly is fine
        assert rig.command(M.MAV_CMD_USER_1, 35.0) == R.ACCEPTED
    finally:
        rig.close()


def test_that_random_and_mutated_bytes_into_the_bridge_never_raise() -> None:
    # Fixture: a signing and a non-signing bridge fed directly (their input path, no socket)
    sink = RuleBasedCommandSink(FlightPhase.MISSION)
    bridges = [MavlinkBridge(MavlinkConfig(uri="udpout:127.0.0.1:9"), sink, params=PARAMS,
                             allow_unsigned_commands=True),
               MavlinkBridge(MavlinkConfig(uri="udpout:127.0.0.1:9", signing=True), sink,
                             params=PARAMS, key=KEY)]
    valid = [_frame(None, M.MAVLink_vision_position_estimate_message(0, 0.1, 0.2, -0.3, 0, 0, 0)),
             _frame(KEY, _arm_msg()),
             _frame(None, M.MAVLink_att_pos_mocap_message(0, [1, 0, 0, 0], 1, 2, -1)),
             _frame(None, M.MAVLink_param_set_message(1, 1, b"KP_POS_XY", 1.0, 9)),
             _frame(None, M.MAVLink_set_position_target_local_ned_message(
                 0, 1, 1, 1, 0b1001_1111_1000, 0.1, 0, -1, 0, 0, 0, 0, 0, 0, 0, 0))]

    @settings(max_examples=400, deadline=None)
    @given(data=st.one_of(
        st.binary(max_size=300),
        st.tuples(st.sampled_from(valid), st.integers(0, 299), st.integers(0, 255),
                  st.booleans()).map(_mutate)))
    def feed(data: bytes) -> None:
        for b in bridges:
            b.feed(data, 1.0)  # Assert: never raises

    try:
        feed()
        for b in bridges:
            assert b.stats().handler_errors == 0
    finally:
        for b in bridges:
            b.close()


def _mutate(args: tuple[bytes, int, int, bool]) -> bytes:
    """A valid frame with one byte replaced (and, to get past the CRC, the CRC recomputed:
    then the payload itself carries the mutation into the handlers)."""
    frame, pos, value, fix_crc = args
    b = bytearray(frame)
    b[pos % len(b)] = value
    if fix_crc and len(b) > 12 and b[0] == 0xFD:
        from pymavlink.generator.mavcrc import x25crc

        n = b[1]
        msg_id = b[7] | b[8] << 8 | b[9] << 16
        entry = M.mavlink_map.get(msg_id)
        if entry is not None and 10 + n + 2 <= len(b):
            crc = x25crc(bytes(b[1:10 + n]))
            crc.accumulate(bytes([entry.crc_extra]))
            b[10 + n:12 + n] = crc.crc.to_bytes(2, "little")
    return bytes(b)


def test_that_the_final_state_is_announced_with_heartbeats_and_landed_state() -> None:
    rig = Rig(phase=FlightPhase.LANDING)
    try:
        rig.sink.set_phase(FlightPhase.DISARMED)
        rig.bridge.publish(hover(rig.t, FlightPhase.DISARMED))
        slept: list[float] = []
        clock = [100.0]

        def fake_sleep(dt: float) -> None:  # the bridge's wall clock, stepped by hand
            slept.append(dt)
            clock[0] += dt

        rig.bridge._clock = lambda: clock[0]
        rig.bridge.announce_final("session over: DISARMED", 1.5, sleep=fake_sleep)
        got = rig.drain(0)
        while rig._pull(1.0):
            pass
        got = {k: got.get(k, []) + list(rig.inbox.get(k, [])) for k in
               ("HEARTBEAT", "EXTENDED_SYS_STATE", "STATUSTEXT")}
        final_hb = [h for h in got["HEARTBEAT"] if h.custom_mode == FlightPhase.DISARMED]
        # Assert: >= 1.5 s of 2 Hz announcements, disarmed and on the ground; the text once
        assert sum(slept) >= 1.5
        assert len(final_hb) >= 3
        assert all(not h.base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED for h in final_hb)
        assert got["EXTENDED_SYS_STATE"][-1].landed_state == M.MAV_LANDED_STATE_ON_GROUND
        assert len([x for x in got["EXTENDED_SYS_STATE"]
                    if x.landed_state == M.MAV_LANDED_STATE_ON_GROUND]) >= 3
        assert [t.text for t in got["STATUSTEXT"]].count("session over: DISARMED") == 1
    finally:
        rig.close()

"""MAVProxy, an independent GCS, against the bridge: it detects the vehicle, prints its attitude,
arms and disarms it, with and without signing.

MAVProxy (GPLv3) runs as a separate process, fed commands on stdin as an operator would type
them; every wait is on a line it prints, with a generous deadline. ``mavproxy.py`` is taken
from the running interpreter's environment (the test extra installs it); a missing one is a
failure, not a skip.
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterator
from pathlib import Path

import pytest
from mavlink_support import TIMEOUT_S, MavProxy, free_udp_port

from drivers.mavlink import MavlinkConfig, load_signing_key
from drivers.mavlink.frames import q_from_euler
from groundstation.mavlink_bridge import MavlinkBridge
from groundstation.operator import (
    Arm,
    Disarm,
    FlightPhase,
    RuleBasedCommandSink,
    SensorHealth,
    VehicleTelemetry,
)

ROLL, PITCH = math.radians(5.0), math.radians(-3.0)


def _telemetry(phase: FlightPhase) -> VehicleTelemetry:
    return VehicleTelemetry(
        t_s=1.0, phase=phase, armed=phase.armed, pos_w_m=(0.0, 0.0, 0.0),
        vel_w_m_s=(0.0, 0.0, 0.0), q_wb=q_from_euler(ROLL, PITCH, 0.0),
        omega_b_rad_s=(0.0, 0.0, 0.0), rotor_speeds_hz=(0.0,) * 6, tilt_rad=0.0, battery_v=16.0,
        health=SensorHealth(preflight_ok=True))


class Vehicle:
    """The bridge served by its own thread on the wall clock, fed by the reference sink."""

    def __init__(self, port: int, key: bytes | None = None, allow_unsigned: bool = False
                 ) -> None:
        self.sink = RuleBasedCommandSink(on_change=lambda ph: self.bridge.publish(_telemetry(ph)))
        cfg = MavlinkConfig(uri=f"udpout:127.0.0.1:{port}", signing=key is not None)
        self.bridge = MavlinkBridge(cfg, self.sink, key=key,
                                    allow_unsigned_commands=allow_unsigned)
        self.bridge.publish(_telemetry(FlightPhase.PREFLIGHT))
        self.bridge.start()


@pytest.fixture
def port() -> int:
    return free_udp_port()


@pytest.fixture
def vehicle(port: int) -> Iterator[Vehicle]:
    v = Vehicle(port, allow_unsigned=True)  # unsigned commands allowed on purpose
    yield v
    v.bridge.close()


def test_that_mavproxy_sees_the_vehicle_and_its_attitude_and_arms_and_disarms_it(
        port: int, vehicle: Vehicle, tmp_path: Path) -> None:
    mp = MavProxy(port, tmp_path)
    try:
        # Test / Assert: detection
        mp.expect(r"Detected vehicle 1:1")
        # arming, acknowledged and reflected in the vehicle's heartbeat and status text
        mp.type("arm throttle")
        mp.expect(r"COMMAND_ACK: COMPONENT_ARM_DISARM: ACCEPTED")
        assert vehicle.sink.wait_for(lambda log: (Arm(), 0) in log, TIMEOUT_S)
        mp.expect(r"AP: PREFLIGHT -> ARMED")
        # the attitude, as MAVProxy decoded it
        mp.type("status ATTITUDE")
        m = mp.expect(r"ATTITUDE \{.*roll : ([-0-9.e]+), pitch : ([-0-9.e]+)")
        assert float(m.group(1)) == pytest.approx(ROLL, abs=1e-6)
        assert float(m.group(2)) == pytest.approx(-PITCH, abs=1e-6)  # NED pitch: nose up
        mp.type("disarm")
        mp.expect(r"COMMAND_ACK: COMPONENT_ARM_DISARM: ACCEPTED")
        mp.expect(r"AP: ARMED -> DISARMED")
    finally:
        mp.close()
    assert [c for c, _ in vehicle.sink.submissions] == [Arm(), Disarm()]
    stats = vehicle.bridge.stats()
    assert stats.command_results.get("ACCEPTED", 0) >= 2
    # MAVProxy's own log holds our telemetry: an independent decoder read it
    os.environ.setdefault("MAVLINK20", "1")
    from pymavlink import mavutil

    log = mavutil.mavlink_connection(str(tmp_path / "mav.tlog"))
    seen = set()
    while (msg := log.recv_msg()) is not None:
        seen.add(msg.get_type())
    assert {"HEARTBEAT", "ATTITUDE", "ATTITUDE_QUATERNION", "LOCAL_POSITION_NED", "ODOMETRY",
            "ACTUATOR_OUTPUT_STATUS", "STATUSTEXT", "COMMAND_LONG"} <= seen


def test_that_mavproxy_with_the_lab_passphrase_arms_a_signing_vehicle(
        port: int, tmp_path: Path) -> None:
    # Fixture: the key comes from the environment, as a lab would provide it
    key = load_signing_key(None, environ={"FASTHEX_MAVLINK_KEY": "labpass"})
    assert key is not None
    v = Vehicle(port, key=key)
    mp = MavProxy(port, tmp_path, "--mav20")
    try:
        mp.expect(r"Detected vehicle 1:1")
        # Test: an arm signed with the wrong passphrase, then one with the lab's
        mp.type("signing key wrongpass")
        mp.type("arm throttle")
        mp.type("signing key labpass")
        mp.type("arm throttle")
        mp.expect(r"COMMAND_ACK: COMPONENT_ARM_DISARM: ACCEPTED")
        # Assert: the second was accepted; the first (handled before it) never reached the sink
        assert v.sink.wait_for(lambda log: (Arm(), 0) in log, TIMEOUT_S)
        assert [c for c, _ in v.sink.submissions] == [Arm()]
        wrong = v.bridge.stats().signing
        assert wrong is not None and wrong.bad_signature >= 1
        mp.type("disarm")
        mp.expect(r"COMMAND_ACK: COMPONENT_ARM_DISARM: ACCEPTED")
        assert v.sink.wait_for(lambda log: (Disarm(), 0) in log, TIMEOUT_S)
    finally:
        mp.close()
        v.bridge.close()
    sig = v.bridge.stats().signing
    assert sig is not None and sig.good >= 2
    assert sig.replayed == 0


def test_that_an_unsigned_mavproxy_cannot_arm_a_vehicle_that_has_no_key(
        port: int, tmp_path: Path) -> None:
    # Fixture: the secure default: no key, unsigned commands not allowed
    v = Vehicle(port)
    mp = MavProxy(port, tmp_path)
    try:
        mp.expect(r"Detected vehicle 1:1")
        # Test
        mp.type("arm throttle")
        # Assert: denied, never reached the flight, counted; telemetry still flows
        mp.expect(r"COMMAND_ACK: COMPONENT_ARM_DISARM: DENIED")
        mp.type("status ATTITUDE")
        mp.expect(r"ATTITUDE \{")
    finally:
        mp.close()
        v.bridge.close()
    assert v.sink.submissions == []
    assert v.bridge.stats().refused_unsigned >= 1

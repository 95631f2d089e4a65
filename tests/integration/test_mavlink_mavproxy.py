"""MAVProxy, an independent GCS, against the bridge: it detects the vehicle, prints its attitude,
arms and disarms it, with and without signing.

MAVProxy (GPLv3) runs as a separate process, fed commands on stdin as an operator would type
them; every wait is on a line it prints, with a generous deadline. Skipped only when the
``mavproxy.py`` script is not installed (the test extra installs it).
"""

from __future__ import annotations

import math
import os
import queue
import re
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from drivers.mavlink import MavlinkBridge, MavlinkConfig, load_signing_key
from drivers.mavlink.frames import q_from_euler
from groundstation.operator import (
    Arm,
    Disarm,
    FlightPhase,
    RuleBasedCommandSink,
    SensorHealth,
    VehicleTelemetry,
)

MAVPROXY = shutil.which("mavproxy.py")
pytestmark = pytest.mark.skipif(
    MAVPROXY is None,
    reason="MAVProxy is not installed (pip install --no-deps MAVProxy==1.8.75 for a headless one)")

TIMEOUT_S = 90.0
ROLL, PITCH = math.radians(5.0), math.radians(-3.0)


def _telemetry(phase: FlightPhase) -> VehicleTelemetry:
    return VehicleTelemetry(
        t_s=1.0, phase=phase, armed=phase.armed, pos_w_m=(0.0, 0.0, 0.0),
        vel_w_m_s=(0.0, 0.0, 0.0), q_wb=q_from_euler(ROLL, PITCH, 0.0),
        omega_b_rad_s=(0.0, 0.0, 0.0), rotor_speeds_hz=(0.0,) * 6, tilt_rad=0.0, battery_v=16.0,
        health=SensorHealth(preflight_ok=True))


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class MavProxy:
    """A MAVProxy process listening on ``port``; its output lines are collected by a thread."""

    def __init__(self, port: int, state_dir: Path, *extra: str) -> None:
        assert MAVPROXY is not None
        env = {**os.environ, "HOME": str(state_dir)}
        env.pop("MAVLINK20", None)
        self.proc = subprocess.Popen(
            [sys.executable, MAVPROXY, f"--master=udpin:127.0.0.1:{port}",
             f"--state-basedir={state_dir}", "--cmd=set flushlogs True", *extra],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
            bufsize=1, env=env, cwd=state_dir)
        self.lines: list[str] = []
        self._q: queue.Queue[str] = queue.Queue()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self._q.put(line.rstrip("\n"))

    def type(self, command: str) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.write(command + "\n")
        self.proc.stdin.flush()

    def expect(self, pattern: str) -> re.Match[str]:
        """The first new output line matching ``pattern`` (a regex)."""
        rx = re.compile(pattern)
        deadline = time.monotonic() + TIMEOUT_S
        while time.monotonic() < deadline:
            try:
                line = self._q.get(timeout=0.5)
            except queue.Empty:
                if self.proc.poll() is not None:
                    break
                continue
            self.lines.append(line)
            m = rx.search(line)
            if m is not None:
                return m
        tail = "\n".join(self.lines[-40:])
        raise AssertionError(f"MAVProxy never printed /{pattern}/; last lines:\n{tail}")

    def close(self) -> None:
        if self.proc.poll() is None:
            try:
                # MAVProxy only honours "exit" with requireexit set; stopping cleanly
                # flushes its telemetry log
                self.type("set requireexit True")
                self.type("exit")
                assert self.proc.stdin is not None
                self.proc.stdin.close()  # its input loop checks for the stop only between lines
                self.proc.wait(timeout=30)
            except (OSError, subprocess.TimeoutExpired):
                self.proc.send_signal(signal.SIGINT)
                self.proc.terminate()
                try:
                    self.proc.wait(timeout=10)
                except subprocess.TimeoutExpired:
                    self.proc.kill()
                    self.proc.wait(timeout=10)
        for stream in (self.proc.stdin, self.proc.stdout):
            if stream is not None and not stream.closed:
                stream.close()


class Vehicle:
    """The bridge served by its own thread on the wall clock, fed by the reference sink."""

    def __init__(self, port: int, key: bytes | None = None) -> None:
        self.sink = RuleBasedCommandSink(on_change=lambda ph: self.bridge.publish(_telemetry(ph)))
        cfg = MavlinkConfig(uri=f"udpout:127.0.0.1:{port}", signing=key is not None)
        self.bridge = MavlinkBridge(cfg, self.sink, key=key)
        self.bridge.publish(_telemetry(FlightPhase.PREFLIGHT))
        self.bridge.start()


@pytest.fixture
def port() -> int:
    return _free_udp_port()


@pytest.fixture
def vehicle(port: int) -> Iterator[Vehicle]:
    v = Vehicle(port)
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

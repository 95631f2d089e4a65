"""Lockstep ``fasthex fly`` sessions commanded over MAVLink: secure by default, end to end.

Each test runs the real CLI in a child process (``--json`` gives the summary and the link's
counters) with a GCS peer on loopback: MAVProxy signed with the session's key, a pymavlink
endpoint that plays the lab GCS and an attacker sending unsigned, wrongly signed, stale and
replayed frames, or MAVSDK (its 4.x Python package runs the C++ library in-process, offline).
Waiting is on messages and output lines with generous deadlines; nothing is timed.
"""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
import threading
from pathlib import Path
from typing import Any

os.environ["MAVLINK20"] = "1"  # before mavutil is imported
from mavlink_support import TIMEOUT_S, MavProxy, free_udp_port, start_fly, write_session
from pymavlink import mavutil
from pymavlink.dialects.v20 import common as mavlink2

from drivers.mavlink.signing import signing_timestamp_now
from groundstation.flight import FlightState

M = mavlink2
PASSPHRASE = "labpass"
KEY = hashlib.sha256(PASSPHRASE.encode()).digest()
WRONG_KEY = hashlib.sha256(b"guess").digest()
FLIGHT_TIMEOUT_S = 600.0
N_ATTACK = 10


def _env_without_key() -> dict[str, str]:
    env = dict(os.environ)
    env.pop("FASTHEX_MAVLINK_KEY", None)
    return env


def _finish(proc: subprocess.Popen[str]) -> dict[str, Any]:
    out, err = proc.communicate(timeout=FLIGHT_TIMEOUT_S)
    assert out.strip(), f"no JSON summary (exit {proc.returncode}):\n{err[-3000:]}"
    summary: dict[str, Any] = json.loads(out)
    return summary


def _frame(key: bytes | None, msg: Any, *, sysid: int, link_id: int = 7,
           timestamp: int | None = None) -> bytes:
    """One frame from a plain pymavlink encoder, signed with ``key`` if given."""
    out: list[bytes] = []

    class _W:
        def write(self, b: bytes) -> None:
            out.append(bytes(b))

    mav = M.MAVLink(_W(), srcSystem=sysid, srcComponent=190)
    if key is not None:
        mav.signing.secret_key = key
        mav.signing.sign_outgoing = True
        mav.signing.link_id = link_id
        mav.signing.timestamp = signing_timestamp_now() if timestamp is None else timestamp
    mav.send(msg)
    return out[0]


def _land() -> Any:
    return M.MAVLink_command_long_message(1, 1, M.MAV_CMD_NAV_LAND, 0, 0, 0, 0, 0, 0, 0, 0)


class Gcs:
    """A pymavlink GCS listening on a free port; a thread keeps every message it receives."""

    def __init__(self, key: bytes | None = None) -> None:
        self.port = free_udp_port()
        self.conn = mavutil.mavlink_connection(f"udpin:127.0.0.1:{self.port}",
                                               source_system=255, source_component=190)
        if key is not None:
            self.conn.setup_signing(key, sign_outgoing=True)
        self.lock = threading.Condition()
        self.heartbeats: list[Any] = []
        self.landed: list[int] = []
        self.acks: list[tuple[int, int]] = []
        self.texts: list[str] = []
        self._done = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._done.is_set():
            msg = self.conn.recv_match(blocking=True, timeout=0.2)
            if msg is None or msg.get_type() == "BAD_DATA":
                continue
            kind = msg.get_type()
            with self.lock:
                if kind == "HEARTBEAT" and msg.get_srcSystem() == 1:
                    self.heartbeats.append(msg)
                elif kind == "EXTENDED_SYS_STATE":
                    self.landed.append(msg.landed_state)
                elif kind == "COMMAND_ACK":
                    self.acks.append((msg.command, msg.result))
                elif kind == "STATUSTEXT":
                    self.texts.append(msg.text)
                self.lock.notify_all()

    def wait(self, what: str, predicate: Any) -> None:
        with self.lock:
            assert self.lock.wait_for(predicate, TIMEOUT_S * 3), (
                what, [h.custom_mode for h in self.heartbeats[-5:]], self.acks, self.texts[-5:])

    def wait_mission(self) -> None:
        self.wait("MISSION", lambda: any(h.custom_mode == FlightState.MISSION
                                         for h in self.heartbeats))

    def wait_ack(self, command: int) -> int:
        self.wait(f"ACK {command}", lambda: any(c == command for c, _ in self.acks))
        with self.lock:
            i = next(i for i, (c, _) in enumerate(self.acks) if c == command)
            return self.acks.pop(i)[1]

    def send_raw(self, frame: bytes) -> None:
        with self.lock:  # the vehicle's address, learnt from its telemetry
            vehicle = next(iter(self.conn.clients))
        self.conn.port.sendto(frame, vehicle)

    def close(self) -> None:
        self._done.set()
        self._thread.join(timeout=5)
        self.conn.close()


def test_that_mavproxy_signed_with_the_sessions_key_lands_the_vehicle(tmp_path: Path) -> None:
    # Fixture: the session names a key file holding the lab passphrase; a 2 min hover
    (tmp_path / "lab.key").write_text(PASSPHRASE + "\n")
    (tmp_path / "lab.key").chmod(0o600)
    session = write_session(tmp_path, hover_s=120.0, key_file="lab.key")
    port = free_udp_port()
    mp = MavProxy(port, tmp_path, "--mav20")
    proc = start_fly(session, tmp_path / "f.fhr", port, env=_env_without_key())
    try:
        mp.expect(r"Detected vehicle 1:1")
        mp.type(f"signing key {PASSPHRASE}")
        # Test: once in the mission, the operator types a land command
        mp.expect(r"AP: TAKEOFF -> MISSION")
        mp.type("long MAV_CMD_NAV_LAND")
        mp.expect(r"COMMAND_ACK: NAV_LAND: ACCEPTED")
        mp.expect(r"AP: LANDING -> DISARMED")
        summary = _finish(proc)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
        mp.close()
    # Assert: landed by the operator, every MAVProxy command verified, nothing rejected
    reasons = [t.split(": ", 1)[1] for t in summary["transitions"]]
    assert "operator: land" in reasons
    assert summary["transitions"][-1].split(": ")[0].endswith("LANDING -> DISARMED")
    assert summary["mavlink_signed"] is True
    assert summary["mavlink_signed_good"] >= 1
    assert summary["mavlink_rejected_bad_signature"] == 0
    assert summary["mavlink_rejected_replay"] == 0
    assert summary["mavlink_commands"].get("ACCEPTED", 0) >= 1


def test_that_unsigned_wrong_key_stale_and_replayed_commands_are_all_rejected_and_counted(
        tmp_path: Path) -> None:
    # Fixture: the key from the environment this time; the lab GCS signs with it
    session = write_session(tmp_path, hover_s=120.0)
    gcs = Gcs(key=KEY)
    env = {**_env_without_key(), "FASTHEX_MAVLINK_KEY": PASSPHRASE}
    proc = start_fly(session, tmp_path / "f.fhr", gcs.port, env=env)
    try:
        gcs.wait_mission()
        # Test: the attacker's frames, all sent while the vehicle flies its mission
        for k in range(N_ATTACK):
            gcs.send_raw(_frame(None, _land(), sysid=66))
            gcs.send_raw(_frame(WRONG_KEY, _land(), sysid=66, link_id=k))
            gcs.send_raw(_frame(KEY, _land(), sysid=67, link_id=k,
                                timestamp=signing_timestamp_now() - 120 * 100_000 + k))
        # a recorded, correctly signed (harmless) command and its byte-exact replays
        recorded = _frame(KEY, M.MAVLink_command_long_message(
            1, 1, M.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 0, 1.0), sysid=68, link_id=3)
        gcs.send_raw(recorded)
        for _ in range(N_ATTACK):
            gcs.send_raw(recorded)
        # a signed request from the lab GCS: its ACK proves all of the above was handled
        gcs.conn.mav.command_long_send(1, 1, M.MAV_CMD_REQUEST_MESSAGE, 0,
                                       M.MAVLINK_MSG_ID_HEARTBEAT, 0, 0, 0, 0, 0, 0)
        assert gcs.wait_ack(M.MAV_CMD_REQUEST_MESSAGE) == M.MAV_RESULT_ACCEPTED
        with gcs.lock:
            assert gcs.heartbeats[-1].custom_mode == FlightState.MISSION  # still flying
        # then the lab's own land, signed
        gcs.conn.mav.command_long_send(1, 1, M.MAV_CMD_NAV_LAND, 0, 0, 0, 0, 0, 0, 0, 0)
        assert gcs.wait_ack(M.MAV_CMD_NAV_LAND) == M.MAV_RESULT_ACCEPTED
        summary = _finish(proc)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
        gcs.close()
    # Assert: 100 % of each kind rejected, counted apart in fly --json; only the lab landed
    assert summary["mavlink_signed"] is True
    assert summary["mavlink_rejected_unsigned"] == N_ATTACK
    assert summary["mavlink_rejected_bad_signature"] == N_ATTACK
    assert summary["mavlink_rejected_stale"] == N_ATTACK
    assert summary["mavlink_rejected_replay"] == N_ATTACK
    reasons = [t.split(": ", 1)[1] for t in summary["transitions"]]
    assert reasons.count("operator: land") == 1
    assert summary["transitions"][-1].split(": ")[0].endswith("LANDING -> DISARMED")


def test_that_without_a_key_a_land_is_refused_the_flight_completes_and_ends_on_the_ground(
        tmp_path: Path) -> None:
    # Fixture: no key anywhere; a 12 s hover (lockstep: a few seconds of wall time, so the
    # LAND arrives in flight)
    session = write_session(tmp_path, hover_s=12.0)
    gcs = Gcs()
    proc = start_fly(session, tmp_path / "f.fhr", gcs.port, env=_env_without_key())
    try:
        gcs.wait_mission()
        # Test
        gcs.conn.mav.command_long_send(1, 1, M.MAV_CMD_NAV_LAND, 0, 0, 0, 0, 0, 0, 0, 0)
        result = gcs.wait_ack(M.MAV_CMD_NAV_LAND)
        summary = _finish(proc)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
        gcs.close()
    # Assert: refused, counted, the mission flown to its end
    assert result == M.MAV_RESULT_DENIED
    assert summary["end_reason"] in ("mission complete", "touchdown")
    assert "operator: land" not in " ".join(summary["transitions"])
    assert summary["mavlink_signed"] is False
    assert summary["mavlink_refused_unsigned"] == 1
    # after the session: the GCS's last word from the vehicle is disarmed and on the ground,
    # repeated (the final state is announced for more than a second before the link closes)
    final = [h for h in gcs.heartbeats if h.custom_mode == FlightState.DISARMED]
    assert len(final) >= 2
    assert not gcs.heartbeats[-1].base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED
    assert gcs.heartbeats[-1].custom_mode == FlightState.DISARMED
    assert gcs.landed[-3:] == [M.MAV_LANDED_STATE_ON_GROUND] * 3
    assert M.MAV_LANDED_STATE_IN_AIR in gcs.landed  # the landed state followed the flight
    assert any("session over: DISARMED" in t for t in gcs.texts)
    # each transition went out once, in the order the loop made them
    transitions = [t for t in gcs.texts if " -> " in t]
    assert len(transitions) == len(set(transitions)) >= 4
    assert [t.split(":")[0] for t in transitions] == [
        t.split(": ")[0].split(" s ")[1] for t in summary["transitions"]]


def test_that_an_unreadable_key_file_is_one_line_and_exit_2_before_anything_opens(
        tmp_path: Path) -> None:
    session = write_session(tmp_path, hover_s=4.0)
    proc = subprocess.run(
        [sys.executable, "-m", "groundstation", "fly", str(session), "--mavlink",
         "udpout:127.0.0.1:9", "--mavlink-key-file", str(tmp_path / "missing.key"),
         "--record", str(tmp_path / "f.fhr")],
        capture_output=True, text=True, timeout=120, env=_env_without_key())
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in proc.stderr
    assert "missing.key" in lines[0] and "cannot read signing key" in lines[0]
    assert not (tmp_path / "f.fhr").exists()


def test_that_mavsdk_without_a_key_is_denied_a_land_and_then_sees_the_vehicle_disarmed_landed(
        tmp_path: Path) -> None:
    # MAVSDK 4.x (PyPI ``mavsdk``) wraps the C++ library in-process: no mavsdk_server, offline
    from mavsdk import ComponentType, Configuration, Mavsdk
    from mavsdk.plugins.action import Action, ActionError, ActionResult
    from mavsdk.plugins.telemetry import LandedState, Odometry, Telemetry

    # Fixture: MAVSDK as the GCS, listening; no key anywhere; the shared mission with a 30 s
    # hover. The flight is lockstep (as fast as the host runs it) and MAVSDK reports the system
    # only after its own handshake: a 4 s hover (1.2 s of wall time at 3.4x) was over before
    # MAVSDK had subscribed, and it first heard LANDING. 30 s leave ~9 s of wall time in air.
    session = write_session(tmp_path, hover_s=30.0, name="mavsdk-flight")
    port = free_udp_port()
    sdk = Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION))
    sdk.add_any_connection(f"udpin://127.0.0.1:{port}")
    proc = start_fly(session, tmp_path / "f.fhr", port, env=_env_without_key())
    in_air = threading.Event()
    states: list[Any] = []
    odometry: list[Any] = []
    try:
        system = sdk.first_autopilot(TIMEOUT_S)
        assert system is not None, "MAVSDK never saw the vehicle"
        telemetry, action = Telemetry(system), Action(system)

        def on_landed(state: Any, _user: Any) -> None:
            states.append(state)
            if state == LandedState.IN_AIR:
                in_air.set()

        telemetry.subscribe_landed_state(on_landed)
        telemetry.subscribe_odometry(lambda o, _u: odometry.append(o))
        assert in_air.wait(TIMEOUT_S * 3), states
        # Test: an unsigned land from a real GCS library
        try:
            action.land()
            denied: Any = None
        except ActionError as exc:
            denied = exc.result
        summary = _finish(proc)
        # Assert: after the session, MAVSDK's view is disarmed and on the ground
        armed_after, landed_after = telemetry.armed(), telemetry.landed_state()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
        sdk.destroy()
    assert denied == ActionResult.COMMAND_DENIED
    assert summary["end_reason"] in ("mission complete", "touchdown")
    assert summary["mavlink_refused_unsigned"] >= 1
    assert armed_after is False
    assert landed_after == LandedState.ON_GROUND
    assert LandedState.IN_AIR in states and states[-1] == LandedState.ON_GROUND
    # ODOMETRY's frame ids are ones MAVSDK maps (not UNDEF)
    assert odometry and odometry[-1].frame_id == Odometry.MavFrame.ESTIM_NED
    assert odometry[-1].child_frame_id == Odometry.MavFrame.BODY_NED

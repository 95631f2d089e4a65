"""The session's MAVLink wiring: key precedence, key errors, the loop's command sink, events,
and the counters that reach ``fasthex fly``'s summary."""

from __future__ import annotations

import hashlib
import math
import queue
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from config.schema import load_config_text
from groundstation import operator as op
from groundstation.gcs import (
    STATUS_BATTERY,
    STATUS_PREFLIGHT,
    STATUS_STATE,
    GcsOptions,
    LoopCommandSink,
    MavlinkKeyError,
    gcs_options,
    resolve_key,
    stats_path,
    status_event,
    summary_fields,
    summary_lines,
)
from groundstation.session_config import TelemetryConfig

HEX_KEY = "ab" * 32


@dataclass
class _Telemetry:
    mavlink_key_file: str | None = None
    mavlink_allow_unsigned: bool = False


def _files(tmp_path: Path) -> tuple[Path, Path]:
    cli, session = tmp_path / "cli.key", tmp_path / "session.key"
    cli.write_text("cli-pass\n")
    session.write_text(HEX_KEY + "\n")
    return cli, session


def test_that_the_cli_key_file_wins_over_the_sessions_which_wins_over_the_environment(
        tmp_path: Path) -> None:
    cli, session = _files(tmp_path)
    env = {"FASTHEX_MAVLINK_KEY": "env-pass"}
    key, source = resolve_key(str(cli), str(session), env)
    assert key == hashlib.sha256(b"cli-pass").digest() and source.startswith("--mavlink-key")
    key, source = resolve_key(None, str(session), env)
    assert key == bytes.fromhex(HEX_KEY) and source.startswith("telemetry.mavlink_key_file")
    key, source = resolve_key(None, None, env)
    assert key == hashlib.sha256(b"env-pass").digest() and source == "$FASTHEX_MAVLINK_KEY"
    assert resolve_key(None, None, {}) == (None, "")


def test_that_a_missing_or_empty_key_file_is_a_one_line_user_error_naming_it(
        tmp_path: Path) -> None:
    with pytest.raises(MavlinkKeyError, match=r"missing\.key: cannot read signing key.*"
                                              r"--mavlink-key-file"):
        resolve_key(str(tmp_path / "missing.key"), None, {})
    (tmp_path / "empty.key").write_text("\n")
    with pytest.raises(MavlinkKeyError, match=r"empty\.key.*telemetry\.mavlink_key_file"):
        resolve_key(None, str(tmp_path / "empty.key"), {})
    with pytest.raises(MavlinkKeyError, match=r"\$FASTHEX_MAVLINK_KEY"):
        resolve_key(None, None, {"FASTHEX_MAVLINK_KEY": "  "})
    # a named file is checked even when MAVLink is off
    with pytest.raises(MavlinkKeyError):
        gcs_options("", _Telemetry(mavlink_key_file=str(tmp_path / "missing.key")),
                    tmp_path / "f.fhr", environ={})


def test_that_the_session_yaml_takes_a_key_file_and_the_unsigned_allowance_not_a_key() -> None:
    cfg = load_config_text("schema: telemetry\nversion: 1\nmavlink_key_file: ~/lab.key\n"
                           "mavlink_allow_unsigned: true\n", TelemetryConfig,
                           schema="telemetry", file_label="session.yaml")
    assert (cfg.mavlink_key_file, cfg.mavlink_allow_unsigned) == ("~/lab.key", True)
    assert TelemetryConfig().mavlink_allow_unsigned is False  # secure by default


def test_that_the_options_carry_the_key_but_never_print_it(tmp_path: Path) -> None:
    _, session = _files(tmp_path)
    opts = gcs_options("udpout:127.0.0.1:14550", _Telemetry(str(session)), tmp_path / "f.fhr",
                       environ={})
    assert opts is not None and opts.key == bytes.fromhex(HEX_KEY)
    assert HEX_KEY not in repr(opts) and "signed=True" in repr(opts)
    assert opts.stats_path == str(tmp_path / "f.fhr.mavlink.json")
    assert gcs_options("", _Telemetry(), tmp_path / "f.fhr", environ={}) is None


def _status(phase: op.FlightPhase, preflight: bool = True) -> list[float]:
    s = [0.0] * op.STATUS_SIZE
    s[STATUS_STATE], s[STATUS_PREFLIGHT], s[STATUS_BATTERY] = float(phase), float(preflight), 15.0
    return s


def test_that_the_loop_sink_queues_accepted_requests_and_refuses_what_the_session_cannot_do(
        ) -> None:
    commands: queue.Queue[str] = queue.Queue(maxsize=1)
    status = _status(op.FlightPhase.MISSION)
    sink = LoopCommandSink(status, commands, math.radians(35.0))
    R = op.CommandResult
    assert sink.submit(op.Land()) is R.ACCEPTED and commands.get_nowait() == "land"
    assert sink.submit(op.Arm()) is R.DENIED  # in flight
    assert sink.submit(op.SetTilt(0.1)) is R.UNSUPPORTED  # the mission file drives the tilt
    assert sink.submit(op.EmergencyStop()) is R.ACCEPTED
    assert sink.submit(op.Land()) is R.TEMPORARILY_REJECTED  # queue full: not lost silently
    status[STATUS_STATE] = math.nan  # not written yet
    assert sink.submit(op.Land()) is R.TEMPORARILY_REJECTED  # PREFLIGHT


def test_that_the_loop_sink_denies_what_an_ended_session_cannot_do_and_arms_once() -> None:
    commands: queue.Queue[str] = queue.Queue(maxsize=4)
    status = _status(op.FlightPhase.ARMED)
    sink = LoopCommandSink(status, commands, math.radians(35.0))
    R = op.CommandResult
    # already armed: acknowledged, and no request the loop would refuse ("cannot arm in ARMED")
    assert sink.submit(op.Arm()) is R.ACCEPTED and commands.empty()
    # the session over (DISARMED is final in fly) or its motors cut: no arm, take-off or
    # land now or on a retry; a disarm or an emergency stop is harmless and acknowledged
    for phase in (op.FlightPhase.DISARMED, op.FlightPhase.CUT):
        status[STATUS_STATE] = float(phase)
        assert sink.submit(op.Arm()) is R.DENIED
        assert sink.submit(op.Land()) is R.DENIED
        assert sink.submit(op.Takeoff(1.0)) is R.DENIED
        assert sink.submit(op.EmergencyStop()) is R.ACCEPTED
    assert commands.get_nowait() == "cut" and commands.get_nowait() == "cut"


def test_that_event_lines_become_status_events_with_their_time_and_severity() -> None:
    ev = status_event("12.345 s TAKEOFF -> MISSION: takeoff complete", 0.0)
    assert (ev.t_s, ev.text, ev.severity) == (12.345, "TAKEOFF -> MISSION: takeoff complete",
                                              op.Severity.INFO)
    assert status_event("3.000 s LANDING -> CUT: IMU lost", 0.0).severity is \
        op.Severity.EMERGENCY
    assert status_event("FAULT 1.500 s: mocap lost", 0.0).severity is op.Severity.WARNING
    assert status_event("no time here", 7.0).t_s == 7.0


def test_that_the_counters_file_becomes_summary_keys_and_one_summary_line(
        tmp_path: Path) -> None:
    from drivers.mavlink.signing import SigningStats
    from groundstation.gcs import write_stats
    from groundstation.mavlink_bridge import BridgeStats

    record = tmp_path / "f.fhr"
    assert summary_fields(record) == {} and summary_lines(record) == []
    stats = BridgeStats(messages_out={"HEARTBEAT": 5}, frames_in=40, corrupted_in=1,
                        signing=SigningStats(10, 0, 3, 4, 5, 6), command_results={"DENIED": 2},
                        setpoint_results={}, ignored={}, events_dropped=0, no_peer_drops=0,
                        gcs_heartbeat_age_s=0.5, refused_unsigned=0, refused_out_of_range=7,
                        handler_errors=0)
    write_stats(stats_path(record), stats, GcsOptions("udpout:127.0.0.1:9", b"k" * 32,
                                                      "$FASTHEX_MAVLINK_KEY", False, ""))
    f = summary_fields(record)
    assert (f["mavlink_signed"], f["mavlink_rejected_unsigned"],
            f["mavlink_rejected_bad_signature"], f["mavlink_rejected_replay"],
            f["mavlink_rejected_stale"], f["mavlink_refused_out_of_range"],
            f["mavlink_frames_out"]) == (True, 3, 4, 5, 6, 7, 5)
    assert f["mavlink_commands"] == {"DENIED": 2}
    (line,) = summary_lines(record)
    assert "mavlink (signed)" in line and "stale 6" in line


def test_that_allowing_unsigned_commands_is_announced_as_a_warning_event(tmp_path: Path) -> None:
    from groundstation.configs import load_vehicle
    from groundstation.gcs import start_gcs

    events = tmp_path / "f.fhr.events.txt"
    events.write_text("")
    opts = GcsOptions("udpout:127.0.0.1:9", None, "", True, str(tmp_path / "s.json"),
                      final_announce_s=0.0)
    gcs = start_gcs(opts, load_vehicle("fasthex"), _status(op.FlightPhase.PREFLIGHT),
                    queue.Queue(), str(events), echo_events=False)
    try:
        assert gcs.bridge.allow_unsigned_commands and not gcs.bridge.signing
        (line,) = events.read_text().splitlines()
        assert "WARNING unsigned" in line and "mavlink_allow_unsigned" in line
    finally:
        gcs.close()
    assert (tmp_path / "s.json").exists()


def test_that_a_link_that_cannot_open_is_an_event_line_not_a_lost_record(tmp_path: Path) -> None:
    import socket

    from groundstation.configs import load_vehicle
    from groundstation.gcs import start_gcs

    events = tmp_path / "events.txt"
    events.write_text("")
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as taken:
        taken.bind(("127.0.0.1", 0))
        port = taken.getsockname()[1]
        opts = GcsOptions(f"udpin:127.0.0.1:{port}", None, "", False, "")
        gcs = start_gcs(opts, load_vehicle("fasthex"), _status(op.FlightPhase.PREFLIGHT),
                        queue.Queue(), str(events), echo_events=False)
    assert gcs is None
    (line,) = events.read_text().splitlines()
    assert f"udpin:127.0.0.1:{port}" in line and "no link" in line


def test_that_the_environment_is_not_read_when_mavlink_is_off(tmp_path: Path) -> None:
    assert gcs_options("", _Telemetry(), tmp_path / "f.fhr",
                       environ={"FASTHEX_MAVLINK_KEY": " "}) is None


def test_that_the_status_ring_hands_out_each_phase_change_once_in_order() -> None:
    # Fixture
    status = _status(op.FlightPhase.PREFLIGHT)
    P = op.FlightPhase
    # Test / Assert: two changes, read; one more; then more than the ring holds
    op.post_transition(status, 1.0, P.ARMED)
    op.post_transition(status, 1.5, P.TAKEOFF)
    first, seen = op.transitions_since(status, 0)
    assert first == [(1.0, P.ARMED), (1.5, P.TAKEOFF)] and seen == 2
    assert status[op.STATUS_STATE] == P.TAKEOFF  # the phase now follows every change
    op.post_transition(status, 2.0, P.MISSION)
    assert op.transitions_since(status, seen) == ([(2.0, P.MISSION)], 3)
    for k in range(op.TRANSITION_RING + 4):
        op.post_transition(status, 3.0 + k, P.LANDING if k % 2 else P.MISSION)
    late, seen = op.transitions_since(status, 3)
    assert seen == 3 + op.TRANSITION_RING + 4 and len(late) == op.TRANSITION_RING
    assert late[0][0] == 3.0 + 4 and late[-1] == (3.0 + op.TRANSITION_RING + 3, P.LANDING)
    # a corrupted entry is skipped, never raised
    status[5] = 99.0
    assert all(p in P for _, p in op.transitions_since(status, 0)[0])


@pytest.mark.parametrize("first_pass", ["before", "after"])
def test_that_a_whole_flight_between_two_telemetry_passes_reaches_the_gcs_phase_by_phase(
        tmp_path: Path, first_pass: str) -> None:
    from mavlink_support import free_udp_port
    from pymavlink import mavutil

    from groundstation.configs import load_vehicle
    from groundstation.gcs import start_gcs
    from groundstation.record import RECORD_DTYPE

    # Fixture: a GCS listening; the loop flies a whole (lockstep-fast) mission between two
    # passes of a starved telemetry process, which then drains 50 rows at once (or before the
    # telemetry process's first pass)
    port = free_udp_port()
    gcs_conn = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=255)
    events = tmp_path / "f.fhr.events.txt"
    events.write_text("")
    opts = GcsOptions(f"udpout:127.0.0.1:{port}", None, "", False, str(tmp_path / "s.json"),
                      final_announce_s=0.0)
    status = _status(op.FlightPhase.PREFLIGHT)
    gcs = start_gcs(opts, load_vehicle("fasthex"), status, queue.Queue(), str(events),
                    echo_events=False)
    assert gcs is not None
    rows = np.zeros(50, RECORD_DTYPE)
    rows["t_s"] = np.arange(50) * 0.1
    P = op.FlightPhase
    try:
        if first_pass == "before":  # else the telemetry process's first pass comes late
            gcs.publish(rows[:1], [])
        # the GCS has seen the vehicle in PREFLIGHT
        assert gcs_conn.recv_match(type="HEARTBEAT", blocking=True, timeout=10.0) is not None
        for t_s, phase in ((0.5, P.ARMED), (1.0, P.TAKEOFF), (2.0, P.MISSION),
                           (3.0, P.LANDING), (4.0, P.DISARMED)):
            op.post_transition(status, t_s, phase)
        # Test
        gcs.publish(rows, [])
        modes: list[int] = [P.PREFLIGHT]
        deadline = time.monotonic() + 10.0
        while (not modes or modes[-1] != P.DISARMED) and time.monotonic() < deadline:
            msg = gcs_conn.recv_match(type="HEARTBEAT", blocking=True, timeout=0.5)
            if msg is not None and (not modes or modes[-1] != msg.custom_mode):
                modes.append(msg.custom_mode)
    finally:
        gcs.close()
        gcs_conn.close()
    # Assert: every phase went out, in order, though only the last was current at the pass
    assert modes == [P.PREFLIGHT, P.ARMED, P.TAKEOFF, P.MISSION, P.LANDING, P.DISARMED]

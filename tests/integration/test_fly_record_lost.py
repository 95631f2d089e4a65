"""No flight without its record: a record the telemetry process cannot open ends the session
before anything is armed, a telemetry process that dies in flight lands the vehicle, and the
link and record options are checked before anything opens.

Real lockstep flights through the byte path (tests/flight_support.py); the telemetry process is
a real child process, killed with SIGKILL as the kernel's OOM killer would.
"""

from __future__ import annotations

import multiprocessing
import os
import signal
from pathlib import Path

import pytest

from groundstation.cli import main
from groundstation.flight import FlightState
from groundstation.session import FlightSession, SessionError
from tests.flight_support import SESSION, SHORT_MISSION, short_session


def _telemetry_child() -> multiprocessing.process.BaseProcess:
    (child,) = [p for p in multiprocessing.active_children() if p.name == "fasthex-telemetry"]
    return child


def test_that_a_record_that_cannot_be_opened_ends_the_session_before_arming(
        tmp_path: Path) -> None:
    # Fixture: the record's path is a folder (the telemetry process's open fails)
    cfg, params, mission = short_session(tmp_path)
    folder = tmp_path / "a-folder.fhr"
    folder.mkdir()
    events: list[str] = []
    # Test
    with pytest.raises(SessionError) as err:
        FlightSession(cfg, params, mission, record_path=folder, echo_events=False,
                      on_event=events.append).run()
    # Assert: its reason in one line, and nothing was armed
    assert str(err.value) == f"cannot write the flight record {folder}: Is a directory"
    assert not any("ARMED" in e for e in events)
    assert not multiprocessing.active_children()


def test_that_a_telemetry_process_dying_in_flight_lands_the_vehicle(tmp_path: Path) -> None:
    # Fixture: the telemetry process killed once the mission starts (the hover, 0.8 m up)
    cfg, params, mission = short_session(tmp_path)
    killed: list[str] = []

    def on_event(line: str) -> None:
        if "TAKEOFF -> MISSION" in line and not killed:
            os.kill(_telemetry_child().pid, signal.SIGKILL)
            killed.append(line)

    record = tmp_path / "lost.fhr"
    # Test
    outcome = FlightSession(cfg, params, mission, record_path=record, echo_events=False,
                            on_event=on_event).run()
    # Assert: a failsafe landing on the estimate, named, soon after the kill (the loop looks
    # every LINK_CHECK_TICKS ticks; the kill lands within a few ms of wall time, ~10x that
    # in lockstep flight time, but a loaded host takes longer to end the process: 1.1 s of
    # flight seen beside the full test suite), well before the mission would end, then the
    # touchdown
    trs = outcome.result.transitions
    mission_t = next(tr.t_s for tr in trs if tr.to_state is FlightState.MISSION)
    lost = [tr for tr in trs if tr.reason.startswith("failsafe: flight record lost")]
    assert len(lost) == 1, [tr.reason for tr in trs]
    assert lost[0].reason == ("failsafe: flight record lost: the telemetry process exited "
                              "(exit code -9)")
    assert (lost[0].from_state, lost[0].to_state) == (FlightState.MISSION, FlightState.LANDING)
    assert mission_t < lost[0].t_s < mission_t + 3.0    # the hover lasts 4 s
    assert trs[-1].to_state is FlightState.DISARMED and trs[-1].reason == "touchdown"
    assert outcome.result.end_reason.startswith("failsafe: flight record lost")
    # the events the dead process could not write are in the events file all the same
    events = (tmp_path / "lost.fhr.events.txt").read_text()
    assert "FAULT" in events and "flight record lost" in events
    assert "LANDING -> DISARMED: touchdown" in events


def test_that_bad_link_and_record_options_stop_fly_before_anything_opens(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # Fixture: the short session, and a copy with a MAVLink port out of range
    (tmp_path / "short-hover.yaml").write_text(SHORT_MISSION)
    session = tmp_path / "s.yaml"
    text = SESSION.format(seed=3, faults="", corrupt=0.0, zmax=2.5, servo_action="hold")
    session.write_text(text)
    bad_link = tmp_path / "bad-link.yaml"
    bad_link.write_text(text.replace("telemetry:\n", 'telemetry:\n  mavlink: "udpout:h:99999"\n'))
    folder = tmp_path / "records"
    folder.mkdir()
    # Test / Assert: one line each, exit 2, no child process
    assert main(["fly", str(session), "--mavlink", "bogus:1:2"]) == 2
    assert capsys.readouterr().err == ("fasthex: --mavlink bogus:1:2: expected udpout:HOST:PORT "
                                       "or udpin:HOST:PORT\n")
    assert main(["fly", str(bad_link)]) == 2
    line = bad_link.read_text().splitlines().index('  mavlink: "udpout:h:99999"') + 1
    assert capsys.readouterr().err == (
        f"fasthex: config error: {bad_link}:{line}: telemetry.mavlink: udpout:h:99999: port "
        "99999 out of range; expected udpout:HOST:PORT or udpin:HOST:PORT\n")
    assert main(["fly", str(session), "--record", str(folder)]) == 2
    assert capsys.readouterr().err == (f"fasthex: the flight record {folder} is a folder; "
                                       "expected a file path (--record or telemetry.record)\n")
    # a device (/dev/full filled all the memory when the summary read it back) and a place
    # where no file can be made
    assert main(["fly", str(session), "--record", "/dev/null"]) == 2
    assert capsys.readouterr().err == (
        "fasthex: the flight record /dev/null is not a regular file (a device or a pipe); "
        "expected a file path (--record or telemetry.record)\n")
    assert main(["fly", str(session), "--record", "/proc/x.fhr"]) == 2
    assert capsys.readouterr().err == ("fasthex: cannot write the flight record's file "
                                       "/proc/x.fhr: No such file or directory\n")
    assert not list(folder.iterdir())  # the checks leave no file behind
    assert not multiprocessing.active_children()

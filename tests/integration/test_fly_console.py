"""What an operator sees of `fasthex fly` in a real terminal (a pseudo-terminal), and where the
record lands.

The terminal test reads the bytes the program writes and plays them on a small screen model
(carriage return, newline, ANSI erase-line), so what is checked is the text left on the screen.
"""

from __future__ import annotations

import fcntl
import json
import os
import pty
import re
import struct
import subprocess
import sys
import termios
import threading
from pathlib import Path

from flight_support import SESSION, SHORT_MISSION, short_session
from terminal_support import screen

from groundstation.session import FlightSession

STATES = ("PREFLIGHT", "ARMED", "TAKEOFF", "MISSION", "LANDING", "DISARMED", "CUT")
STATUS_RE = re.compile(rf"^({'|'.join(STATES)})\s+(\d+\.\d|--) s  pos\. error ")
NAN_INF_RE = re.compile(r"\b(nan|inf)\b", re.IGNORECASE)


def _session(tmp_path: Path, telemetry: str = 'rerun: "off"') -> Path:
    # the short hover with a 1.5 s tilt hold: every phase of a flight in about 8 s
    (tmp_path / "short-hover.yaml").write_text(SHORT_MISSION.replace("duration_s: 4.0",
                                                                      "duration_s: 1.5"))
    text = SESSION.format(seed=3, faults="", corrupt=0.0, zmax=2.5, servo_action="hold")
    path = tmp_path / "short.yaml"
    path.write_text(text.replace('rerun: "off"', telemetry))
    return path


def _fly_in_terminal(args: list[str], cwd: Path) -> tuple[int, str]:
    master, slave = pty.openpty()
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 50, 160, 0, 0))
    proc = subprocess.Popen([sys.executable, "-m", "groundstation", "fly", *args],
                            stdin=slave, stdout=slave, stderr=slave, cwd=cwd, close_fds=True)
    os.close(slave)
    out = bytearray()

    def drain() -> None:  # a terminal reads what the program writes
        while True:
            try:
                data = os.read(master, 4096)
            except OSError:
                return
            if not data:
                return
            out.extend(data)

    reader = threading.Thread(target=drain, daemon=True)
    reader.start()
    try:
        code = proc.wait(timeout=120)
    finally:
        reader.join(timeout=5)
        os.close(master)
    return code, out.decode(errors="replace")


def test_that_a_flight_in_a_terminal_shows_each_event_on_its_own_line_and_one_summary(
        tmp_path: Path) -> None:
    # Fixture
    session = _session(tmp_path)
    record = tmp_path / "flight.fhr"
    # Test
    code, raw = _fly_in_terminal([str(session), "--record", str(record)], tmp_path)
    # Assert
    shown = screen(raw)
    text = "\n".join(shown)
    assert code == 0, text
    events = [e for e in record.with_name(record.name + ".events.txt").read_text().splitlines()
              if not e.startswith(("session ended:", "emulated board at exit:"))]
    assert len(events) >= 11  # device, six preflight checks, five transitions
    # every event on its own screen line, in the order of the events file
    positions = [shown.index(e) for e in events]
    assert positions == sorted(positions)
    # the status line was live while flying, and never shares a line with an event
    status_frames = [seg for seg in re.split(r"[\r\n]|\x1b\[2K", raw) if STATUS_RE.match(seg)]
    # (rewritten 5 times a second of wall time, only when its text changes: before take-off
    # its time reads "--", so that part of a lockstep flight may give one frame; the flight's
    # frames count its progress)
    flying = [seg for seg in status_frames if seg.startswith(("TAKEOFF", "MISSION", "LANDING"))]
    assert len(flying) >= 3, status_frames
    times = [float(STATUS_RE.match(seg).group(2)) for seg in flying]  # type: ignore[union-attr]
    assert times == sorted(times) and times[-1] > times[0], flying
    for seg in re.split(r"[\r\n]", raw):
        if "pos. error" in seg:
            assert not any(e in seg for e in events), seg
    # ... and is erased at the end: nothing stale is left above or below the summary
    assert not [line for line in shown if STATUS_RE.match(line)]
    # events are printed when they happen: arming is on screen before take-off is in status
    armed = raw.index("PREFLIGHT -> ARMED")
    assert armed < min(raw.index(s) for s in status_frames if s.startswith("TAKEOFF"))
    assert not NAN_INF_RE.search(raw), NAN_INF_RE.search(raw)
    assert text.count("Flight summary:") == 1 and text.count("session ended:") == 1
    assert "session ended: mission complete" in text
    assert re.search(r"position error, mean\s+mm\s+\d+\.\d\d", text)
    # a path too long for 79 columns goes whole onto the next line (never split)
    assert re.search(rf"flight record:\s+{re.escape(str(record))}\n", text), text


def test_that_the_session_record_path_is_honoured_and_record_overrides_it(
        tmp_path: Path) -> None:
    # Fixture: a session that names its record (relative to the session file, with the
    # session's name in it); the flight runs in another working directory
    session = _session(tmp_path, 'rerun: "off"\n  record: out/{session}-test.fhr')
    elsewhere = tmp_path / "cwd"
    elsewhere.mkdir()

    def fly(*extra: str) -> dict[str, object]:
        done = subprocess.run([sys.executable, "-m", "groundstation", "fly", str(session),
                               "--json", *extra], cwd=elsewhere, capture_output=True,
                              text=True, timeout=120)
        assert done.returncode == 0, done.stderr
        return dict(json.loads(done.stdout))

    # Test
    configured = fly()
    override = tmp_path / "elsewhere" / "cli.fhr"
    overridden = fly("--record", str(override))
    # Assert
    expected = tmp_path / "out" / "short-hover-emulated-test.fhr"
    assert Path(str(configured["record"])) == expected and expected.is_file()
    assert Path(str(overridden["record"])) == override and override.is_file()
    assert list(elsewhere.iterdir()) == []  # nothing under the working directory
    # --json: counts are integers, measurements rounded to their resolution
    assert isinstance(configured["ticks"], int) and isinstance(configured["all_ticks"], int)
    assert configured["all_spin_within_limits"] == 1
    mean_mm = configured["all_pos_err_mean_mm"]
    assert isinstance(mean_mm, float) and round(mean_mm, 2) == mean_mm
    for key, value in configured.items():
        if isinstance(value, float):
            assert len(repr(value).split(".")[-1]) <= 6, (key, value)


def test_that_a_fault_that_changes_no_state_is_an_event_when_it_happens(tmp_path: Path) -> None:
    # Fixture: a silent servo with the hold action records a fault and stays in MISSION
    from flight_support import fly

    # Test
    out = fly(tmp_path, faults="servo-silent@5.0", servo_action="hold")
    # Assert: told once, in time order with the transitions around it
    fault = next(f for f in out.result.faults if "tilt servo fault: holding" in f)
    events = out.events_path.read_text().splitlines()
    assert events.count(f"FAULT {fault}") == 1
    told_at = events.index(f"FAULT {fault}")
    assert "ARMED -> TAKEOFF" in " ".join(events[:told_at])  # the fault comes at 5 s
    assert "-> DISARMED" in " ".join(events[told_at:])


def test_that_the_status_line_shows_the_time_since_take_off(tmp_path: Path) -> None:
    """The status line's time is the flight's (README): ``--`` before take-off, then counted
    from take-off; it showed the session's time (``TAKEOFF 7.0 s`` for a take-off that
    started at 2.0 s). Lockstep: each transition event comes at a known session time, with the
    status line as the loop last wrote it (every 50 ticks)."""
    # Fixture
    cfg, params, mission = short_session(tmp_path)
    seen: list[tuple[str, str]] = []  # (event, the status line when it was told)

    def on_event(text: str) -> None:
        seen.append((text, session.loop.status if session.loop is not None else ""))

    session = FlightSession(cfg, params, mission, record_path=tmp_path / "status.fhr",
                            echo_events=False, on_event=on_event, dashboard="off")
    # Test
    outcome = session.run()
    # Assert
    assert outcome.result.end_reason == "mission complete"
    at = {m.group(2): (float(m.group(1)), status) for text, status in seen
          if (m := re.match(r"(\d+\.\d+) s (\w+ -> \w+):", text))}
    takeoff_s, before = at["ARMED -> TAKEOFF"]
    assert re.match(r"ARMED\s+-- s  pos\. error ", before), before  # no flight time yet
    mission_s, during = at["TAKEOFF -> MISSION"]
    m = re.match(r"TAKEOFF\s+(\d+\.\d) s  pos\. error ", during)
    assert m is not None, during
    # written within the last 50 ticks (0.1 s) before the transition, counted from take-off
    assert mission_s - takeoff_s - 0.15 <= float(m.group(1)) <= mission_s - takeoff_s, during


def test_that_an_emulated_flight_that_crashed_exits_1_with_the_truths_account(
        tmp_path: Path) -> None:
    # Fixture: the planned landing with every rotor at half thrust from 0.5 s into it (the
    # vehicle comes down at 1.3 m/s, touches down, and the session ends "normally": it exited
    # 0), and the Flight-Ctrl cable pulled in the hover (the motors stop 0.7 m up; that the
    # vehicle then fell only the emulated vehicle knows)
    session = _session(tmp_path)
    text = session.read_text()
    assert "faults: []" in text

    def fly(faults: str, *extra: str) -> subprocess.CompletedProcess[str]:
        session.write_text(text.replace("faults: []", f'faults: ["{faults}"]'))
        return subprocess.run([sys.executable, "-m", "groundstation", "fly", str(session),
                               "--record", str(tmp_path / "crash.fhr"), *extra],
                              capture_output=True, text=True, timeout=120)

    # Test
    hard = fly("rotor-thrust@7.5:0.5")
    fall = fly("fc-disconnect@5", "--json")
    # Assert: exit 1 both; the hard landing's summary says the session ended normally, then
    # the truth and the CRASH
    assert hard.returncode == 1, hard.stderr
    words = " ".join(hard.stdout.split())   # the summary wraps at 79 columns
    assert " session ended: touchdown " in words or " session ended: mission complete " in words
    assert re.search(r" CRASH: a touchdown at 1\.\d\d m/s \(a safe one is <= 1 m/s\) ", words), \
        hard.stdout
    assert fall.returncode == 1
    summary = json.loads(fall.stdout)
    assert summary["truth_landed"] is False and summary["truth_height_m"] > 0.5
    assert summary["truth_touchdowns"] == 0
    assert summary["truth_crash"].startswith(
        f"the session ended {summary['truth_height_m']:.2f} m up with the motors stopped: a "
        "fall")

"""Stop signals as a terminal, ``timeout`` and systemd send them, to a `fasthex fly` that runs in a
real pseudo-terminal as its controlling terminal.

- Ctrl-C typed into the terminal: the line discipline sends SIGINT to the whole foreground
  process group (the ground station and its telemetry process; a realtime flight's servo
  process too: a lockstep flight serves the servo in its own thread);
- SIGTERM to the process group (``timeout``, ``kill -TERM -PGID``; systemd signals every process
  of the unit); ``timeout`` itself, which sends it to the command and then to the group (the
  same signal twice at once is one request);
- SIGHUP: the terminal closes (the master side of the pty is closed).

Each must land the vehicle (``-> LANDING -> DISARMED``) with the end reason naming the signal,
cut nothing, and leave no process, temp dir, pty or symlink behind; a second signal cuts.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import pty
import signal
import subprocess
import sys
import termios
import threading
import time
from pathlib import Path

import pytest
from flight_support import SESSION, SHORT_MISSION

from groundstation.record import read_record
from groundstation.signals import REPEAT_WINDOW_S


def _rows(path: Path) -> int:
    try:
        return len(read_record(path).rows)
    except (OSError, ValueError):
        return 0


def _take_terminal() -> None:
    """In the child: a new session whose controlling terminal is the pty on fd 0, and the stop
    and job-control signals as a shell leaves them for a foreground job (default action, not
    blocked; a test run from a script's ``&`` inherits SIGINT and SIGQUIT ignored)."""
    os.setsid()
    fcntl.ioctl(0, termios.TIOCSCTTY, 0)
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP, signal.SIGQUIT, signal.SIGTSTP,
                signal.SIGTTIN, signal.SIGTTOU):
        signal.signal(sig, signal.SIG_DFL)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, (signal.SIGINT, signal.SIGTERM, signal.SIGHUP))


def _processes_mentioning(text: str) -> list[int]:
    pids = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        with contextlib.suppress(OSError):
            cmd = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
            if text in cmd:
                pids.append(int(entry.name))
    return pids


class TerminalFlight:
    """`fasthex fly` on a lockstep session hovering for a minute, in a pty of its own
    (``clock="realtime"``: the same session on the wall clock, its servo in a process)."""

    def __init__(self, tmp_path: Path, name: str, clock: str = "lockstep",
                 prefix: tuple[str, ...] = ()) -> None:
        self.tmp = tmp_path / "tmp"  # TMPDIR of the flight: its session dir lands here
        self.tmp.mkdir()
        (tmp_path / "short-hover.yaml").write_text(
            SHORT_MISSION.replace("duration_s: 4.0", "duration_s: 60.0"))
        session = tmp_path / f"{name}.yaml"
        session.write_text(SESSION.format(seed=2, faults="", corrupt=0.0, zmax=2.5,
                                          servo_action="hold").replace(
            "clock: lockstep", f"clock: {clock}"))
        self.record = tmp_path / f"{name}.fhr"
        self.events = Path(str(self.record) + ".events.txt")
        self.master, slave = pty.openpty()
        env = dict(os.environ, TMPDIR=str(self.tmp))
        self.proc = subprocess.Popen(
            [*prefix, sys.executable, "-m", "groundstation", "fly", str(session), "--record",
             str(self.record), "--rerun", "off"],
            stdin=slave, stdout=slave, stderr=slave, env=env, preexec_fn=_take_terminal,
            close_fds=True)
        os.close(slave)
        self.output = bytearray()
        self._reader = threading.Thread(target=self._drain, daemon=True)
        self._reader.start()

    def _drain(self) -> None:  # a terminal reads what the program writes
        while True:
            try:
                data = os.read(self.master, 4096)
            except OSError:
                return
            if not data:
                return
            self.output += data

    def wait_airborne(self) -> None:
        deadline = time.monotonic() + 120.0
        while _rows(self.record) < 3000 and time.monotonic() < deadline:  # 6 s of ticks
            time.sleep(0.05)  # polling the record another process writes, bounded
        assert _rows(self.record) >= 3000, self.output.decode(errors="replace")

    def type_ctrl_c(self) -> None:
        os.write(self.master, b"\x03")

    def hang_up(self) -> None:
        os.close(self.master)
        self.master = -1

    def signal_group(self, sig: int) -> None:
        os.killpg(self.proc.pid, sig)

    def wait(self) -> int:
        try:
            return self.proc.wait(timeout=120)
        finally:
            self._reader.join(timeout=5)
            if self.master >= 0:
                os.close(self.master)

    def assert_nothing_left(self) -> None:
        leftovers = list(self.tmp.iterdir())
        assert leftovers == [], leftovers  # session dir with its pty symlinks removed
        deadline = time.monotonic() + 10.0
        while _processes_mentioning(str(self.tmp)) and time.monotonic() < deadline:
            time.sleep(0.05)  # the emulator's orderly stop, bounded
        assert _processes_mentioning(str(self.tmp)) == []
        assert _processes_mentioning(str(self.record)) == []  # telemetry process gone


def _assert_landed(flight: TerminalFlight, signame: str) -> None:
    events = flight.events.read_text()
    assert "operator stop: landing" in events, events
    # the events in full on a failure (pytest cuts a long string in the comparison)
    assert "-> LANDING: operator: land" in events, events
    assert "LANDING -> DISARMED: touchdown" in events, events
    assert "CUT" not in events, events
    assert f"session ended: operator: land (on {signame})" in events, events
    rows = read_record(flight.record).rows
    assert rows["pos_w_m"][-1][2] < 0.15  # on the ground (start height 0.1 m)


@pytest.mark.parametrize(("key", "signame"), [(b"\x03", "SIGINT"), (b"\x1c", "SIGQUIT")],
                         ids=["ctrl-c", "ctrl-backslash"])
def test_that_ctrl_c_typed_in_the_terminal_lands(tmp_path: Path, key: bytes, signame: str
                                                 ) -> None:
    # Ctrl-\ too: by default SIGQUIT kills every process of the job (the ground station in the
    # air, its telemetry process with the record unfinished); in a flight it is a stop
    flight = TerminalFlight(tmp_path, signame)
    flight.wait_airborne()
    os.write(flight.master, key)  # as typed: the line discipline signals the foreground group
    assert flight.wait() == 1  # landed early: not the planned end
    _assert_landed(flight, signame)
    flight.assert_nothing_left()
    # nothing of the job died of it: multiprocessing's resource tracker (a child in the same
    # group) killed by Ctrl-\ was relaunched and flooded the console with KeyErrors
    output = flight.output.decode(errors="replace")
    assert "Traceback" not in output and "resource_tracker" not in output, output


@pytest.mark.exclusive  # a realtime flight: a loaded host's IMU gap would cut it
def test_that_ctrl_c_in_a_realtime_flight_lands_and_its_servo_process_holds_on(
        tmp_path: Path) -> None:
    """A realtime flight serves its servo from a process of its own, in the same foreground
    group: Ctrl-C reaches it too, and it must ignore it (the flight state machine lands; the
    servo keeps answering until it is told to stop), or the landing becomes a servo fault."""
    flight = TerminalFlight(tmp_path, "ctrl-c-realtime", clock="realtime")
    flight.wait_airborne()
    flight.type_ctrl_c()
    assert flight.wait() == 1
    _assert_landed(flight, "SIGINT")
    events = flight.events.read_text()
    assert "servo fault" not in events, events
    assert "faults:        none" in flight.output.decode(errors="replace")
    flight.assert_nothing_left()


def test_that_sigterm_to_the_process_group_lands(tmp_path: Path) -> None:
    flight = TerminalFlight(tmp_path, "term")
    flight.wait_airborne()
    flight.signal_group(signal.SIGTERM)
    assert flight.wait() == 1
    _assert_landed(flight, "SIGTERM")
    flight.assert_nothing_left()


def test_that_timeout_lands_though_it_sends_its_signal_twice(tmp_path: Path) -> None:
    """GNU ``timeout`` sends its signal to the command, then to the command's process group:
    SIGTERM twice within microseconds (often merged into one pending signal; the next test
    delivers them apart). Either way one request: land, not land and then cut."""
    flight = TerminalFlight(tmp_path, "timeout", prefix=("timeout", "-s", "TERM", "600"))
    flight.wait_airborne()
    os.kill(flight.proc.pid, signal.SIGALRM)  # timeout's own timer signal: it times out now
    assert flight.wait() == 124  # timeout's status for "the command timed out"
    events = flight.events.read_text()
    assert "-> LANDING: operator: land" in events
    assert "LANDING -> DISARMED: touchdown" in events
    assert "CUT" not in events, events
    assert "session ended: operator: land (on SIGTERM" in events  # one or both were seen
    rows = read_record(flight.record).rows
    assert rows["pos_w_m"][-1][2] < 0.15  # on the ground (start height 0.1 m)
    flight.assert_nothing_left()


def test_that_sigterm_twice_at_once_lands_as_timeout_on_a_loaded_host_sends_it(
        tmp_path: Path) -> None:
    """The two sends of ``timeout`` reach the ground station as one pending signal when they
    come close enough, and as two when ``timeout`` is preempted between them (a loaded host:
    seen in a realtime flight under CPU hogs, landed then cut 2 ms later). Here the second
    comes 20 ms after the first: two deliveries, one request."""
    flight = TerminalFlight(tmp_path, "term-twice")
    flight.wait_airborne()
    os.kill(flight.proc.pid, signal.SIGTERM)
    time.sleep(0.02)  # well inside the repeat window (0.1 s), long enough to be delivered apart
    os.killpg(flight.proc.pid, signal.SIGTERM)
    assert flight.wait() == 1
    _assert_landed(flight, "SIGTERM, SIGTERM")
    flight.assert_nothing_left()


def test_that_closing_the_terminal_lands(tmp_path: Path) -> None:
    flight = TerminalFlight(tmp_path, "hup")
    flight.wait_airborne()
    flight.hang_up()  # the kernel sends SIGHUP to the session's foreground group
    assert flight.wait() == 1
    _assert_landed(flight, "SIGHUP")
    flight.assert_nothing_left()


@pytest.mark.exclusive  # a realtime flight: a loaded host's IMU gap would cut it
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_that_a_second_signal_cuts(tmp_path: Path, sig: int) -> None:
    # realtime: a person's second press comes after the repeat window (0.1 s) and while the
    # landing (3 s) still runs; a lockstep flight lands in ~0.35 s of wall time
    flight = TerminalFlight(tmp_path, f"cut-{int(sig)}", clock="realtime")
    flight.wait_airborne()
    flight.signal_group(sig)
    sent = time.monotonic()
    n = _rows(flight.record)
    deadline = time.monotonic() + 60.0
    while _rows(flight.record) < n + 250 and time.monotonic() < deadline:  # 0.5 s later
        time.sleep(0.05)
    time.sleep(max(0.0, sent + 3 * REPEAT_WINDOW_S - time.monotonic()))  # past the window
    flight.signal_group(sig)
    assert flight.wait() == 1
    events = flight.events.read_text()
    assert "-> LANDING: operator: land" in events
    assert "-> CUT: operator: second stop request" in events, events
    assert "CUT -> DISARMED" in events
    flight.assert_nothing_left()


#: A job-control shell, as far as a test needs one: it runs the command as a foreground job
#: (its own process group, the terminal's foreground), and when the job stops (Ctrl-Z) it says
#: so and a second later continues it, as an operator typing ``fg`` would. (A ground station
#: that is its terminal's session leader cannot be stopped by Ctrl-Z at all: the kernel
#: discards the terminal's stop signals to an orphaned process group.)
JOB_SHELL = r"""
import os, signal, sys, time
argv = sys.argv[1:]
pid = os.fork()
if pid == 0:
    os.setpgid(0, 0)
    os.execvp(argv[0], argv)
os.setpgid(pid, pid)
signal.signal(signal.SIGTTOU, signal.SIG_IGN)
os.tcsetpgrp(0, pid)
while True:
    _, status = os.waitpid(pid, os.WUNTRACED)
    if os.WIFSTOPPED(status):
        print("[job stopped]", flush=True)
        time.sleep(1.0)
        os.tcsetpgrp(0, pid)
        os.killpg(pid, signal.SIGCONT)
        continue
    sys.exit(os.waitstatus_to_exitcode(status))
"""


def _stopped_processes_mentioning(text: str) -> list[int]:
    stopped = []
    for pid in _processes_mentioning(text):
        with contextlib.suppress(OSError):
            stat = Path(f"/proc/{pid}/stat").read_text()
            if stat[stat.rindex(")") + 2] in "Tt":
                stopped.append(pid)
    return stopped


@pytest.mark.exclusive  # a realtime flight: a loaded host's IMU gap would cut it
def test_that_ctrl_z_in_flight_is_refused_and_the_flight_goes_on(tmp_path: Path) -> None:
    """Ctrl-Z sends SIGTSTP to the foreground job: a suspended ground station stops commanding
    the motors, and the board's watchdog stops them in the air 0.25 s later (seen: a realtime
    flight stopped at 0.8 m for 3.6 s fell and ended "IMU stream lost" on ``fg``). The flight
    must go on, no process of the job may stay stopped (the servo process is in the group),
    and the operator is told; Ctrl-C then lands as usual."""
    flight = TerminalFlight(tmp_path, "ctrl-z", clock="realtime",
                            prefix=(sys.executable, "-c", JOB_SHELL))
    flight.wait_airborne()
    os.write(flight.master, b"\x1a")  # Ctrl-Z, as typed: the line discipline sends SIGTSTP
    n = _rows(flight.record)
    deadline = time.monotonic() + 30.0
    while (_rows(flight.record) < n + 500 and flight.proc.poll() is None
           and time.monotonic() < deadline):  # a second of flight after it
        time.sleep(0.05)
    assert _stopped_processes_mentioning(str(flight.record)) == []
    flight.type_ctrl_c()
    assert flight.wait() == 1
    output = flight.output.decode(errors="replace")
    assert "[job stopped]" not in output, output
    _assert_landed(flight, "SIGINT")
    events = flight.events.read_text()
    assert "operator Ctrl-Z: refused" in events, events
    assert "servo fault" not in events and "IMU stream lost" not in events, events
    assert "operator Ctrl-Z: refused" in output  # on the operator's screen too
    flight.assert_nothing_left()

"""A stop signal while `fasthex fly` starts: one message saying nothing was armed and the exit
code of any stopped session (1), wherever in the start-up it comes. A Ctrl-C while the
session's files loaded (~0.8 s in) gave ``fasthex: interrupted`` and 130, one while the
emulated vehicle started (~2 s in) ``...: nothing was armed`` and 1.

The flight runs in a driver that holds it at one start-up stage (its files loading, or the
emulated vehicle just started) until the test has sent its signal from outside: the stage is
certain, not a guess of how long an interpreter takes to get there on a loaded host.
"""

from __future__ import annotations

import signal
import subprocess
import sys
from pathlib import Path

import pytest
from flight_support import SESSION, SHORT_MISSION

#: ``fasthex fly ARGS`` held at STAGE: it tells the test on stderr, then waits 2 s for a signal
DRIVER = r"""
import sys, time
import groundstation.configs as configs
import groundstation.session as session

stage = sys.argv[1]

def hold():
    print(f"driver: holding at {stage}", file=sys.stderr, flush=True)
    time.sleep(2.0)  # the test's signal comes in here

if stage == "loading":
    load_vehicle = configs.load_vehicle

    def held_load_vehicle(*args, **kwargs):
        hold()
        return load_vehicle(*args, **kwargs)

    configs.load_vehicle = held_load_vehicle
else:
    class HeldEmulator(session.EmulatorProcess):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            hold()

    session.EmulatorProcess = HeldEmulator

from groundstation.cli import main
sys.exit(main(["fly", *sys.argv[2:]]))
"""


def _fly_held(tmp_path: Path, stage: str, sig: int) -> tuple[int, str, Path]:
    (tmp_path / "short-hover.yaml").write_text(SHORT_MISSION)
    session = tmp_path / "s.yaml"
    session.write_text(SESSION.format(seed=2, faults="", corrupt=0.0, zmax=2.5,
                                      servo_action="hold"))
    record = tmp_path / "s.fhr"
    proc = subprocess.Popen([sys.executable, "-c", DRIVER, stage, str(session), "--record",
                             str(record), "--rerun", "off", "--quiet"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)  # Ctrl-Z's SIGCONT stays in its group
    try:
        assert proc.stderr is not None
        seen = []
        for line in proc.stderr:  # bounded: the driver says it or exits
            seen.append(line)
            if line.startswith("driver: holding"):
                break
        assert seen and seen[-1].startswith("driver: holding"), "".join(seen)
        proc.send_signal(sig)
        out, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    return proc.returncode, err + out, record


@pytest.mark.parametrize(("stage", "words"), [
    ("loading", "loading the session"),
    ("emulator", "starting the emulated vehicle")])
def test_that_a_ctrl_c_during_start_up_says_nothing_was_armed_and_exits_1(
        tmp_path: Path, stage: str, words: str) -> None:
    # Test
    code, text, record = _fly_held(tmp_path, stage, signal.SIGINT)
    # Assert
    assert code == 1, text  # as any session stopped before its planned end
    lines = [line for line in text.splitlines() if not line.startswith("driver:")]
    assert lines == [f"fasthex: SIGINT: stopped while {words}: nothing was armed"], text
    assert not record.exists()  # nothing flown: no record


def test_that_ctrl_z_during_start_up_is_no_stop(tmp_path: Path) -> None:
    """Ctrl-Z is refused in a flight (the loop tells the operator); during the start-up it is
    no stop either (it was taken for one: ``fasthex: : stopped while ...``, no signal named)."""
    code, text, record = _fly_held(tmp_path, "emulator", signal.SIGTSTP)
    assert code == 0, text
    assert "stopped while" not in text
    events = Path(str(record) + ".events.txt").read_text()
    assert "operator Ctrl-Z: refused" in events, events


def test_that_a_telemetry_process_that_cannot_start_is_the_error_reported(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # Fixture: the telemetry process's start fails as it does on a host out of file
    # descriptors (the session's clean-up must not mask it with a join of a process that
    # never started)
    import multiprocessing.context

    from flight_support import short_session

    from groundstation.session import FlightSession

    def no_start(self: object) -> None:
        raise OSError(24, "Too many open files")

    monkeypatch.setattr(multiprocessing.context.SpawnProcess, "start", no_start)
    cfg, params, mission = short_session(tmp_path)
    # Test / Assert
    with pytest.raises(OSError, match="Too many open files"):
        FlightSession(cfg, params, mission, record_path=tmp_path / "f.fhr",
                      echo_events=False).run()

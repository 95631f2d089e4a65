"""`fasthex fly` on a hardware session whose devices are absent or silent: one line
``fasthex: DEVICE URI: what is wrong``, exit code 2, no traceback and no (empty) record."""

from __future__ import annotations

import multiprocessing as mp
import os
from pathlib import Path

import pytest
from flight_support import SHORT_MISSION, short_session

from groundstation.cli import main
from groundstation.session import EmulatorProcess, FlightSession, SessionError
from groundstation.session_config import EmulatedBackend

HARDWARE = """\
schema: fasthex.session
version: 1
name: bench
vehicle: fasthex
mission: short-hover.yaml
backend:
  kind: hardware
  flight_ctrl_uri: {fc}
  servo_uri: {servo}
  mocap_uri: {mocap}
telemetry:
  rerun: "off"
"""


def _fly(tmp_path: Path, capsys: pytest.CaptureFixture[str], **uris: str) -> tuple[int, str]:
    (tmp_path / "short-hover.yaml").write_text(SHORT_MISSION)
    session = tmp_path / "bench.yaml"
    session.write_text(HARDWARE.format(**uris))
    record = tmp_path / "bench.fhr"
    code = main(["fly", str(session), "--record", str(record), "--quiet"])
    err = capsys.readouterr().err
    assert not record.exists()  # nothing flown: no record, not an empty one
    assert not Path(str(record) + ".events.txt").exists()
    assert "Traceback" not in err
    return code, err


@pytest.fixture(scope="module")
def emulator(tmp_path_factory: pytest.TempPathFactory) -> object:
    link = tmp_path_factory.mktemp("emu")
    emu = EmulatorProcess(EmulatedBackend(kind="emulated", clock="realtime"), "fasthex",
                          (0.1, -0.1, 0.1), link, realtime_settings=False)
    yield emu
    emu.close()


def test_that_an_absent_flight_ctrl_is_one_line_naming_it(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], emulator: EmulatorProcess) -> None:
    # the servo and the MoCap are there (the emulator's); the Flight-Ctrl's port is not
    uri = f"serial://{tmp_path}/ttyUSB9?baud=500000"
    devices = emulator.devices
    code, err = _fly(tmp_path, capsys, fc=uri,
                     servo=f"serial://{devices['servo']}?baud=1000000&id=1",
                     mocap=f"natnet://{devices['mocap']}?local=127.0.0.1&body=fasthex")
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith(f"fasthex: {uri}: no such device"), lines[0]


def test_that_a_silent_mocap_server_is_one_line_naming_it(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], emulator: EmulatorProcess) -> None:
    mocap = "natnet://127.0.0.1:9?local=127.0.0.1&body=fasthex"  # discard port: no server
    devices = emulator.devices
    code, err = _fly(tmp_path, capsys, fc=f"serial://{devices['flight-ctrl']}?baud=500000",
                     servo=f"serial://{devices['servo']}?baud=1000000&id=1", mocap=mocap)
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("fasthex: ") and "127.0.0.1:9" in lines[0], lines[0]
    assert "no SERVERINFO" in lines[0], lines[0]


def test_that_a_telemetry_process_that_dies_in_start_up_is_one_clear_error(
        tmp_path: Path) -> None:
    """The session waits for the telemetry process's imports before the IMU streams; one that
    exits instead (a broken install, killed by the OOM killer) ends the session with its exit
    code, not a wait of a minute."""
    # Fixture: a real process that exits at once with code 3, and its unset "imported" event
    ctx = mp.get_context("spawn")
    dead = ctx.Process(target=os._exit, args=(3,))
    dead.start()
    dead.join(30.0)
    imported = ctx.Event()
    session = FlightSession(*short_session(tmp_path), record_path=tmp_path / "r.fhr",
                            echo_events=False)
    # Test / Assert
    with pytest.raises(SessionError, match=r"telemetry process exited during start-up "
                                           r"\(exit code 3\)"):
        session._await_telemetry(dead, imported)
    imported.set()  # an imported one: no wait, no error
    session._await_telemetry(dead, imported)

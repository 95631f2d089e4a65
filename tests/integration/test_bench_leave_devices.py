"""Leaving the devices in a known state: after `fasthex probe`, `fasthex fly` (normal end,
failsafe end, Ctrl-C end) and `fasthex servo` the Flight-Ctrl's streams are off and its motors
stopped, asserted from the emulated board's side.

For probe and servo the emulated vehicle runs in this test process (real ptys, a real NatNet
server on UDP loopback, the realtime clock: a board that free-runs like a real one) and the
commands run against a hardware session that names its devices, as on a bench; the board's
state is read from the emulator. The flights are lockstep flights of an emulated session
(deterministic, whatever the load), whose board reports at shutdown what was left on. Under
pytest-xdist the bench tests run alone (``exclusive``: a realtime board whose replies have
timeouts); the flights share the machine.
"""

from __future__ import annotations

import ast
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from flight_support import SESSION, SHORT_MISSION

from config import find_config
from config.schema import load_config
from controller.params import VEHICLE_SCHEMA, VehicleParams
from drivers.dynamixel import Reg
from drivers.mikrokopter.device import FlightCtrl, FlightCtrlConfig
from groundstation.cli import main
from groundstation.record import read_record
from sim_backend.backend import BackendOptions, EmulatedVehicleBackend
from sim_backend.disturbances import DISTURBANCES_SCHEMA, DisturbancePreset
from sim_backend.emulators.dynamixel_p1 import EmulatedMX28

START_POS_W_M = (0.1, -0.1, 0.1)  # SHORT_MISSION's start

HW_SESSION = """\
schema: fasthex.session
version: 1
name: bench-emulated-board
vehicle: fasthex
mission: short-hover.yaml
backend:
  kind: hardware
  flight_ctrl_uri: pty://{fc}
  servo_uri: serial://{servo}?baud=1000000&id=1
  mocap_uri: natnet://{mocap}?local=127.0.0.1&body=fasthex
  imu_rate_hz: 500.0
safety:
  geofence_min_m: [-2.0, -2.0, -0.5]
  geofence_max_m: [2.0, 2.0, 2.5]
  mocap_timeout_s: 0.5
  imu_timeout_s: 0.12
  failsafe_action: land
  servo_fault_action: hold
telemetry:
  rerun: "off"
"""


class Bench:
    def __init__(self, backend: EmulatedVehicleBackend, session: Path) -> None:
        self.backend = backend
        self.session = session

    @property
    def board_quiet(self) -> bool:
        fc = self.backend.flight_ctrl
        return not fc.streams_on and not fc.motors_on


@pytest.fixture
def bench(tmp_path: Path) -> Iterator[Bench]:
    vehicle = load_config(find_config("vehicles", "fasthex"), VehicleParams,
                          schema=VEHICLE_SCHEMA)
    preset = load_config(find_config("disturbances", "ideal"), DisturbancePreset,
                         schema=DISTURBANCES_SCHEMA)
    backend = EmulatedVehicleBackend(BackendOptions(
        vehicle=vehicle, preset=preset, start_pos_w_m=START_POS_W_M, seed=5,
        clock="realtime", link_dir=tmp_path))
    # A hardware session has no zero offset of its own (0 steps): assemble the servo there.
    backend.servo = EmulatedMX28(backend.vehicle, lock=backend.lock,
                                 link_path=tmp_path / "servo",
                                 gear_ratio=vehicle.tilt.worm_ratio, zero_offset_steps=0)
    addresses = {a.device: a.address for a in backend.start()}
    (tmp_path / "short-hover.yaml").write_text(SHORT_MISSION)
    session = tmp_path / "bench.yaml"
    session.write_text(HW_SESSION.format(fc=addresses["flight-ctrl"],
                                         servo=addresses["servo"], mocap=addresses["mocap"]))
    try:
        yield Bench(backend, session)
    finally:
        backend.stop()


def _leave_streaming(bench: Bench) -> None:
    """A client that dies without cleaning up: streams on, motors started."""
    fc = FlightCtrl.open(f"pty://{bench.backend.flight_ctrl.path}", FlightCtrlConfig())
    fc.connect()
    fc.request_motor_start()
    emu = bench.backend.flight_ctrl
    deadline = time.monotonic() + 5.0
    while not (emu.streams_on and emu.motors_on) and time.monotonic() < deadline:
        time.sleep(0.01)  # the board thread handles the bytes on its own time
    fc._transport.close()  # no close(): as if the process had been killed


@pytest.mark.exclusive  # a realtime board in this process, reply timeouts
def test_that_probe_leaves_the_board_with_streams_off_and_motors_stopped(
        bench: Bench, capsys: pytest.CaptureFixture[str]) -> None:
    # Fixture: a previous client left the board streaming with its motors started
    _leave_streaming(bench)
    fc = bench.backend.flight_ctrl
    assert fc.streams_on and fc.motors_on
    # Test
    code = main(["probe", str(bench.session)])
    out = capsys.readouterr().out
    # Assert
    assert code == 0, out
    assert "flight-ctrl  pty://" in out and "can fly" in out
    assert not fc.streams_on and not fc.motors_on


@pytest.mark.exclusive  # a realtime board in this process, reply timeouts
def test_that_servo_commands_leave_the_board_quiet(bench: Bench) -> None:
    # Test: the servo commands never open the Flight-Ctrl; it stays as found (quiet)
    for argv in (["servo", "status", "--session", str(bench.session)],
                 ["servo", "move", "1", "--session", str(bench.session)]):
        assert main(argv) == 0
    # Assert
    assert bench.board_quiet
    assert bench.backend.servo.register(Reg.TORQUE_ENABLE) == 0  # the documented rest state


def _rows(path: Path) -> int:
    try:
        return len(read_record(path).rows)
    except (OSError, ValueError):
        return 0


# ----------------------------------------------------------------- fly: every end path
# Lockstep flights of the emulated session: the emulated board runs in `fly`'s child process,
# whose stderr is `fly`'s. When the board is shut down it reports any stream or motor still on
# (LEFT_ON); the SIGKILL test shows that report appears when a client does leave it on.

LEFT_ON = "the client did not leave the board as found"


def _fly_lockstep(tmp_path: Path, name: str, faults: str = "",
                  mission: str = SHORT_MISSION) -> tuple[subprocess.Popen[str], Path]:
    (tmp_path / "short-hover.yaml").write_text(mission)
    session = tmp_path / f"{name}.yaml"
    session.write_text(SESSION.format(seed=2, faults=faults, corrupt=0.0, zmax=2.5,
                                      servo_action="hold"))
    record = tmp_path / f"{name}.fhr"
    tmp = tmp_path / "tmp"  # TMPDIR of the flight: its session dir lands here, even killed
    tmp.mkdir()
    proc = subprocess.Popen([sys.executable, "-m", "groundstation", "fly", str(session),
                             "--record", str(record), "--quiet", "--rerun", "off"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=dict(os.environ, TMPDIR=str(tmp)))
    return proc, record


def _airborne(proc: subprocess.Popen[str], record: Path) -> None:
    deadline = time.monotonic() + 180.0
    while _rows(record) < 3000 and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)  # polling the record another process writes, bounded
    assert _rows(record) >= 3000, proc.communicate()


def _events(record: Path) -> str:
    return Path(str(record) + ".events.txt").read_text()


def test_that_a_normal_end_leaves_the_board_with_streams_off(tmp_path: Path) -> None:
    # Test
    proc, record = _fly_lockstep(tmp_path, "normal")
    out, err = proc.communicate(timeout=300)
    # Assert
    assert proc.returncode == 0, out + err
    assert "LANDING -> DISARMED: touchdown" in _events(record)
    assert LEFT_ON not in err


def test_that_a_failsafe_end_leaves_the_board_with_streams_off(tmp_path: Path) -> None:
    # Test: MoCap markers occluded for 3 s in the hover, three times the MoCap timeout
    proc, record = _fly_lockstep(tmp_path, "failsafe", faults="mocap-dropout@5.0:3.0")
    _, err = proc.communicate(timeout=300)
    # Assert
    events = _events(record)
    assert "-> LANDING: failsafe: MoCap lost" in events, events
    assert "-> DISARMED" in events or "-> CUT" in events
    assert LEFT_ON not in err, err


def test_that_a_ctrl_c_end_leaves_the_board_with_streams_off(tmp_path: Path) -> None:
    # Fixture
    proc, record = _fly_lockstep(tmp_path, "ctrl-c", mission=SHORT_MISSION.replace(
        "duration_s: 4.0", "duration_s: 60.0"))
    _airborne(proc, record)
    # Test
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=300)
    # Assert
    assert "operator" in _events(record), out + err
    assert LEFT_ON not in err, err


def test_that_a_killed_ground_station_is_seen_to_leave_the_streams_on(tmp_path: Path) -> None:
    # Fixture: the control for the three tests above: a client that cannot clean up
    proc, record = _fly_lockstep(tmp_path, "killed", mission=SHORT_MISSION.replace(
        "duration_s: 4.0", "duration_s: 60.0"))
    _airborne(proc, record)
    # Test: SIGKILL; the orphaned emulator waits for its watchdog, then shuts its board down
    proc.kill()
    _, err = proc.communicate(timeout=300)  # EOF once the emulator (same stderr) has exited
    # Assert: the watchdog stopped the motors; battery, IMU and motor streams were still on
    # (the magnetometer stream is off in the driver's configuration)
    assert "motors stopped" in err
    assert f"closed with B, I, M on: {LEFT_ON}" in err, err
    # the killed session could not remove its temporary directory: the emulator, its last
    # user, removed it after its note (on its log: the directory is gone)
    assert not list((tmp_path / "tmp").glob("fasthex-*"))
    note_line = next(line for line in err.splitlines() if "ground station gone: " in line)
    note = ast.literal_eval(note_line.split("ground station gone: ", 1)[1])
    assert note["reason"] == "ground station gone" and note["motors_stopped"] is True


@pytest.mark.exclusive  # a realtime board in this process, reply timeouts
def test_that_close_sends_the_stop_and_stream_off_sequence(bench: Bench) -> None:
    # Fixture
    fc = FlightCtrl.open(f"pty://{bench.backend.flight_ctrl.path}", FlightCtrlConfig())
    fc.connect()
    fc.start_motors(timeout_s=10.0)  # the loop's sequence: g per motor, then w at idle
    emu = bench.backend.flight_ctrl
    spinning = emu.motors_on
    idle_hz = emu.commanded_rotor_speeds_hz()
    # Test
    fc.close()
    fc.close()  # idempotent
    # Assert: x, then b, m, i, c at period 0 (seen by the board as no stream and no motor)
    # the idle w was a speed (16 Hz: half period 31250), not the 32767 that tk3 sends to stop
    assert spinning and idle_hz == pytest.approx((16.0,) * 6, abs=0.01)
    deadline = time.monotonic() + 5.0
    while not bench.board_quiet and time.monotonic() < deadline:
        time.sleep(0.01)  # the board thread handles the bytes on its own time
    assert bench.board_quiet
    assert emu.stats().watchdog_trips == 0  # stopped by the x, not by the BL watchdog

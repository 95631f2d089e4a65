"""Helpers shared by the flight-session integration tests (short missions, session files)."""

from __future__ import annotations

import contextlib
import os
from pathlib import Path
from typing import TYPE_CHECKING

from controller.missions import Mission
from controller.params import VehicleParams
from drivers.realtime import CPU_LATENCY_PATH
from groundstation.configs import load_mission, load_vehicle
from groundstation.session import FlightSession, SessionOutcome
from groundstation.session_config import SessionConfig, load_session

if TYPE_CHECKING:
    from collections.abc import Callable

    from groundstation.flight import FlightState
    from groundstation.record import FlightRecord

SHORT_MISSION = """\
schema: fasthex.mission
version: 1
name: short-hover
description: take off, hover through a tilt step, land (about 12.5 s)
start_pos_w_m: [0.1, -0.1, 0.1]
segments:
  - kind: takeoff
    duration_s: 2.5
    height_m: 0.8
    alpha: {kind: constant, value_deg: 0.0}
  - kind: hold
    duration_s: 1.0
    measured: false
  - kind: hold
    duration_s: 4.0
    alpha: {kind: steps, times_s: [0.0, 1.0], values_deg: [0.0, 10.0]}
  - kind: land
    duration_s: 4.5
    alpha: {kind: constant, value_deg: 0.0}
  - kind: hold
    duration_s: 0.5
    measured: false
"""

SESSION = """\
schema: fasthex.session
version: 1
name: short-hover-emulated
vehicle: fasthex
mission: short-hover.yaml
backend:
  kind: emulated
  clock: lockstep
  seed: {seed}
  disturbances: paper-calibrated
  faults: [{faults}]
  corrupt_prob: {corrupt}
safety:
  geofence_min_m: [-2.0, -2.0, -0.5]
  geofence_max_m: [2.0, 2.0, {zmax}]
  mocap_timeout_s: 1.0
  imu_timeout_s: 0.1
  failsafe_action: land
  servo_fault_action: {servo_action}
telemetry:
  rerun: "off"
"""


def open_cpu_latency_requests() -> int:
    """How many CPU wake-up latency requests (``/dev/cpu_dma_latency``) this process has open.
    Judged on the process's own files: the kernel's value is the tightest request of every
    process, and other test workers may hold one at the same time."""
    n = 0
    for fd in os.listdir("/proc/self/fd"):
        with contextlib.suppress(OSError):
            n += os.readlink(f"/proc/self/fd/{fd}") == str(CPU_LATENCY_PATH)
    return n


def can_hold_cpu_latency() -> bool:
    """Whether this process may open a CPU wake-up latency request (root, a PM QoS kernel)."""
    try:
        os.close(os.open(CPU_LATENCY_PATH, os.O_WRONLY))
    except OSError:
        return False
    return True


def fly(tmp_path: Path, *, name: str = "flight", seed: int = 3, faults: str = "",
        corrupt: float = 0.0, zmax: float = 2.5, servo_action: str = "hold",
        requests: tuple[tuple[float, str], ...] = (), realtime_settings: bool | None = None,
        on_event: Callable[[str], None] | None = None) -> SessionOutcome:
    (tmp_path / "short-hover.yaml").write_text(SHORT_MISSION)
    session_path = tmp_path / f"{name}.yaml"
    session_path.write_text(SESSION.format(seed=seed, faults=faults, corrupt=corrupt,
                                           zmax=max(zmax, 2.5), servo_action=servo_action))
    cfg = load_session(session_path)
    if zmax < 2.5:  # a fence below the mission is refused at load; the breach test wants one
        from dataclasses import replace
        cfg = replace(cfg, safety=replace(cfg.safety, geofence_max_m=(2.0, 2.0, zmax)))
    session = FlightSession(cfg, load_vehicle("fasthex"),
                            Mission(load_mission(tmp_path / "short-hover.yaml")),
                            record_path=tmp_path / f"{name}.fhr", echo_events=False,
                            scripted_requests=requests, realtime_settings=realtime_settings,
                            on_event=on_event)
    return session.run()




def short_session(tmp_path: Path, *, name: str = "flight", seed: int = 3,
                  mission: str = SHORT_MISSION) -> tuple[SessionConfig, VehicleParams, Mission]:
    (tmp_path / "short-hover.yaml").write_text(mission)
    session_path = tmp_path / f"{name}.yaml"
    session_path.write_text(SESSION.format(seed=seed, faults="", corrupt=0.0, zmax=2.5,
                                           servo_action="hold"))
    return (load_session(session_path), load_vehicle("fasthex"),
            Mission(load_mission(tmp_path / "short-hover.yaml")))


def fly_long_hover_in_this_process(tmp: str) -> None:
    """Child-process entry for the kill -9 test: a session that would hover for a minute, with
    its devices linked in ``tmp/dev`` (the emulator leaves its exit note there)."""
    tmp_path = Path(tmp)
    cfg, params, mission = short_session(
        tmp_path, mission=SHORT_MISSION.replace("duration_s: 4.0", "duration_s: 60.0"))
    dev = tmp_path / "dev"
    dev.mkdir(exist_ok=True)
    FlightSession(cfg, params, mission, record_path=tmp_path / "killed.fhr", session_dir=dev,
                  echo_events=False).run()


def fly_long_hover_in_a_temporary_folder(tmp: str) -> None:
    """Child-process entry: the same session with its links in a temporary folder of the
    session's own making, under ``tmp/t`` (as ``fasthex fly`` makes one)."""
    import tempfile

    tmp_path = Path(tmp)
    (tmp_path / "t").mkdir(exist_ok=True)
    tempfile.tempdir = str(tmp_path / "t")
    cfg, params, mission = short_session(
        tmp_path, mission=SHORT_MISSION.replace("duration_s: 4.0", "duration_s: 60.0"))
    FlightSession(cfg, params, mission, record_path=tmp_path / "killed.fhr",
                  echo_events=False).run()


def fly_shipped_session(tmp_path: Path, session: str, seed: int = 1,
                        requests: tuple[tuple[float, str], ...] = ()) -> SessionOutcome:
    """One of the shipped emulated sessions (the paper's experiments), lockstep, no dashboard;
    ``requests``: operator requests at session times (s), e.g. ``((20.0, "land"),)``."""
    from dataclasses import replace

    from config import find_config
    from groundstation.session_config import resolve_reference

    path = find_config("sessions", session)
    cfg = load_session(path)
    cfg = replace(cfg, backend=replace(cfg.backend, clock="lockstep", seed=seed))
    params = load_vehicle(resolve_reference(path, cfg.vehicle))
    mission = Mission(load_mission(resolve_reference(path, cfg.mission)))
    return FlightSession(cfg, params, mission, record_path=tmp_path / f"{session}.fhr",
                         echo_events=False, dashboard="off", scripted_requests=requests).run()


PaperFlight = tuple[list["FlightState"], "FlightRecord", dict[str, float]]


def fly_paper_experiment(tmp_path: Path, session: str) -> PaperFlight:
    """A shipped experiment session flown in lockstep through the byte path: its transitions,
    its record (scored on the emulated vehicle's true state) and the metrics ``simulate``
    prints. One experiment per test module, so that pytest-xdist flies them side by side."""
    from groundstation.metrics import flight_metrics
    from groundstation.record import read_record

    out = fly_shipped_session(tmp_path, session)
    rec = read_record(out.record_path)
    return ([t.to_state for t in out.result.transitions], rec,
            flight_metrics(rec.rows, min_spin_hz=16.0, max_spin_hz=102.0))


def assert_normal_paper_flight(flight: PaperFlight) -> None:
    """Armed, took off, flew the mission, landed and disarmed; scored on the true state, every
    rotor within its spin limits."""
    from groundstation.flight import FlightState

    states, rec, m = flight
    assert states == [FlightState.ARMED, FlightState.TAKEOFF, FlightState.MISSION,
                      FlightState.LANDING, FlightState.DISARMED]
    assert rec.metadata["state"].startswith("true state")
    assert m["all_spin_within_limits"] == 1.0

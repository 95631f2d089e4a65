"""A flight session: from a validated session file to a flight record and a summary.

Composition (the only place that knows which backend is in use):

- ``emulated``: starts ``python -m sim_backend.backend`` as a child process (it owns the physics
  and the emulated Flight-Ctrl, MX-28T and NatNet server) and reads the device addresses it
  prints; the child dies with us (SIGTERM on parent death, stdin closed, or killed at exit);
- ``hardware``: the URIs of the session file.

Either way the same drivers are opened (``FlightCtrl``, ``TiltServo``, ``NatNetClient``), the
UKF and the flight loop are built, and a telemetry process drains the loop's shared-memory ring
into the flight record (written every 100 ms, so a crash loses at most the last 100 ms) and
writes the events (transitions, faults, preflight results) next to it as
``<record>.events.txt``. That process starts first (its imports overlap the devices' start-up,
not the flight) and makes the record once the devices are open.
"""

from __future__ import annotations

import collections
import contextlib
import importlib
import json
import logging
import multiprocessing as mp
import os
import queue
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NoReturn, TypeVar

import numpy as np

from controller.missions import Mission
from controller.params import VehicleParams
from drivers.dynamixel.device import TiltServo, TiltServoConfig
from drivers.errors import DriverError
from drivers.mikrokopter.device import FlightCtrl, FlightCtrlConfig
from drivers.mocap.natnet_client import NatNetClient
from drivers.mocap.pose import MocapError
from drivers.mocap.qtm_client import QtmClient
from drivers.mocap.uri import open_pose_source
from drivers.realtime import freeze_start_up_heap, thaw_start_up_heap
from drivers.shared_flag import SharedFlag
from estimator import consistency
from estimator.ukf import Ukf
from groundstation.flight import SafetyLimits
from groundstation.gcs import GcsOptions, gcs_options, start_gcs
from groundstation.loop import FlightLoop, LoopOptions, LoopResult, prepared_computer
from groundstation.operator import STATUS_SIZE, STATUS_STATE
from groundstation.record import RECORD_DTYPE, RecordWriter
from groundstation.session_config import EmulatedBackend, HardwareBackend, SessionConfig
from groundstation.signals import ignore_stop_signals, stop_signals_blocked
from groundstation.telemetry import TelemetryRing
from sim_backend.backend import SERVO_ZERO_OFFSET_STEPS, TEMPORARY_MARKER

log = logging.getLogger(__name__)
T = TypeVar("T")



class SessionError(Exception):
    """The session could not start (a device, the emulator); printed without traceback."""


class SessionInterruptedError(SessionError):
    """A stop signal arrived while the session was starting: nothing was armed."""


@dataclass
class SessionOutcome:
    result: LoopResult
    record_path: Path
    events_path: Path
    preflight: list[tuple[str, bool, str]]
    realtime_settings: dict[str, str] = field(default_factory=dict)
    wall_time_s: float = 0.0
    #: the dashboard as flown: spawn, serve, save or off
    dashboard_mode: str = "off"
    #: the dashboard's .rrd file, if one was written
    dashboard_file: Path | None = None
    #: the emulated vehicle's truth at the end (empty on hardware): ``touchdown_speeds_m_s``,
    #: ``landed``, ``height_m`` (``EmulatedVehicleBackend.truth_at_exit``)
    truth: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class DeviceUris:
    flight_ctrl: str
    servo: str
    mocap: str
    servo_zero_steps: int


def device_uris(cfg: SessionConfig, emulator: EmulatorProcess | None) -> DeviceUris:
    """Where the three devices are: the session's URIs, or the running emulator's."""
    backend = cfg.backend
    if isinstance(backend, HardwareBackend):
        return DeviceUris(backend.flight_ctrl_uri, backend.servo_uri, backend.mocap_uri,
                          backend.servo_zero_offset_steps)
    if emulator is None:
        raise SessionError("the emulated backend is not running")
    devs = emulator.devices
    mocap = f"qtm://{devs['mocap']}?body=fasthex" if backend.mocap == "qtm" \
        else f"natnet://{devs['mocap']}?local=127.0.0.1&body=fasthex"
    return DeviceUris(devs["flight-ctrl"], devs["servo"] + "?baud=1000000&id=1", mocap,
                      SERVO_ZERO_OFFSET_STEPS)


class EmulatorProcess:
    """The emulated vehicle in a child process; its devices' addresses once ready."""

    def __init__(self, cfg: EmulatedBackend, vehicle: str, start_pos_w_m: tuple[float, ...],
                 link_dir: Path, corrupt_prob: float = 0.0, truth_path: Path | None = None,
                 realtime_settings: bool = True) -> None:
        args = [sys.executable, "-m", "sim_backend.backend", "--vehicle", vehicle,
                "--disturbances", cfg.disturbances, "--seed", str(cfg.seed),
                "--clock", cfg.clock, "--link-dir", str(link_dir),
                "--corrupt-prob", str(corrupt_prob or cfg.corrupt_prob), "--start",
                *(repr(float(x)) for x in start_pos_w_m)]
        for fault in cfg.faults:
            args += ["--fault", fault]
        args += ["--board-clock-ppm", repr(cfg.board_clock_ppm), "--mocap-clock-offset-s",
                 repr(cfg.mocap_clock_offset_s), "--mocap-clock-ppm", repr(cfg.mocap_clock_ppm),
                 "--mocap", cfg.mocap]
        if truth_path is not None:
            args += ["--truth", str(truth_path)]
        if cfg.scenario:  # resolved to a file by load_session
            args += ["--scenario", cfg.scenario]
        self.lockstep = cfg.clock == "lockstep"
        args += ["--realtime-settings", "on" if realtime_settings else "off"]
        # A session of its own: the terminal's SIGINT (sent to the whole foreground process
        # group) and a SIGTERM/SIGHUP to our group never reach the emulated board, which the
        # ground station stops in order after the landing (``close``).
        self.proc = subprocess.Popen(args, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                     stderr=None, text=True, start_new_session=True)
        self.devices: dict[str, str] = {}
        self.realtime_settings = ""  # what the emulator's real-time settings came to
        #: the emulated board's counters when it stopped (``EmulatorStats`` fields)
        self.exit_stats: dict[str, int] = {}
        #: the emulated vehicle's truth when it stopped (``EmulatedVehicleBackend
        #: .truth_at_exit``): touchdown speeds, landed, height
        self.exit_truth: dict[str, Any] = {}
        deadline = time.monotonic() + 60.0
        assert self.proc.stdout is not None
        while time.monotonic() < deadline:
            line = self.proc.stdout.readline()
            if not line:
                self.close()
                raise SessionError("the emulated vehicle exited before it was ready "
                                   f"(exit code {self.proc.poll()})")
            msg = json.loads(line)
            if msg.get("ready"):
                self.realtime_settings = str(msg.get("realtime", ""))
                return
            self.devices[msg["device"]] = msg["address"]
        self.close()
        raise SessionError("the emulated vehicle did not get ready within 60 s")

    def start_scenario(self) -> None:
        """Tell the emulated vehicle that the mission clock starts now (its scenario's time 0).
        Lockstep: wait for the answer, so that the anchor is this tick's simulated time (the
        physics waits for this tick's ``w``); realtime: the line is enough."""
        import select

        try:
            assert self.proc.stdin is not None and self.proc.stdout is not None
            self.proc.stdin.write("scenario-start\n")
            self.proc.stdin.flush()
            if self.lockstep:
                ready, _, _ = select.select([self.proc.stdout], [], [], 5.0)
                if ready:
                    self.proc.stdout.readline()
        except (OSError, ValueError) as exc:  # a dead emulator is the loop's to notice
            log.warning("scenario start not delivered to the emulated vehicle: %s", exc)

    def close(self) -> None:
        if self.proc.poll() is None:
            with contextlib.suppress(OSError, ValueError):
                assert self.proc.stdin is not None
                self.proc.stdin.write("quit\n")
                self.proc.stdin.flush()
                self.proc.stdin.close()
            try:
                self.proc.wait(timeout=5.0)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=5.0)
            with contextlib.suppress(OSError, ValueError):
                assert self.proc.stdout is not None
                for line in self.proc.stdout.read().splitlines():
                    with contextlib.suppress(ValueError, AttributeError, KeyError, TypeError):
                        msg = json.loads(line)
                        self.exit_stats = dict(msg["exit"])
                        self.exit_truth = dict(msg.get("truth") or {})


def _telemetry_main(ring_name: str, record_path: str, metadata: dict[str, Any],
                    events: Any, events_path: str, notices: Any, stop: Any,
                    dashboard_mode: str, rrd_path: str, params: VehicleParams,
                    mavlink: GcsOptions | None, status: Any, commands: Any, imported: Any,
                    go: Any, session_pid: int, opened: Any, failure: Any) -> None:
    """The telemetry process: ring -> flight record (+ rerun dashboard), event queue -> events
    file. Runs at a lower priority; the loop never waits for it. It never writes to the
    terminal itself: lines for the operator (the viewer's address, the MAVLink link's notices)
    go back to the session through ``notices`` (None: not shown), whose console prints them.

    Started first thing in a session, it imports what it will use and sets ``imported``, then
    waits for ``go`` (the devices are open) before it makes anything: a session that ends in
    its start-up leaves no record. ``stop`` or the session's death meanwhile ends it: the death
    of ``session_pid`` (its parent), even before this process could look (it is then the
    child of another process already, and its own parent's pid tells nothing).

    Once the record is open it sets ``opened``. A record it cannot write (at its opening or
    later: a full disk) ends it with exit code 2 and one line on ``failure`` for the session,
    which then lands the vehicle (``FlightLoop.record_lost``); a dashboard that cannot start is an
    event and a notice, and the flight goes on with its record (the MAVLink link handles its
    own failure to open the same way, in ``start_gcs``)."""
    with contextlib.suppress(OSError):
        os.nice(10)
    # the session ends us (stop event or its death), not the terminal; nor do Ctrl-\ and
    # Ctrl-Z kill or suspend us (or the viewer we start) while the vehicle flies
    ignore_stop_signals(flight=True)
    # the heavy imports now, while the session starts its devices, not in the first seconds of
    # the flight
    for module, wanted in (("rerun", dashboard_mode != "off"),
                           ("groundstation.mavlink_bridge", mavlink is not None)):  # pymavlink
        if wanted:
            importlib.import_module(module)
    imported.set()
    while not go.wait(0.1):
        if stop.is_set() or os.getppid() != session_pid:
            return
    def fail(why: str) -> NoReturn:
        with contextlib.suppress(Exception):
            failure.put(why, timeout=1.0)
        raise SystemExit(2)

    def notice(line: str) -> None:
        if notices is not None:
            with contextlib.suppress(queue.Full):
                notices.put_nowait(line)

    ring = TelemetryRing(RECORD_DTYPE, name=ring_name)
    try:
        writer = RecordWriter(record_path, metadata, keep_in_memory=False)
    except OSError as exc:
        fail(f"cannot write the flight record {record_path}: {exc.strerror or exc}")
    opened.set()
    dash = None
    if dashboard_mode != "off":
        from groundstation.dashboard import Dashboard

        try:
            dash = Dashboard(dashboard_mode, rrd_path, metadata=metadata, params=params)
        except Exception as exc:  # the record matters more: fly on without the dashboard
            line = f"dashboard ({dashboard_mode}): WARNING not started: {exc}"
            with contextlib.suppress(OSError), open(events_path, "a", encoding="utf-8") as ev:
                ev.write(line + "\n")
            notice(line)
        if dash is not None and dash.viewer_url:
            notice(f"dashboard: web viewer at {dash.viewer_url}")

    gcs = None if mavlink is None else start_gcs(mavlink, params, status, commands,
                                                 events_path, notice)
    try:
        pending = _telemetry_run(ring, writer, events, events_path, stop, session_pid, dash,
                                 gcs)
    except OSError as exc:  # the record (or the events file) could not be written on
        fail(f"the flight record {record_path} could not be written on: "
             f"{exc.strerror or exc}")
    if dash is not None:
        dash.close()
    if gcs is not None:  # the final state announced, then the link's counters written
        gcs.close(pending)
    ring.close()


def _telemetry_run(ring: TelemetryRing, writer: RecordWriter, events: Any, events_path: str,
                   stop: Any, session_pid: int, dash: Any, gcs: Any) -> list[str]:
    """The telemetry process's loop: ring -> record (+ dashboard, MAVLink), events -> file,
    every 50 ms until the session stops or dies; the record closed at the end. Returns the
    events not yet published to the MAVLink link."""
    pending_events: list[str] = []
    all_events = False      # the session's END_OF_EVENTS came: nothing follows it
    with open(events_path, "a", encoding="utf-8") as ev:
        while True:
            # the session ended, or died (kill -9): either way, write out what the ring holds
            finished = stop.is_set() or os.getppid() != session_pid
            rows = ring.drain()
            if len(rows):
                writer.append_block(rows)
                if dash is not None:
                    dash.log_rows(rows)
            while not all_events:
                # at the end, wait for the events still on their way: a queue's feeder thread
                # may not have written the session's last ones to the pipe yet (under load
                # the last transitions were lost); a session that died sends no end marker
                try:
                    text = events.get(timeout=END_DRAIN_S) if finished \
                        else events.get_nowait()
                except queue.Empty:
                    break
                if text == END_OF_EVENTS:
                    all_events = True
                    break
                ev.write(text + "\n")
                if dash is not None:
                    dash.log_event_line(text)
                if gcs is not None:
                    pending_events.append(text)
            ev.flush()
            if gcs is not None and len(rows):
                gcs.publish(rows, pending_events)
                pending_events = []
            if finished:
                rest = ring.drain()
                if len(rest):
                    writer.append_block(rest)
                    if dash is not None:
                        dash.log_rows(rest)
                break
            time.sleep(0.05)
    writer.close()
    return pending_events


def _telemetry_failure(tel: Any, failure: Any, *, wait: bool = True) -> str:
    """Why the telemetry process ended: its own line, or its exit code (a crash, a kill).
    ``wait=False`` (the flight loop's thread): nothing that blocks."""
    if wait:
        tel.join(timeout=1.0)
    try:
        return str(failure.get(timeout=0.5) if wait else failure.get_nowait())
    except queue.Empty:
        return f"the telemetry process exited (exit code {tel.exitcode})"


def _salvage_events(events: Any, events_path: Path) -> None:
    """The events the dead telemetry process left in its queue, appended to the events file
    (the session's own process can still write it: a record that cannot be written need not
    mean an events file that cannot)."""
    lines: list[str] = []
    with contextlib.suppress(Exception):
        while True:
            lines.append(events.get(timeout=0.05))
    lines = [line for line in lines if line != END_OF_EVENTS]
    if lines:
        with contextlib.suppress(OSError), events_path.open("a", encoding="utf-8") as ev:
            ev.write("\n".join(lines) + "\n")


class FlightSession:
    """Runs one session: devices up, preflight, fly, land, record, report."""

    def __init__(self, cfg: SessionConfig, params: VehicleParams, mission: Mission, *,
                 record_path: Path, session_dir: Path | None = None,
                 echo_events: bool = True, on_event: Callable[[str], None] | None = None,
                 corrupt_prob: float = 0.0,
                 realtime_settings: bool | None = None,
                 scripted_requests: tuple[tuple[float, str], ...] = (),
                 props_off: bool = False,
                 dashboard: str | None = None, mavlink: str | None = None,
                 mavlink_key_file: str | None = None) -> None:
        self.cfg = cfg
        self.params = params
        self.mission = mission
        self.record_path = record_path
        self.events_path = record_path.with_suffix(record_path.suffix + ".events.txt")
        self.echo_events = echo_events
        #: called (in this process, from the loop's thread: it must not block) with every
        #: event line as it happens; None with echo_events: plain lines on stderr
        self.on_event = on_event
        self.corrupt_prob = corrupt_prob
        #: None: on wherever the clock is real (hardware, realtime emulation), off in lockstep
        self.realtime_settings = realtime_settings
        self.scripted_requests = scripted_requests
        self.dashboard = dashboard or cfg.telemetry.rerun
        self.mavlink_uri = mavlink if mavlink is not None else cfg.telemetry.mavlink
        # the signing key is resolved here, before anything opens (a bad key file: exit 2)
        self.mavlink: GcsOptions | None = gcs_options(
            self.mavlink_uri, cfg.telemetry, record_path, cli_key_file=mavlink_key_file)
        self._tmp = None if session_dir else tempfile.TemporaryDirectory(prefix="fasthex-")
        if self._tmp is not None:  # an emulator orphaned by a kill -9 removes it (backend.py)
            (Path(self._tmp.name) / TEMPORARY_MARKER).touch()
        self.session_dir = session_dir or Path(self._tmp.name)  # type: ignore[union-attr]
        self.emulator: EmulatorProcess | None = None
        self.loop: FlightLoop | None = None
        #: operator requests for the loop (signal handlers append "stop"; deque.append is
        #: atomic and takes no lock); one deque from start-up on, so nothing is missed
        self.requests: collections.deque[Any] = collections.deque()
        #: the installed stop-signal handlers (groundstation.signals.StopSignals), if any:
        #: the end reason names the signals that stopped the flight
        self.stop_signals: Any = None
        #: bench with the propellers off: arm, idle spin test, disarm; no take-off
        self.props_off = props_off

    def _dashboard_mode(self) -> str:
        """``auto``: a spawned viewer where there is a display, else none. Without a viewer
        a 25 MB .rrd next to every record is rarely wanted; ``save`` writes one, and ``fasthex
        replay RECORD`` makes one from the record at any time."""
        if self.dashboard != "auto":
            return self.dashboard
        from groundstation.dashboard import default_mode

        return "spawn" if default_mode() == "spawn" else "off"

    def run(self) -> SessionOutcome:
        cfg = self.cfg
        backend = cfg.backend
        lockstep = isinstance(backend, EmulatedBackend) and backend.clock == "lockstep"
        fc: FlightCtrl | None = None
        servo: TiltServo | None = None
        mocap: Any = None
        tel: mp.process.BaseProcess | None = None
        ring: TelemetryRing | None = None
        ctx = mp.get_context("spawn")
        # multiprocessing's resource tracker (it unlinks the shared memory and semaphores below)
        # is a child of ours too, in the terminal's foreground group: started with the stop
        # signals blocked it keeps them blocked (it unblocks only SIGINT and SIGTERM, which it
        # ignores), so that neither a SIGHUP nor a flight's Ctrl-\ kills it half-way through
        # the session (relaunched, it flooded the console with KeyErrors), nor Ctrl-Z stops it
        from multiprocessing import resource_tracker

        with stop_signals_blocked(flight=True):
            resource_tracker.ensure_running()
        # flags, not Events: an Event's set() waits for ever on a process that died asleep in
        # its wait (drivers.shared_flag), a session killed in start-up or a telemetry process
        # that crashed before `go`
        stop = SharedFlag(ctx)
        tel_imported, tel_go, tel_opened = SharedFlag(ctx), SharedFlag(ctx), SharedFlag(ctx)
        tel_failure: Any = ctx.Queue(maxsize=4)
        events: Any = ctx.Queue(maxsize=10_000)
        status: Any = ctx.Array("d", STATUS_SIZE, lock=False)
        commands: Any = ctx.Queue(maxsize=100)
        wall0 = time.perf_counter()
        outcome: SessionOutcome | None = None
        on_event = self.on_event
        own_console = None
        if on_event is None and self.echo_events:
            from groundstation.console import Console

            own_console = Console(sys.stderr, live=False).start()
            on_event = own_console.event
        # lines from the telemetry process for the operator (viewer address, MAVLink notices)
        notices: Any = ctx.Queue(maxsize=100) if on_event is not None else None
        forwarder = _NoticeForwarder(notices, on_event) if on_event is not None else None

        def note(text: str) -> None:  # an event: to the events file and the operator
            with contextlib.suppress(queue.Full):
                events.put_nowait(text)
            if on_event is not None:
                on_event(text)

        dashboard_mode = self._dashboard_mode()
        settings: dict[str, str] = {}
        truth_path: Path | None = None
        rt_settings = (not lockstep if self.realtime_settings is None
                       else self.realtime_settings and not lockstep)
        # Lockstep sets its own pace (no scheduler settings), but its CPUs are kept out of deep
        # idle all the same: each tick waits on a pty round trip, and a CPU that sleeps through
        # it wakes slowly and cold (drivers.realtime: about 1.7x faster on a quiet machine)
        hold_latency = lockstep and self.realtime_settings is not False
        try:
            if rt_settings:  # before any device thread runs: mlockall stalls the process
                from drivers.realtime import lock_memory

                settings["memory"] = lock_memory()
            # The telemetry process first: its interpreter and imports (1-2 s of CPU; more with
            # rerun or pymavlink) overlap the start-up of the emulator and the devices. Started
            # just before the loop, it took a CPU from the loop (and the emulated board) for
            # the first seconds of the flight: every pty write paid a preemption (100-150 us
            # instead of 3-4 us). It makes nothing (no record) before `go`, below.
            with stop_signals_blocked():  # the shared-memory tracker process starts here
                ring = TelemetryRing(RECORD_DTYPE, capacity=1 << 14)
            meta = {"session": cfg.name, "mission": self.mission.name,
                    "vehicle": self.params.name, "backend": backend.kind,
                    "clock": getattr(backend, "clock", "realtime"),
                    "seed": getattr(backend, "seed", None),
                    "preset": getattr(backend, "disturbances", None),
                    "rate_hz": backend.imu_rate_hz,
                    "measured_interval_s": self.mission.measured_interval_s(),
                    "source": "fasthex fly"}
            tel = ctx.Process(target=_telemetry_main, name="fasthex-telemetry",
                              args=(ring.name, str(self.record_path), meta, events,
                                    str(self.events_path), notices, stop,
                                    dashboard_mode,
                                    str(self.record_path.with_suffix(".rrd")), self.params,
                                    self.mavlink, status, commands, tel_imported, tel_go,
                                    os.getpid(), tel_opened, tel_failure))
            with stop_signals_blocked():  # it ignores them once its interpreter is up
                tel.start()
            # What holds the interpreter (numba's kernels, from its cache in tens of ms or, on
            # a fresh install, compiled in tens of seconds; the rehearsal of the controller; a
            # full GC collection) before the emulated vehicle starts, and before any device
            # streams: an emulated board waits for the first `w` only for its first-command
            # grace (30 s) from its own start, then free-runs, and the flight is no longer the
            # seed's (seen: a flight after a kernel change started at 6 ms); a device's thread
            # must be free to take and timestamp each sample (a MoCap frame held back at the
            # stream's start reads as a server clock step)
            computer = prepared_computer(self.params, self.mission)
            ukf = Ukf(_estimator_config(cfg, self.params))
            consistency.warm_up()  # its kernel too (the loop's MoCap/IMU monitor)
            self._check_interrupted("preparing the controller")
            if isinstance(backend, EmulatedBackend):
                # Lockstep only (that is where it is merged into the record): its writes come
                # from the emulated board's thread, and under disk pressure a page-cache write
                # can block for hundreds of ms, which would stall a realtime IMU stream.
                truth_path = self.session_dir / "truth.f64" if lockstep else None
                self.emulator = EmulatorProcess(backend, cfg.vehicle, self.mission.start_pos_w_m,
                                                self.session_dir, self.corrupt_prob, truth_path,
                                                realtime_settings=rt_settings)
                if self.emulator.realtime_settings:
                    note("emulated vehicle real-time settings: "
                         + self.emulator.realtime_settings)
            self._check_interrupted("starting the emulated vehicle")
            uris = device_uris(cfg, self.emulator)
            fc_uri, servo_uri, mocap_uri = uris.flight_ctrl, uris.servo, uris.mocap
            zero_steps = uris.servo_zero_steps

            # Both clocks: the collections of the flight then walk only what was made since
            # (in a lockstep flight they cost ~0.5 % of its time besides, and a full one
            # 35-70 ms); realtime disables the GC in flight too (apply_realtime_settings).
            freeze_start_up_heap()

            # The devices first: a device that cannot be opened ends the session with one
            # line naming it, before any record exists.
            tilt = self.params.tilt
            servo = TiltServo(TiltServoConfig(
                uri=servo_uri, gear_ratio=tilt.worm_ratio, zero_offset_steps=zero_steps,
                max_tilt_deg=tilt.max_tilt_deg, max_tilt_rate_deg_s=tilt.max_rate_deg_s,
                rate_hz=50.0, serve="on_request" if lockstep else "periodic",
                # in lockstep the tilt planner's ramp is the rate limit (sim time), and the
                # SDK's reply timeout (wall clock, 2 x 250 + 2 ms) is long: a late reply must
                # not become a servo fault that changes the flight (determinism for a seed)
                rate_limit_goal=not lockstep,
                sdk_latency_timer_ms=250.0 if lockstep else 16.0,
                # and a healthy servo's cycle is asked again twice before a missing reply is a
                # fault (an emulated servo starved by a loaded host is late, not faulty)
                late_reply_retries=2 if lockstep else 0),
                # lockstep: the loop waits for each cycle anyway; served in its own thread, the
                # servo answers while the tick computes, with no process hop (drivers.dynamixel)
                isolation="inline" if lockstep else "process")
            with stop_signals_blocked():  # its process must not die of a stray Ctrl-C
                _open_device("servo", servo_uri, servo.start)
            if lockstep:
                # one cycle now, while no simulated time runs: the servo is configured and
                # has answered once, so the loop's first cycles do not depend on how long a
                # loaded host took for that (a repeatable run); a servo that does not answer
                # is the preflight's to report
                with contextlib.suppress(Exception):
                    servo.sync_cycle(LOCKSTEP_SERVO_START_S)
            self._check_interrupted("starting the tilt servo")
            loop_box: list[FlightLoop] = []

            def loop_clock() -> int:
                return loop_box[0].now_ns if loop_box else 0

            mocap = _open_device("mocap", mocap_uri, lambda: open_pose_source(
                mocap_uri, clock=loop_clock if lockstep else None))
            if isinstance(mocap, NatNetClient | QtmClient):
                _open_device("mocap", mocap_uri, lambda: mocap.start(receive_thread=not lockstep))
            else:
                _open_device("mocap", mocap_uri, mocap.start)
            self._check_interrupted("connecting to the MoCap server")
            self._await_telemetry(tel, tel_imported)  # before the IMU streams too
            # The Flight-Ctrl last: once its IMU streams, an emulated board waits for `w` only
            # for its lockstep grace (then free-runs, and a run is no longer repeatable), so
            # nothing slow (the servo's start and configuration, the MoCap handshake) may come
            # after it.
            fc = _open_device("flight-ctrl", fc_uri, lambda: FlightCtrl.open(
                fc_uri, FlightCtrlConfig(imu_rate_hz=backend.imu_rate_hz)))
            ident = _open_device("flight-ctrl", fc_uri, fc.connect)
            if lockstep:  # every sample answers our own `w`: read it in the loop's thread
                fc.read_in_caller_thread()
            # the emulator's ptys live in a temporary folder that is gone after the flight
            where = "the emulated vehicle" if self.emulator is not None else fc_uri
            note(f"flight-ctrl: {ident.protocol} firmware {ident.firmware_id} on {where}")
            self._check_interrupted("opening the Flight-Ctrl")

            self.events_path.write_text("")
            tel_go.set()  # the record and the events file from now on
            self._await_record(tel, tel_opened, tel_failure)
            if forwarder is not None:
                forwarder.start()
            row_sink = ring.push_flat
            event_sink = note

            loop = FlightLoop(
                params=self.params, mission=self.mission, imu=fc, tilt=servo, pose=mocap,
                estimator=ukf, limits=_limits(cfg, self.props_off),
                options=LoopOptions(lockstep=lockstep, imu_rate_hz=backend.imu_rate_hz,
                                    ground_z_m=self.mission.start_pos_w_m[2],
                                    max_flight_s=self.cfg.safety.session_time_limit_s,
                                    scripted_requests=self.scripted_requests),
                row_sink=row_sink, event_sink=event_sink, computer=computer)
            loop.shared_status = status
            loop.command_queue = commands
            if self.emulator is not None and isinstance(backend, EmulatedBackend) \
                    and backend.scenario:
                loop.on_mission_start = self.emulator.start_scenario
            loop.requests = self.requests  # stop requests that came during start-up stand
            telemetry = tel

            def record_lost() -> str | None:  # every LINK_CHECK_TICKS: one waitpid
                if telemetry.is_alive():
                    return None
                return _telemetry_failure(telemetry, tel_failure, wait=False)

            loop.record_lost = record_lost
            loop_box.append(loop)
            self.loop = loop
            if rt_settings:
                from groundstation.timing import apply_realtime_settings

                settings.update(apply_realtime_settings(lock_memory=False))
                event_sink("real-time settings: " + "; ".join(f"{k}: {v}"
                                                               for k, v in settings.items()))
            elif hold_latency:
                from drivers.realtime import hold_cpu_latency

                settings["cpu idle"] = hold_cpu_latency(0)
                event_sink(f"cpu idle: {settings['cpu idle']}")
            try:
                result = loop.run()
            finally:
                if rt_settings:
                    from groundstation.timing import restore_default_settings

                    restore_default_settings()
                elif hold_latency:
                    from drivers.realtime import release_cpu_latency

                    release_cpu_latency()
            result.telemetry_dropped = ring.dropped
            status[STATUS_STATE] = float(int(loop.sm.state))  # the final state, for the GCS
            if self.stop_signals is not None and self.stop_signals.count:
                result.end_reason += f" (on {self.stop_signals.describe()})"
            # to the events file only: the summary that follows says it to the operator
            with contextlib.suppress(queue.Full):
                events.put_nowait(f"session ended: {result.end_reason}")
            rrd = self.record_path.with_suffix(".rrd")
            outcome = SessionOutcome(result, self.record_path, self.events_path,
                                     loop.preflight_report, settings,
                                     time.perf_counter() - wall0, dashboard_mode,
                                     rrd if dashboard_mode != "off" and rrd.exists() else None)
            return outcome
        finally:
            if fc is not None:
                with contextlib.suppress(Exception):
                    fc.stop_motors()
                fc.close()
            if servo is not None:
                with contextlib.suppress(Exception):
                    servo.stop()
            if mocap is not None:
                with contextlib.suppress(Exception):
                    mocap.close()
            with contextlib.suppress(queue.Full, ValueError):  # the telemetry drains up to it
                events.put_nowait(END_OF_EVENTS)
            stop.set()
            if tel is not None and tel.pid is not None:  # started (its start may have raised)
                tel.join(timeout=30.0)
                if tel.is_alive():
                    tel.kill()
                if tel.exitcode and tel_go.is_set():  # it died: its queued events, at least
                    _salvage_events(events, self.events_path)
            if ring is not None:
                ring.close()
            if forwarder is not None:
                forwarder.stop()  # the telemetry process has ended: its last notices too
            if own_console is not None:
                own_console.stop()
            if self.emulator is not None:
                self.emulator.close()
                self._note_emulator_stats()
                if outcome is not None:  # the truth of the flight, for its verdict
                    outcome.truth.update(self.emulator.exit_truth)
                if lockstep and truth_path is not None and truth_path.exists():
                    with contextlib.suppress(Exception):
                        merge_truth(self.record_path, truth_path, backend.imu_rate_hz)
            if self._tmp is not None:
                self._tmp.cleanup()
            thaw_start_up_heap()


    def _note_emulator_stats(self) -> None:
        """The emulated board's view of the link, appended to the events file."""
        st = self.emulator.exit_stats if self.emulator is not None else {}
        if not st or not self.events_path.exists():
            return
        keys = ("imu_sent", "spin_commands", "stream_slips", "watchdog_trips", "tx_overruns",
                "malformed_received", "frame_errors_received")
        with contextlib.suppress(OSError), self.events_path.open("a", encoding="utf-8") as ev:
            ev.write("emulated board at exit: " + ", ".join(
                f"{k.replace('_', ' ')} {st[k]}" for k in keys if k in st) + "\n")

    def _await_telemetry(self, tel: Any, imported: Any) -> None:
        """Wait until the telemetry process has its imports (on a loaded host they can outlast
        the devices' start-up); a stop signal meanwhile ends the session as in any start-up
        stage."""
        deadline = time.monotonic() + TELEMETRY_START_S
        while not imported.wait(0.05):
            self._check_interrupted("starting the telemetry process")
            if not tel.is_alive():
                raise SessionError(f"the telemetry process exited during start-up (exit code "
                                   f"{tel.exitcode})")
            if time.monotonic() > deadline:
                raise SessionError("the telemetry process did not start within "
                                   f"{TELEMETRY_START_S:.0f} s")

    def _await_record(self, tel: Any, opened: Any, failure: Any) -> None:
        """Wait until the telemetry process has opened the flight record (a file open: ms):
        a record it cannot write ends the session here, before anything is armed."""
        deadline = time.monotonic() + TELEMETRY_START_S
        while not opened.wait(0.02):
            self._check_interrupted("opening the flight record")
            if not tel.is_alive():
                raise SessionError(_telemetry_failure(tel, failure))
            if time.monotonic() > deadline:
                raise SessionError("the telemetry process did not open the flight record "
                                   f"within {TELEMETRY_START_S:.0f} s")

    def _check_interrupted(self, stage: str) -> None:
        """A stop signal during start-up ends the session there: nothing is armed yet. (A
        refused Ctrl-Z is no stop: the loop tells it at its first tick.)"""
        if "stop" in self.requests:
            raise SessionInterruptedError(f"stopped while {stage}: nothing was armed")


class _NoticeForwarder:
    """Lines from the telemetry process (a multiprocessing queue) -> the session's event
    callback, from a thread of this process."""

    def __init__(self, notices: Any, on_event: Callable[[str], None]) -> None:
        self._notices = notices
        self._on_event = on_event
        self._stop = False
        self._thread = threading.Thread(target=self._run, name="fasthex-notices", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def _run(self) -> None:
        while not self._stop:
            try:
                self._on_event(self._notices.get(timeout=0.2))
            except queue.Empty:
                continue
            except (OSError, ValueError, EOFError):  # the queue was closed
                return

    def stop(self) -> None:
        self._stop = True
        if self._thread.is_alive():
            self._thread.join(timeout=1.0)
        while True:
            try:
                self._on_event(self._notices.get_nowait())
            except (queue.Empty, OSError, ValueError, EOFError):
                return


def _open_device(what: str, uri: str, open_it: Callable[[], T]) -> T:
    """Run one device-opening step; a driver or OS error becomes a one-line SessionError
    naming the device and its URI (``flight-ctrl serial:///dev/ttyUSB0: cannot open: ...``)."""
    try:
        return open_it()
    except (DriverError, MocapError, OSError, TimeoutError) as exc:
        text = str(exc) or type(exc).__name__
        raise SessionError(text if uri in text else f"{what} {uri}: {text}") from None


#: lockstep: how long the first servo cycle may take (the servo being configured)
LOCKSTEP_SERVO_START_S = 20.0
#: how long the telemetry process may take for its imports (a loaded host, a cold disk cache)
TELEMETRY_START_S = 60.0
#: the session's last item on the events queue, and how long the telemetry process waits for
#: events still under way once the session has stopped (it died: no end marker comes)
END_OF_EVENTS = "\x00end of events"
END_DRAIN_S = 0.5
#: props-off bench test: idle spin after the spin-up, seconds
PROPS_OFF_SPIN_S = 3.0


def _limits(cfg: SessionConfig, props_off: bool) -> SafetyLimits:
    limits = cfg.safety.limits()
    if props_off:
        from dataclasses import replace

        limits = replace(limits, props_off_spin_s=PROPS_OFF_SPIN_S)
    return limits


def merge_truth(record_path: Path, truth_path: Path, imu_rate_hz: float) -> int:
    """Put the emulated vehicle's true state into a lockstep flight record.

    Row k of a lockstep record is IMU sample k (its ``t_s`` is k IMU periods), and the truth log
    holds the true state at every IMU sample, so they pair by index. ``pos_w_m``, ``vel_w_m_s``,
    ``q_wb`` and ``omega_b_rad_s`` become the truth (what the metrics score, as in ``fasthex
    simulate``); ``est_pos_w_m`` and ``est_q_wb`` keep what the controller was fed. The file is
    replaced atomically. Returns the number of rows given a true state."""
    from groundstation.record import RecordWriter, read_record
    from sim_backend.backend import TruthLog

    rec = read_record(record_path)
    truth = TruthLog.read(truth_path)
    rows = rec.rows.copy()
    idx = np.rint(rows["t_s"] * imu_rate_hz).astype(np.int64)
    ok = (idx >= 0) & (idx < len(truth))
    if not np.any(ok):
        return 0
    t = truth[idx[ok]]
    rows["pos_w_m"][ok] = t[:, 1:4]
    rows["vel_w_m_s"][ok] = t[:, 4:7]
    rows["q_wb"][ok] = t[:, 7:11]
    rows["omega_b_rad_s"][ok] = t[:, 11:14]
    meta = dict(rec.metadata, state="true state of the emulated vehicle (est_*: the estimate)")
    tmp = record_path.with_suffix(record_path.suffix + ".tmp")
    try:
        writer = RecordWriter(tmp, meta, keep_in_memory=False)
        writer.append_block(rows)
        writer.close()
        os.replace(tmp, record_path)
    except OSError:  # a full disk: the record as the flight wrote it stands, no stray file
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise
    return int(np.sum(ok))


def _estimator_config(cfg: SessionConfig, params: VehicleParams) -> Any:
    from dataclasses import replace

    return replace(cfg.estimator, mass_kg=params.mass_kg, gravity_m_s2=params.gravity_m_s2)

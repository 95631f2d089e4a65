"""The emulated backend: one process that owns the simulated FAST-Hex and exposes its devices.

- **flight-ctrl**: the emulated Flight-Ctrl (tk3) on a pty, driving the simulator's rotors and
  reading its IMU model;
- **servo**: the emulated MX-28T on a pty, geared to the simulator's tilt drive;
- **mocap**: an emulated NatNet (Motive) server on UDP loopback, or with ``--mocap qtm`` an
  emulated Qualisys QTM RT server on TCP loopback, streaming the simulator's pose with the
  preset's noise, rate and latency.

Time: the Flight-Ctrl emulator is the only thing that advances the physics (one IMU period per
received ``w`` frame in ``lockstep``, the wall clock in ``realtime``). Every advance also lets the
MoCap server publish the frames due at the new simulated time, *before* the Flight-Ctrl writes
the IMU sample of that time: a ground station that drains its MoCap socket when it receives an
IMU sample sees exactly the poses due by then, so lockstep flights are deterministic.

Run as ``python -m sim_backend.backend --vehicle fasthex --disturbances paper-calibrated
--start X Y Z --seed N --clock lockstep --link-dir DIR [--scenario FILE]``.

A scenario (:mod:`sim_backend.scenario`) sets the simulated plant at once; its disturbances and
faults are timed in mission seconds and wait for the ground station's ``scenario-start`` line on
stdin (sent when its mission clock starts): the backend anchors the schedule at its simulated
time then and answers ``{"scenario_t0_s": T}``. In lockstep the physics stands still until the
ground station's next ``w`` frame, so the anchor is the time of the IMU sample the ground station
is answering. It prints one JSON line per device
(``{"device": "flight-ctrl", "kind": "pty", "address": PATH}``) and then ``{"ready": true}``,
and runs until SIGINT/SIGTERM, a ``quit`` line on stdin, or the death of its parent (stdin
closing without ``quit``): then it first lets the emulated board's watchdog stop the motors.
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import dataclasses
import json
import logging
import math
import os
import select
import signal
import sys
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, Protocol

import numpy as np

from config import find_config
from config.schema import load_config
from controller.params import VEHICLE_SCHEMA, VehicleParams
from drivers.realtime import apply_realtime_settings, freeze_start_up_heap, settings_line
from sim_backend.disturbances import DISTURBANCES_SCHEMA, DisturbancePreset
from sim_backend.emulators.dynamixel_p1 import EmulatedMX28, Fault
from sim_backend.emulators.flightctrl import (
    EmulatedFlightCtrl,
    FlightCtrlEmulatorConfig,
    WireFaults,
)
from sim_backend.emulators.natnet import NatNetEmulatorConfig, NatNetServer
from sim_backend.emulators.qtm import QtmEmulatorConfig, QtmServer
from sim_backend.faults import (  # noqa: F401  (re-exported: the backend's fault API)
    FAULT_KINDS,
    SIGNED_FAULT_KINDS,
    TILT_KICK_S,
    TILT_KICK_STEPS,
    FaultKind,
    ImuWireLoss,
    ScheduledFault,
)
from sim_backend.scenario import SCENARIO_SCHEMA, Scenario
from sim_backend.simulator import FastHexSimulator
from sim_backend.vehicle import EmulatedVehicle, ImuReading, PoseReading

log = logging.getLogger(__name__)

Vec3 = tuple[float, float, float]

#: Present Position of the emulated servo at tilt 0 (where the mechanism was assembled).
SERVO_ZERO_OFFSET_STEPS = 1024


@dataclass(frozen=True)
class BackendOptions:
    vehicle: VehicleParams
    preset: DisturbancePreset
    start_pos_w_m: Vec3
    seed: int = 1
    clock: Literal["realtime", "lockstep"] = "lockstep"
    link_dir: Path | None = None
    wire_faults: WireFaults = field(default_factory=WireFaults)
    watchdog_s: float = 0.25
    faults: tuple[ScheduledFault, ...] = ()
    truth_path: Path | None = None
    # clock errors to rehearse the time base on (not faults: they are there from the start)
    board_clock_ppm: float = 0.0
    mocap_clock_offset_s: float = 0.0
    mocap_clock_ppm: float = 0.0
    mocap: Literal["natnet", "qtm"] = "natnet"  # which MoCap server the vehicle is seen by
    scenario: Scenario | None = None


@dataclass(frozen=True)
class DeviceAddress:
    device: str
    kind: Literal["pty", "udp", "tcp"]
    address: str


class TruthLog:
    """The true state at every IMU sample, for scoring a flight flown through the byte path.

    Binary file of float64 rows ``t_s, pos_w_m[3], vel_w_m_s[3], q_wb[4], omega_b_rad_s[3]``
    (14 columns), appended every 50 rows (100 ms at 500 Hz) so a killed emulator loses little.
    """

    COLUMNS = 14

    def __init__(self, path: Path) -> None:
        self._fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        self._rows: list[tuple[float, ...]] = []

    def append(self, row: tuple[float, ...]) -> None:
        self._rows.append(row)
        if len(self._rows) >= 50:
            self.flush()

    def flush(self) -> None:
        if self._rows and self._fd >= 0:
            os.write(self._fd, np.asarray(self._rows, dtype=np.float64).tobytes())
            self._rows = []

    def close(self) -> None:
        self.flush()
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1

    @classmethod
    def read(cls, path: Path) -> np.ndarray:
        data = np.fromfile(path, dtype=np.float64)
        return data[: len(data) // cls.COLUMNS * cls.COLUMNS].reshape(-1, cls.COLUMNS)


class _Publisher(Protocol):
    def publish_due(self, now_s: float, defer: bool = False) -> int: ...

    def capture_deferred(self) -> int: ...


class _SteppedVehicle:
    """The simulator as the emulators see it: each advance also publishes the MoCap frames due
    at the new time. Implements :class:`EmulatedVehicle` by delegation.

    With ``defer_captures`` (lockstep) a frame due at an advance is captured at :meth:`settle`,
    which the emulated board calls once its reply is on the wire (the capture then runs while
    the ground station computes, off the lockstep round trip), or at the next advance, before
    the vehicle moves: either way at the pose of its capture time.
    """

    def __init__(self, sim: FastHexSimulator, defer_captures: bool = False) -> None:
        self.sim = sim
        self.defer_captures = defer_captures
        self.on_advance: list[_Publisher] = []
        #: (simulated time, action) pairs, run once when the time is reached
        self.scheduled: list[tuple[float, Callable[[], None]]] = []
        self.truth: TruthLog | None = None
        # scheduled faults that alter what the devices read (not the physics)
        self.battery_sag_v = 0.0
        self.mocap_offset_w_m: Vec3 = (0.0, 0.0, 0.0)
        self.mocap_frozen: PoseReading | None = None  # mocap-freeze: the pose it sticks at

    def now_s(self) -> float:
        return self.sim.now_s()

    def advance(self, dt_s: float) -> None:
        self.settle()
        self.sim.advance(dt_s)
        now = self.sim.now_s()
        while self.scheduled and self.scheduled[0][0] <= now:
            self.scheduled.pop(0)[1]()
        for publisher in self.on_advance:
            publisher.publish_due(now, self.defer_captures)

    def settle(self) -> None:
        """Run the work deferred from the last advance (the MoCap captures)."""
        if self.defer_captures:
            for publisher in self.on_advance:
                publisher.capture_deferred()

    def command_rotor_speeds_hz(self, speeds_hz: Sequence[float]) -> None:
        self.sim.command_rotor_speeds_hz(speeds_hz)

    def rotor_speeds_hz(self) -> tuple[float, ...]:
        return self.sim.rotor_speeds_hz()

    def motor_currents_a(self) -> tuple[float, ...]:
        return self.sim.motor_currents_a()

    def read_imu(self) -> ImuReading:
        if self.truth is not None:  # the Flight-Ctrl samples the IMU: log the truth with it
            st = self.sim.state()
            self.truth.append((self.sim.now_s(), *st.pos_w_m, *st.vel_w_m_s, *st.q_wb,
                               *st.omega_b_rad_s))
        return self.sim.read_imu()

    def command_tilt_rad(self, tilt_rad: float) -> None:
        self.sim.command_tilt_rad(tilt_rad)

    def tilt_rad(self) -> float:
        return self.sim.tilt_rad()

    def true_pose(self) -> PoseReading:
        pose = self.sim.true_pose()
        if self.mocap_frozen is not None:  # same place and attitude, the time goes on
            return PoseReading(pose.t_s, self.mocap_frozen.pos_w_m, self.mocap_frozen.q_wb)
        o = self.mocap_offset_w_m
        if o == (0.0, 0.0, 0.0):
            return pose
        p = pose.pos_w_m
        return PoseReading(pose.t_s, (p[0] + o[0], p[1] + o[1], p[2] + o[2]), pose.q_wb)

    def battery_voltage_v(self) -> float:
        return self.sim.battery_voltage_v() - self.battery_sag_v


class EmulatedVehicleBackend:
    """Builds and runs the simulator and its three emulated devices (see module docstring)."""

    def __init__(self, opts: BackendOptions) -> None:
        self.opts = opts
        p = opts.preset
        sc = opts.scenario
        # the plant is the scenario's; the ground station flies with the vehicle file
        self.sim = FastHexSimulator(opts.vehicle if sc is None else sc.plant_params(opts.vehicle),
                                    p, seed=opts.seed, start_pos_w_m=opts.start_pos_w_m,
                                    plant=None if sc is None else sc.plant,
                                    disturbances=() if sc is None else sc.disturbances)
        lockstep = opts.clock == "lockstep"
        self.vehicle = _SteppedVehicle(self.sim, defer_captures=lockstep)
        assert isinstance(self.vehicle, EmulatedVehicle)
        self.lock = threading.Lock()
        link = opts.link_dir
        self.flight_ctrl = EmulatedFlightCtrl(
            self.vehicle, lock=self.lock,
            after_output=self.vehicle.settle if lockstep else None,
            link_path=link / "flight-ctrl" if link else None,
            config=FlightCtrlEmulatorConfig(clock=opts.clock, faults=opts.wire_faults,
                                            watchdog_s=opts.watchdog_s,
                                            board_clock_error_ppm=opts.board_clock_ppm),
        )
        self.servo = EmulatedMX28(
            self.vehicle, lock=self.lock, link_path=link / "servo" if link else None,
            gear_ratio=opts.vehicle.tilt.worm_ratio, zero_offset_steps=SERVO_ZERO_OFFSET_STEPS,
            step_on_wall_clock=opts.clock == "realtime",
        )
        natnet_cfg = NatNetEmulatorConfig(
            command_port=0,
            rate_hz=p.mocap_rate_hz,
            pos_noise_m=p.mocap_pos_noise_m,
            rot_noise_rad=p.mocap_att_noise_rad,
            latency_s=p.mocap_latency_s,
            occlusion_probability=p.mocap_dropout_prob,
            occlusion_frames=1,
            seed=opts.seed,
            server_clock_offset_s=opts.mocap_clock_offset_s,
            server_clock_drift_ppm=opts.mocap_clock_ppm,
        )
        self.mocap: NatNetServer | QtmServer
        if opts.mocap == "qtm":  # the same preset: rate, noise, latency, dropouts, clock
            c = natnet_cfg
            self.mocap = QtmServer(self.vehicle, QtmEmulatorConfig(
                port=0, rate_hz=c.rate_hz, pos_noise_m=c.pos_noise_m,
                rot_noise_rad=c.rot_noise_rad, latency_s=c.latency_s,
                occlusion_probability=c.occlusion_probability,
                occlusion_frames=c.occlusion_frames, seed=c.seed,
                server_clock_offset_s=c.server_clock_offset_s,
                server_clock_drift_ppm=c.server_clock_drift_ppm), lock=threading.Lock())
        else:
            self.mocap = NatNetServer(self.vehicle, natnet_cfg, lock=threading.Lock())
        self.vehicle.on_advance.append(self.mocap)
        if opts.truth_path is not None:
            self.vehicle.truth = TruthLog(opts.truth_path)
        actions = []
        for fault in opts.faults:
            # a kick is spread over TILT_KICK_S: the IMU sees a real (plausible) rate change
            # rather than a jump its driver must take for a corrupted byte
            times = ([fault.t_s + i * TILT_KICK_S / TILT_KICK_STEPS
                      for i in range(TILT_KICK_STEPS)] if fault.kind == "tilt-kick"
                     else [fault.t_s])
            actions += [(t, self._fault_action(fault)) for t in times]
        self.vehicle.scheduled.extend(sorted(actions, key=lambda a: a[0]))
        if any(f.kind in ("imu-rate", "imu-gap") for f in opts.faults):
            self.flight_ctrl.imu_wire_fault = ImuWireLoss(opts.faults)
        self._started = False
        self.scenario_t0_s: float | None = None

    def start_scenario(self) -> float:
        """Anchor the scenario's schedule (mission time 0) at the present simulated time and
        schedule its faults; returns that time. Idempotent: a second call changes nothing."""
        sc = self.opts.scenario
        with self.lock:  # the Flight-Ctrl thread advances the physics under this lock
            if self.scenario_t0_s is not None:
                return self.scenario_t0_s
            t0 = self.sim.now_s()
            self.scenario_t0_s = t0
            if sc is None:
                return t0
            self.sim.start_scenario(t0)
            shifted = [dataclasses.replace(f, t_s=f.t_s + t0) for f in sc.scheduled_faults()]
            actions = list(self.vehicle.scheduled)
            for fault in shifted:
                times = ([fault.t_s + i * TILT_KICK_S / TILT_KICK_STEPS
                          for i in range(TILT_KICK_STEPS)] if fault.kind == "tilt-kick"
                         else [fault.t_s])
                actions += [(t, self._fault_action(fault)) for t in times]
            self.vehicle.scheduled[:] = sorted(actions, key=lambda a: a[0])
            wire = [*self.opts.faults, *shifted]
            if any(f.kind in ("imu-rate", "imu-gap") for f in shifted):
                self.flight_ctrl.imu_wire_fault = ImuWireLoss(wire)
            return t0

    def _fault_action(self, fault: ScheduledFault) -> Callable[[], None]:
        if fault.kind == "mocap-dropout":
            frames = max(1, round(fault.duration_s * self.mocap.config.rate_hz))
            return lambda: self.mocap.occlude(frames)
        if fault.kind == "servo-silent":
            return lambda: self.servo.set_fault(Fault.SILENT)
        vehicle = self.vehicle
        if fault.kind == "battery-sag":
            def sag() -> None:
                vehicle.battery_sag_v += fault.value
            return sag
        if fault.kind == "mocap-jump":
            def jump() -> None:
                o = vehicle.mocap_offset_w_m
                vehicle.mocap_offset_w_m = (o[0] + fault.value, o[1], o[2])
            return jump
        if fault.kind == "rotor-thrust":
            return lambda: self.sim.scale_rotor_thrust(fault.value, fault.rotor)
        if fault.kind == "mocap-latency":
            def latency() -> None:  # frames already queued keep their transmit time
                self.mocap.config = dataclasses.replace(self.mocap.config,
                                                        latency_s=fault.value)
            return latency
        if fault.kind == "mocap-freeze":
            def freeze() -> None:
                vehicle.mocap_frozen = vehicle.true_pose()
            return freeze
        if fault.kind == "tilt-kick":  # one of TILT_KICK_STEPS (see __init__)
            step = math.radians(fault.value) / TILT_KICK_STEPS
            return lambda: self.sim.kick_body_rate((step, 0.0, 0.0))
        if fault.kind in ("imu-rate", "imu-gap"):
            return lambda: None  # the board's wire hook checks the sample times itself
        # fc-disconnect: from the Flight-Ctrl's own thread, which is advancing the physics
        return lambda: threading.Thread(target=self.flight_ctrl.disconnect, daemon=True).start()

    def truth_at_exit(self) -> dict[str, object]:
        """What only the emulator knows of the flight, for the ground station's verdict: the
        vertical speed of every touchdown (m/s), whether the vehicle rests on the ground, and
        the height of its reference point above its resting height (m)."""
        from sim_backend.closed_loop import SAFE_TOUCHDOWN_SPEED_M_S

        sim = self.sim
        speeds = [round(v, 4) for v in sim.touchdown_speeds_m_s]
        height_m = round(sim.true_pose().pos_w_m[2] - sim.ground_height_m, 4)  # as reported
        crash = ""
        fastest = max(speeds, default=0.0)
        if fastest > SAFE_TOUCHDOWN_SPEED_M_S:
            crash = (f"a touchdown at {fastest:.2f} m/s (a safe one is <= "
                     f"{SAFE_TOUCHDOWN_SPEED_M_S:g} m/s)")
        # the motors are off by now: a vehicle still up falls (the session ended above ground)
        fall_m_s = math.sqrt(2.0 * sim.params.gravity_m_s2 * max(height_m, 0.0))
        if not sim.landed and fall_m_s > SAFE_TOUCHDOWN_SPEED_M_S:
            crash = (crash + "; " if crash else "") + (
                f"the session ended {height_m:.2f} m up with the motors stopped: a fall, "
                f">= {fall_m_s:.1f} m/s at the ground")
        return {"touchdown_speeds_m_s": speeds, "landed": sim.landed,
                "height_m": height_m, "crash": crash}

    def start(self) -> list[DeviceAddress]:
        self.mocap.start(realtime=False)
        self.servo.start()
        self.flight_ctrl.start()
        self._started = True
        return self.addresses()

    def addresses(self) -> list[DeviceAddress]:
        return [
            DeviceAddress("flight-ctrl", "pty", self.flight_ctrl.path),
            DeviceAddress("servo", "pty", self.servo.path),
            DeviceAddress("mocap", "tcp", f"127.0.0.1:{self.mocap.port}")
            if isinstance(self.mocap, QtmServer) else
            DeviceAddress("mocap", "udp", f"127.0.0.1:{self.mocap.command_port}"),
        ]

    def stop(self) -> None:
        for stop in (self.flight_ctrl.stop, self.servo.close, self.mocap.close):
            with contextlib.suppress(Exception):
                stop()
        self.end_truth_log()

    def end_truth_log(self) -> None:
        """Write out and close the truth log (idempotent). Called as soon as the ground station
        is gone, so the log ends at the last tick it flew: the board's free run that follows
        (the watchdog stopping the motors) is no part of the flight."""
        with self.lock:  # the Flight-Ctrl thread appends under this lock
            truth, self.vehicle.truth = self.vehicle.truth, None
        if truth is not None:
            truth.close()


def _die_with_parent() -> None:
    """Linux: get SIGUSR1 when the parent dies (kill -9 included)."""
    if not sys.platform.startswith("linux"):
        return
    with contextlib.suppress(OSError, AttributeError):
        libc = ctypes.CDLL("libc.so.6", use_errno=True)
        pr_set_pdeathsig = 1
        libc.prctl(pr_set_pdeathsig, signal.SIGUSR1)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m sim_backend.backend",
                                 description="Run the emulated FAST-Hex and its devices.")
    ap.add_argument("--vehicle", default="fasthex")
    ap.add_argument("--disturbances", default="paper-calibrated")
    ap.add_argument("--start", nargs=3, type=float, default=(0.0, 0.0, 0.1),
                    metavar=("X", "Y", "Z"), help="start position of O_B (m, world)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--clock", choices=("realtime", "lockstep"), default="lockstep")
    ap.add_argument("--link-dir", type=Path, default=None,
                    help="directory for stable device symlinks")
    ap.add_argument("--corrupt-prob", type=float, default=0.0,
                    help="byte corruption probability on the Flight-Ctrl link")
    ap.add_argument("--watchdog-s", type=float, default=0.25)
    ap.add_argument("--truth", type=Path, default=None,
                    help="log the true state at every IMU sample to this file")
    ap.add_argument("--realtime-settings", choices=("on", "off"), default="on",
                    help="realtime clock: pin to the first CPU, SCHED_FIFO, locked memory "
                    "(each where permitted)")
    ap.add_argument("--fault", action="append", default=[], metavar="KIND@T[:D]",
                    help=f"inject a fault at simulated time T ({', '.join(FAULT_KINDS)})")
    ap.add_argument("--board-clock-ppm", type=float, default=0.0,
                    help="rate error of the board's sample clock (-12000: 1.2 %% slow)")
    ap.add_argument("--mocap-clock-offset-s", type=float, default=0.0,
                    help="the MoCap server's clock minus the emulator's (>= 0)")
    ap.add_argument("--mocap-clock-ppm", type=float, default=0.0,
                    help="rate error of the MoCap server's clock")
    ap.add_argument("--scenario", type=Path, default=None, metavar="FILE",
                    help="scenario file: plant overrides now, disturbances and faults from "
                    "the ground station's scenario-start on")
    ap.add_argument("--mocap", choices=("natnet", "qtm"), default="natnet",
                    help="emulated MoCap server: NatNet (Motive, UDP) or Qualisys QTM RT (TCP)")
    args = ap.parse_args(argv)
    try:
        faults = tuple(ScheduledFault.parse(f) for f in args.fault)
    except ValueError as exc:
        ap.error(str(exc))
    parent = os.getppid()
    _die_with_parent()
    logging.basicConfig(level=logging.WARNING, stream=sys.stderr,
                        format="emulator %(levelname)s %(name)s: %(message)s")
    vehicle = load_config(find_config("vehicles", args.vehicle), VehicleParams,
                          schema=VEHICLE_SCHEMA)
    preset = load_config(find_config("disturbances", args.disturbances), DisturbancePreset,
                         schema=DISTURBANCES_SCHEMA)
    scenario = None if args.scenario is None else load_config(
        args.scenario, Scenario, schema=SCENARIO_SCHEMA)
    backend = EmulatedVehicleBackend(BackendOptions(
        vehicle=vehicle, preset=preset, start_pos_w_m=(args.start[0], args.start[1], args.start[2]),
        seed=args.seed, clock=args.clock, link_dir=args.link_dir,
        wire_faults=WireFaults(corrupt_prob=args.corrupt_prob, seed=args.seed),
        watchdog_s=args.watchdog_s, faults=faults, truth_path=args.truth,
        board_clock_ppm=args.board_clock_ppm, mocap_clock_offset_s=args.mocap_clock_offset_s,
        mocap_clock_ppm=args.mocap_clock_ppm, mocap=args.mocap, scenario=scenario,
    ))
    # the set-up's heap collected and frozen before any device thread runs: the collections
    # while it serves walk only what was made since (a full one would hold the interpreter,
    # and the board's replies, for ~50 ms)
    freeze_start_up_heap()
    stop = _StopFlags()
    # Handlers only set a flag; the C-level wake-up byte ends the main thread's wait at once.
    # (``threading.Event.set`` from a handler can deadlock on the lock the interrupted main
    # thread holds inside ``Event.wait``.)
    signal.set_wakeup_fd(stop.wake_fd, warn_on_full_buffer=False)
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, stop.on_stop_signal)
    signal.signal(signal.SIGUSR1, stop.on_parent_death)
    try:
        for dev in backend.start():
            print(json.dumps({"device": dev.device, "kind": dev.kind, "address": dev.address}),
                  flush=True)
        realtime = ""
        if args.clock == "realtime" and args.realtime_settings == "on":
            # the first CPU: the ground station pins itself to the last one
            realtime = settings_line(apply_realtime_settings(cpu=0, freeze_gc=False))
        print(json.dumps({"ready": True, "t_s": backend.sim.now_s(), "realtime": realtime}),
              flush=True)

        def _watch_stdin() -> None:
            # "quit" is the parent's orderly stop; end of input without it means the parent
            # died (its end of the pipe closes before the kernel re-parents us).
            with contextlib.suppress(Exception):
                for line in sys.stdin:
                    if line.strip() == "scenario-start":
                        t0 = backend.start_scenario()
                        print(json.dumps({"scenario_t0_s": t0}), flush=True)
                        continue
                    if line.strip() == "quit":
                        stop.request(orphaned=False)
                        return
            stop.request(orphaned=True)

        if not sys.stdin.isatty():
            threading.Thread(target=_watch_stdin, daemon=True).start()
        while not stop.wait(0.5):
            if os.getppid() != parent:
                stop.orphaned = True
                break
        if stop.orphaned or os.getppid() != parent:
            stop.orphaned = True
            _await_watchdog(backend, args.link_dir)
    finally:
        backend.stop()
        # a ground station gone (kill -9) cannot remove the temporary folder it made for the
        # links (and the truth log, megabytes): the emulator, its last user, does (the note
        # on the watchdog went to the log above)
        link_dir = args.link_dir
        if stop.orphaned and link_dir is not None and (link_dir / TEMPORARY_MARKER).exists():
            import shutil

            shutil.rmtree(link_dir, ignore_errors=True)
        # the board's counters, for the ground station's events (stream slips: the emulator
        # fell behind its own clock; watchdog trips: no `w` for the watchdog time)
        with contextlib.suppress(Exception):
            print(json.dumps({"exit": dataclasses.asdict(backend.flight_ctrl.stats()),
                              "truth": backend.truth_at_exit()}), flush=True)
    return 0


class _StopFlags:
    """Why and when the emulator stops, set from signal handlers and the stdin watcher without
    a lock: plain attributes plus a self-pipe that wakes :meth:`wait`."""

    def __init__(self) -> None:
        self.stop = False
        self.orphaned = False
        self._r, self.wake_fd = os.pipe()
        os.set_blocking(self._r, False)
        os.set_blocking(self.wake_fd, False)

    def on_stop_signal(self, signum: int, frame: object) -> None:
        self.stop = True

    def on_parent_death(self, signum: int, frame: object) -> None:
        self.orphaned = True
        self.stop = True

    def request(self, *, orphaned: bool) -> None:
        """From a thread: stop (the parent died, or it asked with ``quit``)."""
        if orphaned:
            self.orphaned = True
        self.stop = True
        with contextlib.suppress(OSError):
            os.write(self.wake_fd, b"\0")

    def wait(self, timeout_s: float) -> bool:
        if not self.stop:
            with contextlib.suppress(OSError):
                ready, _, _ = select.select([self._r], [], [], timeout_s)
                if ready:
                    with contextlib.suppress(OSError):
                        os.read(self._r, 512)
        return self.stop


#: in a link folder, a file saying the ground station made the folder for one session (a
#: temporary folder): an emulator orphaned by a killed ground station removes that folder
TEMPORARY_MARKER = ".fasthex-temporary"


def _await_watchdog(backend: EmulatedVehicleBackend, link_dir: Path | None) -> None:
    """The ground station died without stopping the motors: keep the emulated board running
    (it free-runs after its lockstep grace period) until its BL-Ctrl watchdog has stopped every
    motor, as the real board would, and leave a note of it in ``link_dir/emulator-exit.json``."""
    import time

    backend.end_truth_log()  # the flight ended with the ground station's last tick
    deadline = time.monotonic() + 10.0
    fc = backend.flight_ctrl
    while time.monotonic() < deadline and any(s > 0.0 for s in fc.commanded_rotor_speeds_hz()):
        time.sleep(0.05)
    stats = fc.stats()
    note = {"reason": "ground station gone", "sim_time_s": fc.sim_time_s(),
            "watchdog_trips": stats.watchdog_trips,
            "motors_stopped": not any(s > 0.0 for s in fc.commanded_rotor_speeds_hz())}
    log.warning("ground station gone: %s", note)
    if link_dir is not None:
        (link_dir / "emulator-exit.json").write_text(json.dumps(note))


if __name__ == "__main__":
    sys.exit(main())

"""Emulated MikroKopter Flight-Ctrl with six BL-Ctrls, on a pseudo-terminal.

Speaks the same bytes as the board, through the codecs of :mod:`drivers.mikrokopter`:

- **tk3 firmware** (default): answers ``?`` with ``?<firmware_id>`` (``mkfl1.8``), honours the
  stream periods ``i``/``m``/``b``/``c`` (µs, 0 = off) with an 8-bit sequence number per
  stream (periods outside what the board supports, 500 µs .. 1 s, i.e. 1 Hz .. 2 kHz, and
  at least 2 ms for the six-frame motor stream, are clamped to that range and counted: a
  period of 1 µs cannot flood the link, nor one of 2^30 µs stall a lockstep flight), starts
  motors on ``g`` (state ``starting`` 0x10 for ``motor_start_s``, then ``spinning`` 0x20 at
  the slowest speed until a ``w`` arrives), applies ``w`` spin rates to the vehicle's rotors,
  stops on ``x``, and - as the BL firmware does - stops every running motor and raises the
  ``emergency`` flag (0x80) when no ``w`` arrived within ``watchdog_s``. Motor-state ``M``
  frames are sent for every motor each motor period.
- **stock firmware** (``firmware="stock"``): ``#``-framed replies to ``v`` (VersionInfo), ``d``
  (DebugOut stream), ``c`` (Data3D stream), ``t`` (engine test, applied while disarmed) and
  ``b`` (ExternControl ack); it ignores tk3 frames, like a real stock board.

Input side: any byte sequence is survived. Frames that do not decode, ``w`` frames with the
wrong motor count, clamped periods and spin rates beyond the BL-Ctrl's range
(:data:`drivers.mikrokopter.messages.MAX_SPIN_HZ`, held at that speed) are counted in
:class:`EmulatorStats` (``dropped_inputs``). :meth:`EmulatedFlightCtrl.feed` hands bytes to
the input side in process (fuzzing) exactly as the pty reader does.

Clocks (``clock=``):

- ``realtime``: simulated time follows the wall clock; streams are paced by it.
- ``lockstep``: the emulator advances the vehicle by exactly one IMU period each time a ``w``
  frame arrives and then sends the next ``I`` sample (plus any ``M``/``B``/``C`` falling due),
  so a flight runs as fast as the ground station answers and is deterministic. Setting a
  non-zero IMU period sends one ``I`` at once to start the exchange. If no ``w`` arrives for
  ``lockstep_grace_s`` of wall time (a dead ground station; before the first ``w`` ever,
  ``lockstep_first_w_grace_s``: one still starting its other devices), the emulator free-runs
  in real time until the next ``w``; the watchdog always counts simulated time, so a dead
  ground station still gets its motors stopped.

Wire faults (:class:`WireFaults`): output paced at a baud rate (10 bits per byte; frames that
would overflow a 50 ms UART backlog are dropped and counted), random byte corruption and byte
drops on the board -> host direction, and :meth:`EmulatedFlightCtrl.disconnect` (the client
sees the device disappear).

The vehicle is only used through :class:`sim_backend.vehicle.EmulatedVehicle`, every call under
the optional shared ``lock``. IMU vectors go body -> board axes through the same
:class:`drivers.mikrokopter.messages.ImuAxes` the driver uses to come back.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import math
import random
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import IntEnum
from pathlib import Path
from typing import Literal, TypeVar

from config.schema import ConfigValueError
from drivers.mikrokopter import framing_stock, framing_tk3
from drivers.mikrokopter import messages as mkm
from sim_backend.ptylink import PtyEndpoint
from sim_backend.vehicle import EmulatedVehicle

__all__ = ["EmulatedFlightCtrl", "EmulatorStats", "FlightCtrlEmulatorConfig", "SentImu",
           "WireFaults"]

log = logging.getLogger(__name__)

_NS = 1_000_000_000
_MAX_STEP_NS = 2_000_000  # physics steps no longer than 2 ms
_TX_BACKLOG_S = 0.05
_EARTH_FIELD_W_T = (2.0e-5, 0.0, -4.3e-5)  # roughly mid-latitude Europe, world z up
_MAX_SPEED_HZ_FOR_THROTTLE = 130.0
_FASTEST_HALF_PERIOD_US = round(500_000 / mkm.MAX_SPIN_HZ)
_T = TypeVar("_T")


@dataclass(frozen=True, slots=True)
class WireFaults:
    """Faults of the emulated wire (board -> host direction)."""

    baud: int | None = None
    """Pace output at this rate (8N1: 10 bits per byte); None = as fast as the pty goes."""
    corrupt_prob: float = 0.0
    """Probability that a byte is replaced by a different random byte."""
    drop_prob: float = 0.0
    """Probability that a byte is lost."""
    disconnect_after_s: float | None = None
    """Pull the cable (close the pty) once this much simulated time has passed since start."""
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("corrupt_prob", "drop_prob"):
            value = getattr(self, name)
            if not 0.0 <= value < 1.0:
                raise ConfigValueError(name, f"{value} outside [0, 1)")
        if self.baud is not None and self.baud <= 0:
            raise ConfigValueError("baud", f"{self.baud} must be > 0")


@dataclass(frozen=True, slots=True)
class FlightCtrlEmulatorConfig:
    firmware: Literal["tk3", "stock"] = "tk3"
    firmware_id: str = "mkfl1.8"
    """What ``?`` answers (tk3)."""
    stock_version: tuple[int, int, int] = (2, 12, 0)
    """SW major, minor, patch reported by a stock board (2.12a)."""
    n_motors: int = 6
    clock: Literal["realtime", "lockstep"] = "realtime"
    watchdog_s: float = 0.25
    """BL-side timeout: no ``w`` for this long (simulated time) stops the motors. A stock
    board applies the same time to its engine test (``t``), which must be renewed."""
    lockstep_grace_s: float = 2.0
    """Lockstep only: wall time without any ``w`` after which the emulator free-runs."""
    lockstep_first_w_grace_s: float = 30.0
    """Lockstep, before any `w` has arrived: the grace before free-running."""
    lockstep_default_period_s: float = 0.002
    """Lockstep step while the IMU stream is off."""
    motor_start_s: float = 0.3
    """Duration of the open-loop start (``starting`` flag) in simulated time."""
    imu_axes: mkm.ImuAxes = field(default_factory=mkm.ImuAxes)
    faults: WireFaults = field(default_factory=WireFaults)
    record_truth: bool = False
    """Keep every sent ``I`` sample (with whether the wire altered it) for tests."""
    board_clock_error_ppm: float = 0.0
    """Rate error of the board's crystal (-12000: 1.2 % slow): every stream period is that
    much longer in true time (a 2 ms ``I`` period lasts 2.024 ms), in realtime and in lockstep
    alike. In lockstep each ``w`` then advances the vehicle by the longer period, so a host
    that counts samples x 2 ms runs slow against the vehicle, as it would on such a board."""

    def __post_init__(self) -> None:
        if not 1 <= self.n_motors <= 15:
            raise ConfigValueError("n_motors", f"{self.n_motors} outside 1..15")
        if not abs(self.board_clock_error_ppm) <= 50_000.0:
            raise ConfigValueError("board_clock_error_ppm", "must be within +-50000 ppm")
        for name in ("watchdog_s", "lockstep_grace_s", "lockstep_first_w_grace_s",
                     "lockstep_default_period_s",
                     "motor_start_s"):
            if not getattr(self, name) > 0.0:
                raise ConfigValueError(name, "must be > 0")


@dataclass(slots=True)
class EmulatorStats:
    frames_received: int = 0
    malformed_received: int = 0
    spin_commands: int = 0
    imu_sent: int = 0
    frames_sent: int = 0
    frames_altered: int = 0
    """Frames in which at least one byte was corrupted or dropped."""
    bytes_corrupted: int = 0
    bytes_dropped: int = 0
    tx_overruns: int = 0
    """Frames dropped because the paced UART backlog was full."""
    stream_slips: int = 0
    """Stream periods skipped because the emulator fell behind (realtime)."""
    watchdog_trips: int = 0
    lockstep_steps: int = 0
    freerun_entries: int = 0
    frame_errors_received: int = 0
    """Received frames the deframer dropped (aborted, truncated, oversize, bad escape or
    checksum)."""
    periods_clamped: int = 0
    """Stream periods outside 500 µs .. 1 s, clamped into that range."""
    spin_rates_clamped: int = 0
    """``w`` values faster than the BL-Ctrl's top speed, held at the top speed."""
    input_errors: int = 0
    """Inputs whose handling failed unexpectedly (logged); the emulator keeps running."""

    @property
    def dropped_inputs(self) -> int:
        """Received frames not applied as sent: undecodable, malformed or failed."""
        return self.frame_errors_received + self.malformed_received + self.input_errors


@dataclass(frozen=True, slots=True)
class SentImu:
    """An ``I`` sample as the emulator sent it (``seq`` = total count, wire seq = seq % 256)."""

    seq: int
    t_ns: int
    message: mkm.ImuMessage
    altered: bool
    wire: bytes
    """The bytes put on the wire (after any corruption or drops)."""


class _MotorState(IntEnum):
    OFF = 0
    STARTING = 1
    SPINNING = 2


@dataclass(slots=True)
class _Motor:
    state: _MotorState = _MotorState.OFF
    emergency: bool = False
    start_ns: int = 0
    cmd_half_period: int = mkm.HALF_PERIOD_SLOWEST


class EmulatedFlightCtrl:
    """The emulated board. ``start()`` runs it on its own thread; ``stop()`` ends it.

    ``path`` is what a client opens (the stable symlink when ``link_path`` is given).
    """

    def __init__(self, vehicle: EmulatedVehicle, *, lock: threading.Lock | None = None,
                 link_path: str | Path | None = None,
                 config: FlightCtrlEmulatorConfig | None = None,
                 after_output: Callable[[], None] | None = None) -> None:
        self.config = config or FlightCtrlEmulatorConfig()
        self._vehicle = vehicle
        #: called (under ``lock``) once each iteration's output is written: work the vehicle
        #: deferred until the reply is on its way (the backend's MoCap captures in lockstep)
        self._after_output = after_output
        self._lock: contextlib.AbstractContextManager[object] = (
            lock if lock is not None else contextlib.nullcontext())
        self._pty = PtyEndpoint(link_path)
        self._rng = random.Random(self.config.faults.seed)
        # the counters of EmulatorStats: one writer (the emulator thread, or feed()'s caller
        # while it does not run) adds to a plain dict, which stats() copies in one step (the
        # GIL); a lock and an attribute lookup per count cost ~4 us per lockstep step
        self._counts = dict.fromkeys((f.name for f in dataclasses.fields(EmulatorStats)), 0)
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._closed = False
        self.sent_imu: deque[SentImu] = deque(maxlen=1_000_000)
        #: fault hook: (sample index, simulated time s) -> True to lose that ``I`` on the wire
        self.imu_wire_fault: Callable[[int, float], bool] | None = None
        # board state (owned by the emulator thread once started)
        self._tk3 = framing_tk3.Tk3Parser()
        self._stock = framing_stock.StockParser()
        self._motors = [_Motor() for _ in range(self.config.n_motors)]
        self._periods_ns: dict[str, int] = {}
        self._due_ns: dict[str, int] = {}
        self._seq: dict[str, int] = {"I": 0, "M": 0, "B": 0, "C": 0}
        self._imu_total = 0
        self._last_w_ns = 0
        self._last_w_wall = time.monotonic()
        self._w_seen = False  # lockstep: no `w` yet (the ground station is still starting)
        self._freerun = self.config.clock == "realtime"
        self._sim_ns = 0
        self._start_ns = 0
        self._wall0 = 0.0
        self._sim0_ns = 0
        self._tx_queue: deque[tuple[float, bytes]] = deque()
        self._out = bytearray()  # frames sent this iteration, not yet written
        # the config's times in ns, once (the step reads them several times per `w`)
        self._motor_start_ns = round(self.config.motor_start_s * _NS)
        self._watchdog_ns = round(self.config.watchdog_s * _NS)
        self._tx_busy_until = 0.0
        self._rotor_cmd: tuple[float, ...] = ()

    # ---------------------------------------------------------------- public API

    @property
    def path(self) -> str:
        return self._pty.path

    def start(self) -> EmulatedFlightCtrl:
        if self._thread is not None:
            raise RuntimeError("emulator already started")
        with self._lock:
            self._sim_ns = round(self._vehicle.now_s() * _NS)
        self._start_ns = self._sim_ns
        self._anchor()
        self._last_w_ns = self._sim_ns
        self._last_w_wall = time.monotonic()
        self._apply_rotors()
        self._thread = threading.Thread(target=self._run, name="emulated-flightctrl",
                                        daemon=True)
        self._thread.start()
        log.info("emulated Flight-Ctrl (%s, %s clock) on %s", self.config.firmware,
                 self.config.clock, self.path)
        return self

    def stop(self) -> None:
        """Stop the thread and close the pty (idempotent). A board still streaming or with a
        motor on at that point is reported (a warning): its client did not leave it as found
        (bytes the client sent before it let go are handled first)."""
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=5.0)
        if not self._closed and (self._thread is None or not self._thread.is_alive()):
            with contextlib.suppress(OSError):
                while self._pty.wait_readable(0.0):
                    data = self._pty.read(4096)
                    if not data:
                        break
                    self._handle_input(data)
            if self.streams_on or self.motors_on:
                on = sorted(self._periods_ns) + (["motors"] if self.motors_on else [])
                log.warning("emulated Flight-Ctrl: closed with %s on: the client did not "
                            "leave the board as found", ", ".join(on))
        self._pty.close()
        self._closed = True

    def disconnect(self) -> None:
        """Emulate a pulled cable: the pty disappears under the client."""
        self.stop()

    def stats(self) -> EmulatorStats:
        parsers = self._stock.stats.frame_errors + self._tk3.stats.frame_errors
        counts = self._counts.copy()
        counts["frame_errors_received"] = parsers
        return EmulatorStats(**counts)

    def feed(self, data: bytes) -> None:
        """Handle bytes as if they had come in on the pty (same thread rules: call it only
        while the emulator thread is not running). Never raises for any content."""
        self._handle_input(data)
        self._flush_out()

    def stream_periods_us(self) -> dict[str, int]:
        """The active stream periods by message letter (``I M B C`` tk3, ``D 3D`` stock), µs."""
        return {k: v // 1000 for k, v in self._periods_ns.items()}

    def sim_time_s(self) -> float:
        return self._sim_ns / _NS

    def commanded_rotor_speeds_hz(self) -> tuple[float, ...]:
        """What the emulated BL-Ctrls last told the vehicle's rotors (Hz; 0 = stopped)."""
        return self._rotor_cmd

    @property
    def streams_on(self) -> bool:
        """True while any stream is on: what a client that leaves cleanly must switch off."""
        return bool(self._periods_ns)

    @property
    def motors_on(self) -> bool:
        """True while any motor is starting or spinning (not stopped by ``x`` or the
        watchdog)."""
        return any(m.state != _MotorState.OFF for m in list(self._motors))

    def __enter__(self) -> EmulatedFlightCtrl:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # ---------------------------------------------------------------- thread

    def _run(self) -> None:
        try:
            while not self._stop.is_set():
                self._iterate()
        except Exception:  # the emulator must not die silently
            log.exception("emulated Flight-Ctrl crashed")
            raise

    def _iterate(self) -> None:
        now = time.monotonic()
        timeout = self._next_wakeup(now) - now
        if self._pty.wait_readable(min(max(timeout, 0.0), 0.05)):
            data = self._pty.read(4096)
            if data:
                if self._freerun:  # commands take effect at the present simulated time
                    self._advance_to(self._sim0_ns + round((time.monotonic() - self._wall0) * _NS))
                self._handle_input(data)
        now = time.monotonic()
        if not self._freerun and now - self._last_w_wall > self._grace_s():
            self._freerun = True
            self._anchor()
            self._count("freerun_entries")
        if self._freerun:
            self._advance_to(self._sim0_ns + round((time.monotonic() - self._wall0) * _NS))
        self._flush_out()
        self._flush_tx(time.monotonic())
        cut = self.config.faults.disconnect_after_s
        if cut is not None and self._sim_ns - self._start_ns >= round(cut * _NS):
            log.warning("emulated Flight-Ctrl: cable pulled (disconnect_after_s = %s)", cut)
            self._stop.set()
            self._pty.close()

    def _anchor(self) -> None:
        self._wall0 = time.monotonic()
        self._sim0_ns = self._sim_ns

    def _next_wakeup(self, now: float) -> float:
        wake = now + 0.05
        if self._tx_queue:
            wake = min(wake, self._tx_queue[0][0])
        if self._freerun:
            event = self._next_event_ns()
            if event is not None:
                wake = min(wake, self._wall0 + (event - self._sim0_ns) / _NS)
        else:
            wake = min(wake, self._last_w_wall + self._grace_s())
        return wake

    def _grace_s(self) -> float:
        """Lockstep: how long without `w` before free-running. Before the first `w` it is
        long, so that a ground station that takes a few seconds to start its other devices
        (on a loaded host) still finds the vehicle where the seed put it: a repeatable run."""
        if self._w_seen:
            return self.config.lockstep_grace_s
        return max(self.config.lockstep_grace_s, self.config.lockstep_first_w_grace_s)

    # ---------------------------------------------------------------- input

    def _handle_input(self, data: bytes) -> None:
        if self.config.firmware == "stock":
            for frame in self._stock.feed(data):
                self._count("frames_received")
                self._guarded(self._handle_stock, frame)
            return
        for raw in self._tk3.feed(data):
            self._count("frames_received")
            try:
                msg = mkm.decode_host_message(raw)
            except mkm.MalformedMessageError:
                self._count("malformed_received")
                continue
            self._guarded(self._handle_tk3, msg)

    def _guarded(self, handler: Callable[[_T], None], item: _T) -> None:
        """Run one input handler; a failure is logged and counted, the board keeps running
        (a real Flight-Ctrl does not reboot on a strange frame)."""
        try:
            handler(item)
        except Exception:
            self._count("input_errors")
            log.exception("emulated Flight-Ctrl: input %r failed", item)

    def _handle_tk3(self, msg: mkm.HostMessage) -> None:
        if isinstance(msg, mkm.SpinRates):
            self._on_spin_rates(msg)
        elif isinstance(msg, mkm.Identify):
            self._send_tk3(mkm.IdentityMessage(self.config.firmware_id))
        elif isinstance(msg, mkm.SetStreamPeriod):
            key = {mkm.Stream.IMU: "I", mkm.Stream.MOTOR: "M", mkm.Stream.BATTERY: "B",
                   mkm.Stream.MAG: "C"}[msg.stream]
            self._set_period(key, self._supported_period_us(msg.period_us, key) * 1000)
            if key == "I" and msg.period_us and not self._freerun:
                self._emit_due(self._sim_ns)  # lockstep: the first sample starts the exchange
        elif isinstance(msg, mkm.StartMotors):
            for i in self._motor_indices(msg.motor_id):
                m = self._motors[i]
                if m.state == _MotorState.OFF:
                    m.state, m.emergency, m.start_ns = _MotorState.STARTING, False, self._sim_ns
                    m.cmd_half_period = mkm.HALF_PERIOD_SLOWEST
            self._last_w_ns = self._sim_ns  # the watchdog starts with the start command
            self._apply_rotors()
        elif isinstance(msg, mkm.StopMotors):
            for i in self._motor_indices(msg.motor_id):
                self._motors[i].state = _MotorState.OFF
            self._apply_rotors()
        elif isinstance(msg, mkm.Throttles):
            pass  # open-loop throttle is not used on the FAST-Hex; accepted and ignored
        elif isinstance(msg, mkm.Beep):
            pass

    def _supported_period_us(self, period_us: int, key: str) -> int:
        """The period the board runs for a requested one (0 = off), clamped to 500 µs .. 1 s
        (2 ms .. 1 s for the motor stream, one frame per motor each period)."""
        if period_us == 0:
            return 0
        shortest = mkm.MIN_MOTOR_PERIOD_US if key == "M" else mkm.MIN_STREAM_PERIOD_US
        clamped = max(shortest, min(mkm.MAX_STREAM_PERIOD_US, period_us))
        if clamped != period_us:
            self._count("periods_clamped")
        return clamped

    def _motor_indices(self, motor_id: int | None) -> range:
        if motor_id is None:
            return range(len(self._motors))
        if 1 <= motor_id <= len(self._motors):
            return range(motor_id - 1, motor_id)
        return range(0)

    def _on_spin_rates(self, msg: mkm.SpinRates) -> None:
        self._count("spin_commands")
        if len(msg.half_periods_us) == len(self._motors):
            for m, p in zip(self._motors, msg.half_periods_us, strict=True):
                if 0 < abs(p) < _FASTEST_HALF_PERIOD_US:
                    # Faster than a BL-Ctrl can spin: it runs at its top speed.
                    p = _FASTEST_HALF_PERIOD_US if p > 0 else -_FASTEST_HALF_PERIOD_US
                    self._count("spin_rates_clamped")
                m.cmd_half_period = p if p != 0 else mkm.HALF_PERIOD_SLOWEST
            self._last_w_ns = self._sim_ns
            self._apply_rotors()
        else:
            self._count("malformed_received")
        self._last_w_wall = time.monotonic()
        self._w_seen = True
        if self.config.clock == "lockstep":
            if self._freerun:
                self._freerun = False
            period = self._periods_ns.get("I") or round(
                self.config.lockstep_default_period_s * _NS)
            self._advance_to(self._sim_ns + period)
            self._count("lockstep_steps")

    # ---------------------------------------------------------------- time and events

    def _set_period(self, key: str, period_ns: int) -> None:
        if period_ns <= 0:
            self._periods_ns.pop(key, None)
            self._due_ns.pop(key, None)
        else:
            # the board's clock: a period it counts lasts 1 / (1 + error) of it in true time
            self._periods_ns[key] = round(period_ns / (1.0 + self.config.board_clock_error_ppm
                                                       * 1e-6))
            self._due_ns[key] = self._sim_ns

    def _next_event_ns(self) -> int | None:
        """The next stream sample, motor start-up end or watchdog trip (simulated ns)."""
        nxt = min(self._due_ns.values()) if self._due_ns else None
        running = False
        for m in self._motors:
            state = m.state
            if state is _MotorState.OFF:
                continue
            running = True
            if state is _MotorState.STARTING:
                ev = m.start_ns + self._motor_start_ns
                nxt = ev if nxt is None or ev < nxt else nxt
        if running:
            ev = self._last_w_ns + self._watchdog_ns + 1
            nxt = ev if nxt is None or ev < nxt else nxt
        return nxt

    def _any_running(self) -> bool:
        return any(m.state is not _MotorState.OFF for m in self._motors)

    def _advance_to(self, target_ns: int) -> None:
        """Step the vehicle to ``target_ns``, handling every event on the way in time order."""
        while True:
            event = self._next_event_ns()
            stop = target_ns if event is None else max(self._sim_ns, min(event, target_ns))
            while self._sim_ns < stop:
                dt = min(stop - self._sim_ns, _MAX_STEP_NS)
                with self._lock:
                    self._vehicle.advance(dt / _NS)
                self._sim_ns += dt
            self._update_motors()
            self._emit_due(self._sim_ns)
            if self._sim_ns >= target_ns:
                return

    def _update_motors(self) -> None:
        changed = False
        t = self._sim_ns
        start_ns = self._motor_start_ns
        for m in self._motors:
            if m.state is _MotorState.STARTING and t >= m.start_ns + start_ns:
                m.state = _MotorState.SPINNING
                changed = True
        if t > self._last_w_ns + self._watchdog_ns and self._any_running():
            # tk3: the BL firmware stops and flags emergency. Stock: the engine-test set-points
            # simply fall back to 0 when not renewed (PC_MotortestActive runs out).
            emergency = self.config.firmware == "tk3"
            for m in self._motors:
                if m.state != _MotorState.OFF:
                    m.state, m.emergency = _MotorState.OFF, emergency
            self._count("watchdog_trips")
            log.warning("emulated Flight-Ctrl: no spin-rate command for %.3f s: motors stopped",
                        self.config.watchdog_s)
            changed = True
        if changed:
            self._apply_rotors()

    def _apply_rotors(self) -> None:
        speeds: list[float] = []
        for m in self._motors:
            if m.state == _MotorState.OFF:
                speeds.append(0.0)
            elif m.state == _MotorState.STARTING:
                speeds.append(mkm.MIN_SPIN_HZ)
            else:
                speeds.append(abs(mkm.half_period_to_spin_hz(m.cmd_half_period)))
        cmd = tuple(speeds)
        if cmd != self._rotor_cmd:
            self._rotor_cmd = cmd
            with self._lock:
                self._vehicle.command_rotor_speeds_hz(cmd)

    def _emit_due(self, t_ns: int) -> None:
        for key in ("I", "M", "B", "C", "D", "3D"):
            due = self._due_ns.get(key)
            if due is None or due > t_ns:
                continue
            period = self._periods_ns[key]
            self._emit(key)
            due += period
            if due <= t_ns:  # fell behind by more than one period: skip, do not burst
                skipped = (t_ns - due) // period + 1
                due += skipped * period
                self._count("stream_slips", int(skipped))
            self._due_ns[key] = due

    def _emit(self, key: str) -> None:
        if key == "I":
            self._emit_imu()
        elif key == "M":
            self._emit_motors()
        elif key == "B":
            with self._lock:
                volts = self._vehicle.battery_voltage_v()
            self._send_tk3(mkm.BatteryMessage(self._next_seq("B"), volts))
        elif key == "C":
            self._send_tk3(mkm.MagMessage(self._next_seq("C"), self._mag_board_t()))
        elif key == "D":
            self._emit_debug()
        elif key == "3D":
            self._emit_data3d()

    def _next_seq(self, key: str) -> int:
        seq = self._seq[key]
        self._seq[key] = (seq + 1) & 0xFF
        return seq

    def _emit_imu(self) -> None:
        with self._lock:
            reading = self._vehicle.read_imu()
        accel, gyro = self.config.imu_axes.imu_to_board(reading.accel_m_s2, reading.gyro_rad_s)
        encoded = mkm.ImuMessage(self._imu_total & 0xFF, accel, gyro).encode()
        total, t_ns = self._imu_total, self._sim_ns
        record = None
        if self.config.record_truth:
            # what the board really sends: quantised
            msg = mkm.ImuMessage.decode(encoded[1:])

            def record(altered: bool, wire: bytes) -> None:
                self.sent_imu.append(SentImu(total, t_ns, msg, altered, wire))

        frame = framing_tk3.encode_frame(encoded)
        if self.imu_wire_fault is not None and self.imu_wire_fault(total, t_ns / _NS):
            frame = frame[:-1] + b"!"  # aborted on the wire: the host sees a framing error
        self._send(frame, record)
        self._imu_total += 1
        self._count("imu_sent")

    def _emit_motors(self) -> None:
        with self._lock:
            speeds = self._vehicle.rotor_speeds_hz()
            currents = self._vehicle.motor_currents_a()
        seq = self._next_seq("M")
        for i, m in enumerate(self._motors):
            spinning = m.state == _MotorState.SPINNING
            speed = speeds[i] if i < len(speeds) else 0.0
            direction = -1.0 if m.cmd_half_period < 0 else 1.0
            period = mkm.spin_hz_to_half_period(direction * speed) if speed > 0.0 else 0
            throttle = round(min(1.0, speed / _MAX_SPEED_HZ_FOR_THROTTLE) * 1023)
            current = currents[i] if i < len(currents) else 0.0
            self._send(framing_tk3.encode_frame(mkm.encode_motor_state(
                seq, i + 1, m.emergency, spinning, m.state == _MotorState.STARTING, period,
                throttle if m.state != _MotorState.OFF else 0, current)))

    def _mag_board_t(self) -> tuple[float, float, float]:
        with self._lock:
            pose = self._vehicle.true_pose()
        w, x, y, z = pose.q_wb
        # body = R_wb^T world, with R_wb from the body -> world quaternion
        ex, ey, ez = _EARTH_FIELD_W_T
        r = (
            (1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)),
            (2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)),
            (2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)),
        )
        body = tuple(r[0][i] * ex + r[1][i] * ey + r[2][i] * ez for i in range(3))
        return self.config.imu_axes.to_board((body[0], body[1], body[2]))

    # ---------------------------------------------------------------- stock firmware

    def _handle_stock(self, frame: framing_stock.StockFrame) -> None:
        if frame.address not in (framing_stock.Address.ANY, framing_stock.Address.FLIGHT_CTRL):
            return
        try:
            msg = mkm.decode_stock_message(frame.cmd, frame.data)
        except mkm.MalformedMessageError:
            self._count("malformed_received")
            return
        if isinstance(msg, mkm.VersionRequest):
            major, minor, patch = self.config.stock_version
            self._send_stock(mkm.VersionInfo(major, minor, 11, 0xA5, patch, (0, 0), 25, 255, 0))
        elif isinstance(msg, mkm.DebugRequest):
            self._set_period("D", msg.interval_ms * 1_000_000)  # u8 x 10 ms: 10 ms .. 2.55 s
        elif isinstance(msg, mkm.Data3DRequest):
            self._set_period("3D", msg.interval_ms * 1_000_000)
        elif isinstance(msg, mkm.EngineTest):
            # Raw 8-bit set-points; the emulated BLs map 0..255 linearly onto 0..100 Hz.
            for m, sp in zip(self._motors, msg.setpoints, strict=False):
                if sp:
                    m.state = _MotorState.SPINNING
                    m.cmd_half_period = mkm.spin_hz_to_half_period(sp / 255 * 100.0)
                else:
                    m.state = _MotorState.OFF
            self._last_w_ns = self._sim_ns
            self._apply_rotors()
            self._send_stock(mkm.EngineTestAck())
        elif isinstance(msg, mkm.ExternControl):
            self._send_stock(mkm.ExternControlAck(msg.frame))

    def _emit_debug(self) -> None:
        with self._lock:
            volts = self._vehicle.battery_voltage_v()
            current = sum(self._vehicle.motor_currents_a())
            speeds = self._vehicle.rotor_speeds_hz()
        analog = [0] * 32
        analog[9] = round(volts * 10)
        analog[22] = round(current * 10)
        for i in range(4):
            analog[12 + i] = min(255, round(speeds[i] / 100.0 * 255)) if i < len(speeds) else 0
        self._send_stock(mkm.DebugOut((0, 0), tuple(analog)))

    def _emit_data3d(self) -> None:
        with self._lock:
            pose = self._vehicle.true_pose()
        w, x, y, z = pose.q_wb
        roll = math.degrees(math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y)))
        pitch = math.degrees(math.asin(max(-1.0, min(1.0, 2 * (w * y - z * x)))))
        yaw = math.degrees(math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))) % 360.0
        self._send_stock(mkm.Data3D((pitch, roll, yaw), (0, 0, 0), 512))

    # ---------------------------------------------------------------- output

    def _send_tk3(self, msg: mkm.BoardMessage) -> None:
        self._send(framing_tk3.encode_frame(msg.encode()))

    def _send_stock(self, msg: mkm.StockMessage) -> None:
        self._send(framing_stock.encode_frame(framing_stock.Address.FLIGHT_CTRL,
                                              msg.CMD, msg.payload()))

    def _send(self, frame: bytes,
              record: Callable[[bool, bytes], None] | None = None) -> None:
        """Put one frame through the faulty wire; ``record(altered, wire)`` runs before the
        bytes can reach the client."""
        faults = self.config.faults
        altered = False
        if faults.corrupt_prob or faults.drop_prob:
            frame, altered = self._damage(frame)
        self._count("frames_sent")
        if altered:
            self._count("frames_altered")
        if faults.baud is None:
            if record is not None:
                record(altered, frame)
            self._out += frame  # written at the end of the iteration (_flush_out)
            return
        now = time.monotonic()
        start = max(now, self._tx_busy_until)
        done = start + len(frame) * 10.0 / faults.baud
        if done - now > _TX_BACKLOG_S:
            self._count("tx_overruns")
            if record is not None:
                record(True, b"")
            return
        if record is not None:
            record(altered, frame)
        self._tx_busy_until = done
        self._tx_queue.append((done, frame))

    def _damage(self, frame: bytes) -> tuple[bytes, bool]:
        faults, rng = self.config.faults, self._rng
        out = bytearray()
        altered = False
        for byte in frame:
            r = rng.random()
            if r < faults.drop_prob:
                self._count("bytes_dropped")
                altered = True
                continue
            if r < faults.drop_prob + faults.corrupt_prob:
                byte = (byte + rng.randrange(1, 256)) & 0xFF
                self._count("bytes_corrupted")
                altered = True
            out.append(byte)
        return bytes(out), altered

    def _flush_out(self) -> None:
        """Write what this iteration sent, in one system call (a pty write costs ~6 us: a
        step that emits an IMU sample and six motor frames would pay seven); then the
        vehicle's deferred work (``after_output``)."""
        if self._out:
            data, self._out = bytes(self._out), bytearray()
            self._write(data)
        if self._after_output is not None:
            try:
                with self._lock:
                    self._after_output()
            except Exception:  # the board keeps running, as after a failed input
                log.exception("emulated Flight-Ctrl: the vehicle's deferred work failed")

    def _flush_tx(self, now: float) -> None:
        while self._tx_queue and self._tx_queue[0][0] <= now:
            self._write(self._tx_queue.popleft()[1])

    def _write(self, data: bytes) -> None:
        if self._stop.is_set():
            return
        with contextlib.suppress(OSError):
            self._pty.write(data)

    def _count(self, name: str, n: int = 1) -> None:
        self._counts[name] += n


def main(argv: list[str] | None = None) -> int:
    """Run one emulated Flight-Ctrl on a bench vehicle and print where to connect."""
    import argparse

    from sim_backend.vehicle import BenchVehicle

    parser = argparse.ArgumentParser(description=main.__doc__)
    parser.add_argument("--link", default=None, help="stable symlink to the pty slave")
    parser.add_argument("--firmware", choices=("tk3", "stock"), default="tk3")
    parser.add_argument("--clock", choices=("realtime", "lockstep"), default="realtime")
    parser.add_argument("--firmware-id", default="mkfl1.8")
    args = parser.parse_args(argv)
    config = FlightCtrlEmulatorConfig(firmware=args.firmware, clock=args.clock,
                                      firmware_id=args.firmware_id)
    emu = EmulatedFlightCtrl(BenchVehicle(), link_path=args.link, config=config).start()
    print(f"emulated Flight-Ctrl ({args.firmware}, {args.clock}): pty://{emu.path}", flush=True)
    try:
        while True:
            time.sleep(3600)  # the emulator runs on its own thread; wait for Ctrl-C
    except KeyboardInterrupt:
        pass
    finally:
        emu.stop()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Emulated Dynamixel MX-28T (Protocol 1.0 firmware) on a pseudo-terminal.

The servo speaks Protocol 1.0 (``FF FF ID LEN INST params CHK``, see
:mod:`drivers.dynamixel.protocol1`) on the master side of a :class:`PtyEndpoint`; any client,
the official ``dynamixel-sdk`` included, opens the slave path like a USB2Dynamixel. The control
table is :data:`drivers.dynamixel.control_table.MX28_P1` (74 bytes, EEPROM and RAM areas,
access rights and ranges).

Modelled:
- PING, READ, WRITE, REG_WRITE/ACTION, RESET, SYNC_WRITE and BULK_READ; Status Return Level,
  Return Delay Time, the broadcast ID; a bad checksum is answered with the Checksum bit;
- joint, wheel and multi-turn modes (from the angle limits), Multi Turn Offset, Resolution
  Divider, signed positions; writing Goal Position turns the torque on (as on the real servo);
- motion towards the goal at the Moving Speed, capped at the no-load speed (55 rpm), on the
  *vehicle's* clock: the servo's output shaft drives the simulated tilt through the worm
  (``tilt_rad = gear_ratio * servo_angle_rad``), so in lockstep the servo follows simulated time;
- error bits: voltage (supply outside the limits), angle limit, range, checksum, instruction,
  overload (load above Torque Limit) and overheating (first-order thermal model driven by the
  load); the Shutdown mask turns the torque off;
- faults: stop answering, garbled replies, late replies, forced error bits, unplugging and
  re-plugging the port, a power cycle (the multi-turn count is lost).

Emulator choices where the manual is silent: a write to a read-only register, out of its range
or to a locked EEPROM is ignored with the Range bit; a joint-mode goal outside CW..CCW is ignored
with the Angle bit; a READ past the table is padded with zeros (Range bit); a READ longer than
a status packet can carry (more than 248 bytes: LEN would pass 250) is answered with the Range
bit and no data. Any byte sequence is survived: what does not decode or cannot be applied is
counted (:meth:`EmulatedMX28.input_stats`), never fatal to the serving thread;
:meth:`EmulatedMX28.feed` hands bytes to the input side in process (fuzzing).

Vehicle calls are made under the optional shared ``lock`` (the vehicle is not thread-safe).
"""

from __future__ import annotations

import contextlib
import logging
import math
import termios
import threading
import time
from collections import deque
from dataclasses import dataclass
from enum import Enum
from pathlib import Path
from typing import Any

from drivers.dynamixel import protocol1 as p1
from drivers.dynamixel.control_table import (
    BROADCAST_ID,
    BY_ADDRESS,
    EEPROM_END,
    MAX_ID,
    MODEL_MX28_P1,
    MULTI_TURN_MAX_STEPS,
    MULTI_TURN_MIN_STEPS,
    MX28_P1,
    NO_LOAD_SPEED_RPM,
    RAD_PER_STEP,
    STEPS_PER_TURN,
    TABLE_SIZE,
    Access,
    ErrorBit,
    Instruction,
    Mode,
    Reg,
    Register,
    baud_from_register,
    encode_signed_magnitude_11,
    mode_from_limits,
    signed_magnitude_11,
)
from sim_backend.ptylink import PtyEndpoint
from sim_backend.vehicle import EmulatedVehicle

#: each register's (first byte, end, size, value mask, sign bit or 0), by address: the table
#: is read and written some 30 times per instruction, so the layout is worked out once here
_LAYOUT: dict[int, tuple[int, int, int, int, int]] = {
    a: (a, a + r.size, r.size, (1 << (8 * r.size)) - 1,
        (1 << (8 * r.size - 1)) if r.signed else 0)
    for a, r in BY_ADDRESS.items()}

log = logging.getLogger(__name__)

STEP_PERIOD_S = 0.002
"""How often the motion and thermal models are stepped while no bytes arrive (wall time)."""
IDLE_WAIT_S = 0.05
"""Lockstep (no stepping on the wall clock): the longest the serving thread sleeps while no
bytes arrive; it only looks for a stop then."""
SPEED_WINDOW_S = 0.05
"""Present Speed is the mean speed over this much vehicle time."""


_TERMIOS_BAUDS = {getattr(termios, f"B{bps}"): bps for bps in (
    9600, 19200, 38400, 57600, 115200, 230400, 460800, 500000, 576000, 921600, 1000000,
    1152000, 2000000, 2500000, 3000000, 3500000, 4000000) if hasattr(termios, f"B{bps}")}
BAUD_TOLERANCE = 0.03
"""A UART still decodes bytes whose bit rate is within ~3 % of its own."""


class Fault(Enum):
    """A reply fault to inject."""

    NONE = "none"
    SILENT = "silent"
    """Stop answering (the bytes are still read and the instructions applied)."""
    GARBLE = "garble"
    """Answer with a wrong checksum."""
    LATE = "late"
    """Answer ``late_s`` after the instruction, later than the client's timeout."""


@dataclass(frozen=True, slots=True)
class InputStats:
    """What the servo's input side dropped or refused."""

    instructions: int
    dropped_bytes: int
    """Bytes outside any packet (noise, a broken header)."""
    checksum_errors: int
    rejected: int
    """Instructions answered with an error bit (range, angle, instruction) and not applied."""
    input_errors: int
    """Instructions whose handling failed unexpectedly (logged); the servo kept serving."""

    @property
    def dropped_inputs(self) -> int:
        return self.checksum_errors + self.rejected + self.input_errors


@dataclass(frozen=True, slots=True)
class GoalRecord:
    """A Goal Position write as the servo saw it (vehicle time, raw signed steps)."""

    t_s: float
    goal_steps: int


class EmulatedMX28:
    """One MX-28T on a pty, its output shaft geared to ``vehicle``'s tilt.

    ``zero_offset_steps`` is the Present Position (multi-turn, divider 1, no offset) at tilt 0:
    where the mechanism was assembled. ``drive_clock=True`` makes this emulator advance the
    vehicle by the elapsed wall time (times ``time_scale``) when nothing else does (a bench).
    ``model_baud``: bytes sent at a bit rate (the client's termios speed on the pty) more than
    3 % off the Baud Rate register are dropped, as a UART would: a wrong baud means silence.
    """

    def __init__(
        self,
        vehicle: EmulatedVehicle,
        *,
        lock: threading.Lock | None = None,
        link_path: str | Path | None = None,
        dxl_id: int = 1,
        gear_ratio: float = 0.05,
        zero_offset_steps: int = 0,
        baud_register: int = 1,
        firmware_version: int = 41,
        model_number: int = MODEL_MX28_P1,
        supply_voltage_v: float | None = 12.0,
        ambient_temp_c: float = 25.0,
        thermal_time_constant_s: float = 120.0,
        full_load_temp_rise_c: float = 80.0,
        drive_clock: bool = False,
        time_scale: float = 1.0,
        model_baud: bool = True,
        step_on_wall_clock: bool = True,
    ) -> None:
        if not 0 <= dxl_id <= MAX_ID:
            raise ValueError(f"Dynamixel ID {dxl_id} outside 0..{MAX_ID}")
        self._vehicle = vehicle
        self._lock: Any = lock if lock is not None else contextlib.nullcontext()
        self._link_path = link_path
        self._k = gear_ratio
        self._zero_steps = zero_offset_steps
        self._model = model_number
        self._firmware = firmware_version
        self._factory_id = 1
        self._supply_v = supply_voltage_v
        self._ambient_c = ambient_temp_c
        self._tau_thermal_s = thermal_time_constant_s
        self._full_load_rise_c = full_load_temp_rise_c
        self._drive_clock = drive_clock
        self._time_scale = time_scale
        #: False in a lockstep backend: the motion is then integrated only when an instruction
        #: arrives (at a fixed simulated time), never at wall-clock instants
        self._step_on_wall_clock = step_on_wall_clock

        self._table = bytearray(TABLE_SIZE)
        self._factory_reset()
        self._write_reg(Reg.ID, dxl_id)
        self._write_reg(Reg.BAUD_RATE, baud_register)
        self._pending: tuple[int, bytes] | None = None  # REG_WRITE (address, data)

        # Physical state.
        self._turn_shift_steps = 0          # multi-turn count lost at power-up
        self._temp_c = ambient_temp_c
        self._external_load = 0.0           # fraction of the stall torque, signed
        self._forced_errors = ErrorBit.NONE
        with self._lock:
            self._last_vehicle_t = vehicle.now_s()
            self._last_real_steps = self._real_steps_locked()
        self._traj_steps = self._last_real_steps
        self._speed_steps_s = 0.0
        self._speed_window: deque[tuple[float, float]] = deque([(self._last_vehicle_t,
                                                                 self._last_real_steps)])
        self._last_wall = time.monotonic()

        # Faults and bookkeeping.
        self.fault = Fault.NONE
        self._fault_replies_left: int | None = None  # None: the fault lasts until changed
        self.late_s = 0.08
        self.replies_sent = 0
        self.instructions = 0
        self.rejected_instructions = 0
        self.input_errors = 0
        self.goal_log: deque[GoalRecord] = deque(maxlen=100_000)
        self.tilt_log: deque[tuple[float, float]] = deque(maxlen=200_000)

        self._model_baud = model_baud
        self.wrong_baud_bytes = 0
        self._parser = p1.Parser()
        self._replies: list[tuple[float, bytes]] = []  # (wall due time, bytes)
        self._endpoint: PtyEndpoint | None = PtyEndpoint(link_path)
        self._mutex = threading.RLock()
        self._stop = threading.Event()
        self._plugged = threading.Event()
        self._plugged.set()
        self._thread: threading.Thread | None = None

    # ------------------------------------------------------------------ client side facts
    @property
    def path(self) -> str:
        """The device path a client opens (the stable link if one was given)."""
        if self._endpoint is None:
            return str(self._link_path)
        return self._endpoint.path

    def register(self, reg: Reg) -> int:
        """Current value of a register (signed registers decoded)."""
        with self._mutex:
            return self._read_reg(reg)

    @property
    def temperature_c(self) -> float:
        return self._temp_c

    # ------------------------------------------------------------------ fault knobs
    def set_fault(self, fault: Fault, late_s: float | None = None,
                  replies: int | None = None) -> None:
        """Inject ``fault`` on every reply from now on, or on the next ``replies`` replies only
        (then the servo answers normally again)."""
        if replies is not None and replies < 1:
            raise ValueError(f"replies must be at least 1, got {replies}")
        with self._mutex:
            self.fault = fault
            self._fault_replies_left = replies
            if late_s is not None:
                self.late_s = late_s

    def force_error_bits(self, bits: ErrorBit) -> None:
        """OR ``bits`` into every status packet (until set back to ``ErrorBit.NONE``)."""
        with self._mutex:
            self._forced_errors = ErrorBit(bits)

    def set_external_load(self, fraction: float) -> None:
        """A torque on the output, as a signed fraction of the stall torque (1.0 = stall)."""
        with self._mutex:
            self._external_load = fraction

    def set_supply_voltage(self, volts: float | None) -> None:
        """Regulated supply voltage (V); ``None`` feeds the servo from the vehicle battery."""
        with self._mutex:
            self._supply_v = volts

    def set_temperature(self, temp_c: float) -> None:
        """Jump the thermal model to ``temp_c`` (it then relaxes with its time constant)."""
        with self._mutex:
            self._temp_c = temp_c

    def unplug(self) -> None:
        """Pull the USB cable: the pty (and its link) disappear; the servo keeps its state."""
        with self._mutex:
            self._plugged.clear()
            if self._endpoint is not None:
                self._endpoint.close()
                self._endpoint = None
            self._replies.clear()
            self._parser.reset()

    def replug(self) -> None:
        """Plug the cable back: a new pty, at the same link path if one was given."""
        with self._mutex:
            if self._endpoint is None:
                self._endpoint = PtyEndpoint(self._link_path)
            self._plugged.set()

    def power_cycle(self) -> None:
        """Power off and on: RAM back to defaults, torque off, multi-turn count lost."""
        with self._mutex:
            saved = bytes(self._table[:EEPROM_END])
            self._factory_reset()
            self._table[:EEPROM_END] = saved
            self._write_reg(Reg.TORQUE_LIMIT, self._read_reg(Reg.MAX_TORQUE))
            with self._lock:
                raw = self._real_steps_locked() + self._turn_shift_steps
            # After power-up the count restarts inside the first turn.
            self._turn_shift_steps -= STEPS_PER_TURN * math.floor(raw / STEPS_PER_TURN)
            with self._lock:
                self._traj_steps = self._real_steps_locked()
            self._pending = None

    # ------------------------------------------------------------------ thread
    def start(self) -> EmulatedMX28:
        if self._thread is None:
            self._thread = threading.Thread(target=self._serve, name="emulated-mx28",
                                            daemon=True)
            self._thread.start()
        return self

    def close(self) -> None:
        self._stop.set()
        self._plugged.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        with self._mutex:
            if self._endpoint is not None:
                self._endpoint.close()
                self._endpoint = None

    def __enter__(self) -> EmulatedMX28:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _serve(self) -> None:
        while not self._stop.is_set():
            endpoint = self._endpoint
            if endpoint is None:
                self._plugged.wait(STEP_PERIOD_S)
                with self._mutex:
                    self.step()
                continue
            # in lockstep nothing moves between instructions: no wake-ups on a timer (each one
            # would take the GIL from the Flight-Ctrl thread that is stepping the physics)
            timeout = STEP_PERIOD_S if self._step_on_wall_clock else IDLE_WAIT_S
            if self._replies:
                timeout = max(0.0, min(timeout, self._replies[0][0] - time.monotonic()))
            data = b""
            try:
                if endpoint.wait_readable(timeout):
                    data = endpoint.read()
            except (OSError, ValueError):
                data = b""  # endpoint closed under us (unplug)
            with self._mutex:
                if data or self._step_on_wall_clock:
                    self.step()
                if data and not self._baud_matches(endpoint):
                    self.wrong_baud_bytes += len(data)
                    data = b""
                if data:
                    self._feed_locked(data)
                self._send_due()

    def feed(self, data: bytes) -> list[bytes]:
        """Handle bytes as if they came in on the pty; returns the status packets the servo
        would send (faults applied, timing ignored). Never raises for any content."""
        with self._mutex:
            queued = len(self._replies)
            self._feed_locked(data)
            replies = [r for _, r in self._replies[queued:]]
            del self._replies[queued:]
            return replies

    def _feed_locked(self, data: bytes) -> None:
        for packet in self._parser.feed(data):
            try:
                reply = self.handle(packet)
            except Exception:
                # A servo does not die on a strange packet: count it and keep serving.
                self.input_errors += 1
                log.exception("emulated MX-28: instruction %r failed", packet)
                continue
            self._schedule(reply)

    def input_stats(self) -> InputStats:
        with self._mutex:
            return InputStats(self.instructions, self._parser.dropped_bytes,
                              self._parser.checksum_errors, self.rejected_instructions,
                              self.input_errors)

    def _baud_matches(self, endpoint: PtyEndpoint) -> bool:
        if not self._model_baud:
            return True
        try:
            # The slave's termios is shared by every fd on it: the client's settings show here.
            speed = termios.tcgetattr(endpoint.master_fd)[5]
        except termios.error:
            return True
        client = _TERMIOS_BAUDS.get(speed)
        if client is None:
            return True  # a rate we cannot name: do not judge
        servo = baud_from_register(self._read_reg(Reg.BAUD_RATE))
        return abs(client - servo) <= BAUD_TOLERANCE * servo

    def _schedule(self, reply: bytes | None) -> None:
        if reply is None:
            return
        fault = self.fault
        if fault is not Fault.NONE and self._fault_replies_left is not None:
            self._fault_replies_left -= 1
            if self._fault_replies_left <= 0:
                self.fault, self._fault_replies_left = Fault.NONE, None
        if fault is Fault.SILENT:
            return
        if fault is Fault.GARBLE:
            reply = reply[:-1] + bytes(((reply[-1] ^ 0x5A) & 0xFF,))
        delay_s = 2e-6 * self._read_reg(Reg.RETURN_DELAY_TIME)
        if fault is Fault.LATE:
            delay_s += self.late_s
        self._replies.append((time.monotonic() + delay_s, reply))

    def _send_due(self) -> None:
        now = time.monotonic()
        while self._replies and self._replies[0][0] <= now:
            _, reply = self._replies.pop(0)
            if self._endpoint is not None:
                with contextlib.suppress(OSError):
                    self._endpoint.write(reply)
                    self.replies_sent += 1

    # ------------------------------------------------------------------ table access
    def _factory_reset(self) -> None:
        self._table[:] = bytes(TABLE_SIZE)
        for r in MX28_P1:
            self._write_reg(r.reg, r.initial)
        self._write_reg(Reg.MODEL_NUMBER, self._model)
        self._write_reg(Reg.FIRMWARE_VERSION, self._firmware)

    def _read_reg(self, reg: Reg) -> int:
        start, end, _, mask, sign_bit = _LAYOUT[reg]
        raw = int.from_bytes(self._table[start:end], "little")
        if raw & sign_bit:
            raw -= mask + 1
        return raw

    def _write_reg(self, reg: Reg, value: int) -> None:
        start, end, size, mask, _ = _LAYOUT[reg]
        self._table[start:end] = (value & mask).to_bytes(size, "little")

    def mode(self) -> Mode:
        return mode_from_limits(self._read_reg(Reg.CW_ANGLE_LIMIT),
                                self._read_reg(Reg.CCW_ANGLE_LIMIT))

    # ------------------------------------------------------------------ physics
    def _real_steps_locked(self) -> float:
        """Encoder count (steps, since power-up) from the vehicle's tilt. Caller holds the lock."""
        servo_rad = self._vehicle.tilt_rad() / self._k
        return servo_rad / RAD_PER_STEP + self._zero_steps + self._turn_shift_steps

    def _present_steps(self, real_steps: float) -> int:
        if self.mode() is Mode.MULTI_TURN:
            divider = max(1, self._read_reg(Reg.RESOLUTION_DIVIDER))
            value = round(real_steps / divider) + self._read_reg(Reg.MULTI_TURN_OFFSET)
            return max(MULTI_TURN_MIN_STEPS, min(MULTI_TURN_MAX_STEPS, value))
        return round(real_steps) % STEPS_PER_TURN

    def _goal_real_steps(self, real_steps: float) -> float:
        goal = self._read_reg(Reg.GOAL_POSITION)
        if self.mode() is Mode.MULTI_TURN:
            divider = max(1, self._read_reg(Reg.RESOLUTION_DIVIDER))
            return float((goal - self._read_reg(Reg.MULTI_TURN_OFFSET)) * divider)
        # Joint mode: an absolute angle inside the present turn (it cannot wrap).
        base = STEPS_PER_TURN * math.floor(round(real_steps) / STEPS_PER_TURN)
        return float(base + (goal & 0x0FFF))

    def _max_speed_steps_s(self) -> float:
        top = NO_LOAD_SPEED_RPM * STEPS_PER_TURN / 60.0
        speed = self._read_reg(Reg.MOVING_SPEED) & 0x3FF
        if speed == 0:
            return top
        return min(top, speed * 0.114 * STEPS_PER_TURN / 60.0)

    def step(self) -> None:
        """Advance motion, load and temperature to the vehicle's present time.

        The serving thread calls this on every instruction, and every ``STEP_PERIOD_S`` when
        it steps on the wall clock (realtime; in lockstep nothing moves between instructions,
        the physics' own rate-limited servo follows the last goal). Call it *without* holding
        the vehicle lock: it takes that lock itself (after its own)."""
        with self._mutex:
            self._step()

    def _step(self) -> None:
        if self._drive_clock:
            wall = time.monotonic()
            dt_wall = wall - self._last_wall
            self._last_wall = wall
            if dt_wall > 0.0:
                with self._lock:
                    self._vehicle.advance(min(dt_wall, 0.1) * self._time_scale)
        with self._lock:
            t_s = self._vehicle.now_s()
            real = self._real_steps_locked()
            tilt = self._vehicle.tilt_rad()
        dt = t_s - self._last_vehicle_t
        if dt <= 0.0:
            self._refresh_present(real)
            return
        # Speed over a short window, as the servo's own estimate does (one step of the physics
        # can be a few microseconds long, and the vehicle's tilt moves in small bursts).
        self._speed_window.append((t_s, real))
        while len(self._speed_window) > 2 and t_s - self._speed_window[1][0] >= SPEED_WINDOW_S:
            self._speed_window.popleft()
        t0, r0 = self._speed_window[0]
        self._speed_steps_s = (real - r0) / (t_s - t0) if t_s > t0 else 0.0
        self._last_vehicle_t = t_s
        self._last_real_steps = real
        self.tilt_log.append((t_s, tilt))

        torque_on = self._read_reg(Reg.TORQUE_ENABLE) == 1
        mode = self.mode()
        if not torque_on:
            self._traj_steps = real
        elif mode is Mode.WHEEL:
            speed = signed_magnitude_11(self._read_reg(Reg.MOVING_SPEED))
            top = NO_LOAD_SPEED_RPM / 0.114
            speed_units = max(-top, min(top, speed))  # bit 10 = CW = decreasing position
            self._traj_steps += speed_units * 0.114 * STEPS_PER_TURN / 60.0 * dt
        else:
            goal = self._goal_real_steps(real)
            max_step = self._max_speed_steps_s() * dt
            self._traj_steps += max(-max_step, min(max_step, goal - self._traj_steps))
        if torque_on:
            tilt_cmd = ((self._traj_steps - self._zero_steps - self._turn_shift_steps)
                        * RAD_PER_STEP * self._k)
            with self._lock:
                self._vehicle.command_tilt_rad(tilt_cmd)

        # Thermal model: relaxes towards ambient + rise * load^2.
        load = abs(self._load_fraction())
        target = self._ambient_c + self._full_load_rise_c * load * load
        self._temp_c += (target - self._temp_c) * (1.0 - math.exp(-dt / self._tau_thermal_s))

        conditions = self._condition_errors()
        if conditions & ErrorBit(self._read_reg(Reg.SHUTDOWN)):
            self._write_reg(Reg.TORQUE_ENABLE, 0)
        self._refresh_present(real)

    def _load_fraction(self) -> float:
        if self._read_reg(Reg.TORQUE_ENABLE) != 1:
            return 0.0
        # The friction of the worm while moving, plus whatever the test applies.
        moving = 0.05 * math.copysign(1.0, self._speed_steps_s) if abs(
            self._speed_steps_s) > 1.0 else 0.0
        return self._external_load + moving

    def _supply_voltage(self) -> float:
        if self._supply_v is not None:
            return self._supply_v
        with self._lock:
            return self._vehicle.battery_voltage_v()

    def _condition_errors(self) -> ErrorBit:
        bits = ErrorBit.NONE
        volts = self._supply_voltage()
        if not (0.1 * self._read_reg(Reg.MIN_VOLTAGE_LIMIT) <= volts
                <= 0.1 * self._read_reg(Reg.MAX_VOLTAGE_LIMIT)):
            bits |= ErrorBit.VOLTAGE
        if self._temp_c > self._read_reg(Reg.TEMPERATURE_LIMIT):
            bits |= ErrorBit.OVERHEATING
        if abs(self._external_load) * 1023 > self._read_reg(Reg.TORQUE_LIMIT):
            bits |= ErrorBit.OVERLOAD
        return bits

    def _refresh_present(self, real: float) -> None:
        self._write_reg(Reg.PRESENT_POSITION, self._present_steps(real))
        speed_units = round(abs(self._speed_steps_s) * 60.0 / STEPS_PER_TURN / 0.114)
        # Present Speed: bit 10 set = CW (decreasing position).
        self._write_reg(Reg.PRESENT_SPEED, encode_signed_magnitude_11(
            -speed_units if self._speed_steps_s < 0 else speed_units))
        load_units = round(self._load_fraction() * 1000)
        self._write_reg(Reg.PRESENT_LOAD, encode_signed_magnitude_11(load_units))
        self._write_reg(Reg.PRESENT_VOLTAGE, max(0, min(255, round(self._supply_voltage() * 10))))
        self._write_reg(Reg.PRESENT_TEMPERATURE, max(0, min(255, round(self._temp_c))))
        self._write_reg(Reg.MOVING, int(abs(self._speed_steps_s) > 1.0
                                        or abs(self._traj_steps - real) > 1.0))
        self._write_reg(Reg.REGISTERED, int(self._pending is not None))
        self._write_reg(Reg.REALTIME_TICK, int(self._last_vehicle_t * 1000.0) & 0xFFFF)

    # ------------------------------------------------------------------ protocol
    def handle(self, packet: p1.Packet) -> bytes | None:
        """Apply one instruction packet; return the status packet to send, if any."""
        self.instructions += 1
        my_id = self._read_reg(Reg.ID)
        srl = self._read_reg(Reg.STATUS_RETURN_LEVEL)
        broadcast = packet.dxl_id == BROADCAST_ID
        addressed = packet.dxl_id == my_id
        if not packet.checksum_ok:
            return self._status(my_id, ErrorBit.CHECKSUM) if addressed else None
        code, params = packet.code, packet.params

        if code == Instruction.SYNC_WRITE:
            self._sync_write(my_id, params)
            return None
        if code == Instruction.BULK_READ:
            return self._bulk_read(my_id, params)
        if not (addressed or broadcast):
            return None

        error = ErrorBit.NONE
        data = b""
        if code == Instruction.PING:
            pass
        elif code == Instruction.READ and len(params) == 2:
            data, error = self._read_bytes(params[0], params[1])
        elif code == Instruction.WRITE and len(params) >= 2:
            error = self._write_bytes(params[0], params[1:])
        elif code == Instruction.REG_WRITE and len(params) >= 2:
            error = self._check_write(params[0], params[1:])
            if not error:
                self._pending = (params[0], bytes(params[1:]))
                self._write_reg(Reg.REGISTERED, 1)
        elif code == Instruction.ACTION:
            if self._pending is None:
                error = ErrorBit.INSTRUCTION
            else:
                address, payload = self._pending
                self._pending = None
                self._write_reg(Reg.REGISTERED, 0)
                error = self._write_bytes(address, payload)
        elif code == Instruction.RESET:
            reply = self._status(my_id, ErrorBit.NONE)
            self._factory_reset()
            self._pending = None
            return None if broadcast else reply
        else:
            error = ErrorBit.INSTRUCTION

        if broadcast:
            return None
        wants_reply = (code == Instruction.PING or srl >= 2
                       or (srl >= 1 and code == Instruction.READ))
        return self._status(my_id, error, data) if wants_reply else None

    def _status(self, dxl_id: int, error: ErrorBit, data: bytes = b"") -> bytes:
        if error & (ErrorBit.RANGE | ErrorBit.ANGLE_LIMIT | ErrorBit.INSTRUCTION):
            self.rejected_instructions += 1
        bits = (error | self._condition_errors() | self._forced_errors) & 0x7F
        return p1.encode_status(dxl_id, int(bits), data)

    def _read_bytes(self, address: int, length: int) -> tuple[bytes, ErrorBit]:
        if length + 2 > p1.MAX_LENGTH:
            # The reply would not fit one status packet: refused, as out of range.
            return b"", ErrorBit.RANGE
        # Always return `length` bytes: the SDK does not check the reply length.
        end = address + length
        data = bytes(self._table[address:min(end, TABLE_SIZE)])
        error = ErrorBit.NONE
        if end > TABLE_SIZE:
            data += bytes(length - len(data))
            error = ErrorBit.RANGE
        return data, error

    def _registers_touched(self, address: int, n: int) -> list[Register] | None:
        regs: list[Register] = []
        a = address
        while a < address + n:
            r = BY_ADDRESS.get(a)
            if r is None:
                # Not a register start: a byte inside a register or a reserved address.
                owner = next((x for x in MX28_P1 if x.address < a < x.address + x.size), None)
                if owner is None:
                    return None
                regs.append(owner)
                a = owner.address + owner.size
                continue
            regs.append(r)
            a += r.size
        return regs

    def _check_write(self, address: int, payload: bytes) -> ErrorBit:
        if address + len(payload) > TABLE_SIZE:
            return ErrorBit.RANGE
        regs = self._registers_touched(address, len(payload))
        if regs is None:
            return ErrorBit.RANGE
        scratch = bytearray(self._table)
        scratch[address : address + len(payload)] = payload
        locked = self._read_reg(Reg.LOCK) == 1
        for r in regs:
            if r.access is Access.R or (locked and r.eeprom):
                return ErrorBit.RANGE
            raw = int.from_bytes(scratch[r.address : r.address + r.size], "little")
            value = raw - (1 << 16) if r.signed and raw & 0x8000 else raw
            if r.reg == Reg.GOAL_POSITION:
                error = self._check_goal(value, scratch)
                if error:
                    return error
            elif not r.lo <= value <= r.hi:
                return ErrorBit.RANGE
        return ErrorBit.NONE

    def _check_goal(self, value: int, scratch: bytearray) -> ErrorBit:
        cw = int.from_bytes(scratch[6:8], "little")
        ccw = int.from_bytes(scratch[8:10], "little")
        mode = mode_from_limits(cw, ccw)
        if mode is Mode.MULTI_TURN:
            ok = MULTI_TURN_MIN_STEPS <= value <= MULTI_TURN_MAX_STEPS
            return ErrorBit.NONE if ok else ErrorBit.RANGE
        if mode is Mode.JOINT and not cw <= value <= ccw:
            return ErrorBit.ANGLE_LIMIT
        return ErrorBit.NONE if 0 <= value <= 4095 else ErrorBit.RANGE

    def _write_bytes(self, address: int, payload: bytes) -> ErrorBit:
        error = self._check_write(address, payload)
        if error:
            return error
        torque_before = self._read_reg(Reg.TORQUE_ENABLE)
        self._table[address : address + len(payload)] = payload
        touched = range(address, address + len(payload))
        if int(Reg.GOAL_POSITION) in touched or int(Reg.GOAL_POSITION) + 1 in touched:
            self._write_reg(Reg.TORQUE_ENABLE, 1)
            self.goal_log.append(GoalRecord(self._last_vehicle_t,
                                            self._read_reg(Reg.GOAL_POSITION)))
        if int(Reg.MAX_TORQUE) in touched:
            self._write_reg(Reg.TORQUE_LIMIT, self._read_reg(Reg.MAX_TORQUE))
        if torque_before == 0 and self._read_reg(Reg.TORQUE_ENABLE) == 1:
            with self._lock:
                self._traj_steps = self._real_steps_locked()
        return ErrorBit.NONE

    def _sync_write(self, my_id: int, params: bytes) -> None:
        if len(params) < 2:
            return
        address, size = params[0], params[1]
        body = params[2:]
        if size == 0:
            return
        for i in range(0, len(body) - size, size + 1):
            if body[i] == my_id:
                self._write_bytes(address, bytes(body[i + 1 : i + 1 + size]))

    def _bulk_read(self, my_id: int, params: bytes) -> bytes | None:
        for i in range(1, len(params) - 2, 3):
            length, dxl_id, address = params[i], params[i + 1], params[i + 2]
            if dxl_id == my_id:
                data, error = self._read_bytes(address, length)
                return self._status(my_id, error, data)
        return None


def serve_bench_servo(link_path: str, stop: Any, ready: Any, silent: Any = None,
                      time_scale: float = 1.0) -> None:
    """Process entry point: one emulated MX-28T geared to a :class:`BenchVehicle`, served until
    ``stop`` (a multiprocessing Event) is set. ``ready`` is set once ``link_path`` exists; while
    the optional ``silent`` Event is set the servo does not answer."""
    from sim_backend.vehicle import BenchVehicle

    vehicle = BenchVehicle(max_tilt_rate_rad_s=math.radians(100.0))
    servo = EmulatedMX28(vehicle, link_path=link_path, drive_clock=True, time_scale=time_scale)
    with servo:
        ready.set()
        while not stop.wait(0.02):
            quiet = silent is not None and silent.is_set()
            servo.set_fault(Fault.SILENT if quiet else Fault.NONE)

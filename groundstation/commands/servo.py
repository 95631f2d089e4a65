"""``fasthex servo status|home|move DEG``: bench work on the tilt servo (real or emulated).

The servo is named by ``--uri`` (``serial:///dev/ttyUSB1?baud=1000000&id=1``) or by a session
file (its servo; an emulated session starts the emulated vehicle for the duration of the
command).

- ``status`` only reads (PING and READ: no EEPROM or RAM write, the torque is left as it is): it
  identifies the servo and prints its measured state.
- ``home`` declares the present position to be tilt ``--at-deg`` (0 by default: the mechanism on
  its zero jig) and prints the zero offset to put in the configuration.
- ``move DEG`` commands a tilt within the vehicle's range ``[0, max_tilt_deg]`` (outside it: an
  error, exit 2) and waits until the servo reaches it (at the configured tilt-rate limit).

``home`` and ``move`` configure the servo as a flight does (multi-turn mode, Moving Speed from
the tilt-rate limit, torque on) and switch its torque off when they end, on every path: the
documented rest state (the worm drive is self-locking, so the tilt holds without torque).
"""

from __future__ import annotations

import argparse
import math
import tempfile
import time
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from drivers.dynamixel.device import ServoReading

NAME = "servo"
HELP = "tilt servo bench work: status (read only), home (zero calibration), move DEG"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("action", choices=("status", "home", "move"))
    parser.add_argument("deg", nargs="?", type=float, default=None,
                        help="move: the goal tilt in degrees, within the vehicle's range")
    parser.add_argument("--uri", default=None, help="servo URI (instead of a session)")
    parser.add_argument("--session", default="exp1-emulated",
                        help="session whose servo to use (default exp1-emulated)")
    parser.add_argument("--zero-steps", type=int, default=None,
                        help="zero offset (Present Position at tilt 0), e.g. from `servo home`")
    parser.add_argument("--at-deg", type=float, default=0.0, help="home: the present tilt")


def format_reading(uri: str, r: ServoReading, gear_ratio: float, zero_steps: int) -> list[str]:
    from drivers.dynamixel.device import steps_to_tilt

    ident = r.identity
    tilt_deg = math.degrees(steps_to_tilt(r.present_position_steps, gear_ratio, zero_steps))
    goal_deg = math.degrees(steps_to_tilt(r.goal_position_steps, gear_ratio, zero_steps))
    return [
        f"servo {uri}: model {ident.model_number} firmware {ident.firmware_version} id "
        f"{ident.dxl_id} mode {ident.mode.name.lower()}",
        f"tilt {tilt_deg:.2f} deg (goal {goal_deg:.2f}), servo {r.present_position_steps} "
        f"steps, load {100 * r.load_fraction:.0f} %, {r.voltage_v:.1f} V, "
        f"{r.temperature_c:.0f} C, torque {'on' if r.torque_enabled else 'off'}, "
        f"{'moving' if r.moving else 'still'}, "
        f"{'configured since power-up' if r.led_on else 'not configured since power-up'}",
    ]


def run(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from config import find_config
    from controller.missions import Mission
    from drivers.dynamixel.device import (
        ServoError,
        TiltServo,
        TiltServoConfig,
        error_names,
        read_servo,
    )
    from drivers.errors import DriverError
    from groundstation.cli import UserError
    from groundstation.configs import load_mission, load_vehicle
    from groundstation.session import EmulatorProcess, device_uris
    from groundstation.session_config import EmulatedBackend, load_session, resolve_reference

    path = find_config("sessions", args.session)
    cfg = load_session(path)
    params = load_vehicle(resolve_reference(path, cfg.vehicle))
    t = params.tilt
    if args.action == "move":
        if args.deg is None:
            raise UserError("servo move needs the goal tilt in degrees, e.g. "
                            "`fasthex servo move 20`")
        if not (math.isfinite(args.deg) and 0.0 <= args.deg <= t.max_tilt_deg):
            raise UserError(f"servo move {args.deg:g}: the tilt of {params.name} is within "
                            f"[0, {t.max_tilt_deg:g}] deg")
    emulator = None
    with tempfile.TemporaryDirectory(prefix="fasthex-servo-") as tmp:
        try:
            if args.uri:
                uri, zero = args.uri, args.zero_steps or 0
            else:
                if isinstance(cfg.backend, EmulatedBackend):
                    mission = Mission(load_mission(resolve_reference(path, cfg.mission)))
                    # a bench tool sends no `w`: the emulated board free-runs like a real one
                    emulator = EmulatorProcess(replace(cfg.backend, clock="realtime"), cfg.vehicle,
                                               mission.start_pos_w_m, Path(tmp),
                                               realtime_settings=False)
                uris = device_uris(cfg, emulator)
                uri, zero = uris.servo, uris.servo_zero_steps
                if args.zero_steps is not None:  # overrides the session's zero
                    zero = args.zero_steps
            if args.action == "status":
                try:
                    reading = read_servo(uri)
                except DriverError as exc:
                    raise UserError(str(exc)) from None
                print("\n".join(format_reading(uri, reading, t.worm_ratio, zero)))
                return 0
            servo = TiltServo(TiltServoConfig(uri=uri, gear_ratio=t.worm_ratio,
                                              zero_offset_steps=zero,
                                              max_tilt_deg=t.max_tilt_deg,
                                              max_tilt_rate_deg_s=t.max_rate_deg_s))
            with servo:  # stop() switches the torque off, on every path out
                try:
                    state = servo.wait_for(lambda s: s.ok, 5.0)
                except ServoError as exc:
                    raise UserError(f"servo at {uri} not ready: {exc}") from None
                ident = servo.probe()
                print(f"servo {uri}: model {ident.model_number} firmware "
                      f"{ident.firmware_version} id {ident.dxl_id} mode "
                      f"{ident.mode.name.lower()}")
                if args.action == "home":
                    offset = servo.home(math.radians(args.at_deg))
                    # the state below measured after the home, its tilt from the new zero
                    seen = servo.latest().seq
                    try:
                        servo.wait_for(lambda s: s.seq > seen, 2.0)
                    except ServoError as exc:
                        raise UserError(f"servo at {uri} silent after homing: {exc}") from None
                    was = "" if offset == zero else f"; was {zero}"
                    print(f"zero offset: {offset} steps (Present Position at tilt 0{was}); put "
                          "it in the session as backend.servo_zero_offset_steps")
                else:
                    goal = math.radians(args.deg)
                    servo.set_tilt(goal)
                    timeout = 5.0 + abs(goal - state.tilt_rad) / math.radians(t.max_rate_deg_s)
                    t0 = time.monotonic()
                    try:
                        state = servo.wait_for(
                            lambda s: abs(s.tilt_rad - goal) < math.radians(0.2)
                            and not s.moving, timeout)
                    except ServoError as exc:
                        raise UserError(f"tilt not reached: {exc}") from None
                    print(f"reached {math.degrees(state.tilt_rad):.2f} deg in "
                          f"{time.monotonic() - t0:.1f} s")
                state = servo.latest()
                print(f"tilt {math.degrees(state.tilt_rad):.2f} deg (goal "
                      f"{math.degrees(state.goal_tilt_rad):.2f}), servo "
                      f"{state.servo_position_steps} steps, load {100 * state.load_fraction:.0f} "
                      f"%, {state.voltage_v:.1f} V, {state.temperature_c:.0f} C, health "
                      f"{state.health.name}, errors {error_names(state.errors)}")
            print("torque off (the worm drive holds the tilt)")
        finally:
            if emulator is not None:
                emulator.close()
    return 0

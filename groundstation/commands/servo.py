"""``fasthex servo status|home|move DEG``: bench work on the tilt servo (real or emulated).

The servo is named by ``--uri`` (``serial:///dev/ttyUSB1?baud=1000000&id=1``) or by a session
file (its servo; an emulated session starts the emulated vehicle for the duration of the
command). ``status`` identifies the servo and prints its measured state; ``home`` declares the
present position to be tilt ``--at-deg`` (0 by default: the mechanism on its zero jig) and prints
the zero offset to put in the configuration; ``move DEG`` commands a tilt and waits until the
servo reaches it (at the configured tilt-rate limit).
"""

from __future__ import annotations

import argparse
import math
import tempfile
import time
from pathlib import Path

NAME = "servo"
HELP = "tilt servo bench work: status, home (zero calibration), move DEG"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("action", choices=("status", "home", "move"))
    parser.add_argument("deg", nargs="?", type=float, default=None,
                        help="move: the goal tilt in degrees")
    parser.add_argument("--uri", default=None, help="servo URI (instead of a session)")
    parser.add_argument("--session", default="exp1-emulated",
                        help="session whose servo to use (default exp1-emulated)")
    parser.add_argument("--zero-steps", type=int, default=None,
                        help="zero offset (Present Position at tilt 0) for --uri")
    parser.add_argument("--at-deg", type=float, default=0.0, help="home: the present tilt")


def run(args: argparse.Namespace) -> int:
    from config import find_config
    from controller.missions import Mission
    from drivers.dynamixel.device import ServoError, TiltServo, TiltServoConfig
    from groundstation.cli import UserError
    from groundstation.configs import load_mission, load_vehicle
    from groundstation.session import EmulatorProcess, device_uris
    from groundstation.session_config import EmulatedBackend, load_session, resolve_reference

    if args.action == "move" and args.deg is None:
        raise UserError("servo move needs the goal tilt in degrees, e.g. `fasthex servo move 20`")
    path = find_config("sessions", args.session)
    cfg = load_session(path)
    params = load_vehicle(resolve_reference(path, cfg.vehicle))
    emulator = None
    with tempfile.TemporaryDirectory(prefix="fasthex-servo-") as tmp:
        try:
            if args.uri:
                uri, zero = args.uri, args.zero_steps or 0
            else:
                if isinstance(cfg.backend, EmulatedBackend):
                    mission = Mission(load_mission(resolve_reference(path, cfg.mission)))
                    emulator = EmulatorProcess(cfg.backend, cfg.vehicle, mission.start_pos_w_m,
                                               Path(tmp))
                uris = device_uris(cfg, emulator)
                uri, zero = uris.servo, uris.servo_zero_steps
            t = params.tilt
            servo = TiltServo(TiltServoConfig(uri=uri, gear_ratio=t.worm_ratio,
                                              zero_offset_steps=zero,
                                              max_tilt_deg=t.max_tilt_deg,
                                              max_tilt_rate_deg_s=t.max_rate_deg_s))
            with servo:
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
                    print(f"zero offset: {offset} steps (Present Position at tilt 0); put it "
                          "in the servo configuration as zero_offset_steps")
                elif args.action == "move":
                    goal = math.radians(args.deg)
                    servo.set_tilt(goal)
                    clamped = min(max(goal, 0.0), t.max_tilt_rad)
                    timeout = 5.0 + abs(clamped - state.tilt_rad) / math.radians(
                        t.max_rate_deg_s)
                    t0 = time.monotonic()
                    try:
                        state = servo.wait_for(
                            lambda s: abs(s.tilt_rad - clamped) < math.radians(0.2)
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
                      f"{state.health.name}, errors {state.errors!r}")
        finally:
            if emulator is not None:
                emulator.close()
    return 0

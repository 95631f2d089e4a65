"""``fasthex probe [SESSION]``: identify the session's hardware (or emulated hardware) without
arming: Flight-Ctrl firmware, servo model and mode, MoCap bodies and frame rate.

It only asks: the servo is read (PING and READ), the Flight-Ctrl is identified and, when it
answered in tk3, left with its streams off and its motors stopped (what a crashed client may
have left on). A device that does not answer gets one line ``URI: NOT FOUND: why``.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

NAME = "probe"
HELP = "identify the Flight-Ctrl, the tilt servo and the MoCap stream of a session"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("session", nargs="?", default="exp1-emulated",
                        help="session name or YAML file (default exp1-emulated)")


def run(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from config import find_config
    from controller.missions import Mission
    from drivers.dynamixel.device import probe_servo
    from drivers.errors import DriverError
    from drivers.mikrokopter.device import probe
    from drivers.mocap.pose import MocapError
    from drivers.mocap.uri import open_pose_source
    from groundstation.configs import load_mission
    from groundstation.session import EmulatorProcess, device_uris
    from groundstation.session_config import EmulatedBackend, load_session, resolve_reference

    path = find_config("sessions", args.session)
    cfg = load_session(path)
    emulator = None
    ok = True
    with tempfile.TemporaryDirectory(prefix="fasthex-probe-") as tmp:
        try:
            if isinstance(cfg.backend, EmulatedBackend):
                mission = Mission(load_mission(resolve_reference(path, cfg.mission)))
                # a bench tool sends no `w`: the emulated board free-runs like a real one
                emulator = EmulatorProcess(replace(cfg.backend, clock="realtime"), cfg.vehicle,
                                           mission.start_pos_w_m, Path(tmp),
                                           realtime_settings=False)
            uris = device_uris(cfg, emulator)
            try:
                ident = probe(uris.flight_ctrl)
                verdict = "can fly" if ident.accepted else "CANNOT fly at 500 Hz"
                print(f"flight-ctrl  {uris.flight_ctrl}: {ident.protocol} firmware "
                      f"{ident.firmware_id} ({verdict})")
                ok &= ident.accepted
            except DriverError as exc:
                print(f"flight-ctrl  {uris.flight_ctrl}: NOT FOUND: {_reason(exc)}")
                ok = False
            try:
                s = probe_servo(uris.servo)
                model = "MX-28T (Protocol 1.0)" if s.is_mx28_p1 else f"model {s.model_number}"
                print(f"servo        {uris.servo}: {model}, firmware {s.firmware_version}, "
                      f"id {s.dxl_id}, mode {s.mode.name.lower()}, position "
                      f"{s.present_position_steps} steps")
                ok &= s.is_mx28_p1
            except DriverError as exc:
                print(f"servo        {uris.servo}: NOT FOUND: {_reason(exc)}")
                ok = False
            try:
                with open_pose_source(uris.mocap) as src:
                    src.wait_for_rate(5.0)
                    stats = src.stats()
                    bodies: dict[str, int] = getattr(src, "bodies", dict)()
                    print(f"mocap        {uris.mocap}: bodies {sorted(bodies) or '?'}, "
                          f"{stats.rate_hz:.0f} Hz, latency "
                          f"{1e3 * stats.latency_s:.1f} ms")
                    ok &= stats.rate_hz > 0
            except (MocapError, DriverError, OSError) as exc:
                print(f"mocap        {uris.mocap}: NOT FOUND: {_reason(exc)}")
                ok = False
        finally:
            if emulator is not None:
                emulator.close()
    return 0 if ok else 1


def _reason(exc: Exception) -> str:
    """The error without the device name the line already shows."""
    text = str(exc)
    for prefix in (getattr(exc, "uri", None), getattr(exc, "device", None)):
        if isinstance(prefix, str) and text.startswith(f"{prefix}: "):
            return text[len(prefix) + 2:]
    return text

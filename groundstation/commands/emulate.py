"""``fasthex emulate [SESSION]``: run only the emulated vehicle and say where its devices are.

Prints one line per device (``flight-ctrl``, ``servo``: a pty path; ``mocap``: a NatNet UDP
address, or with ``--mocap qtm`` a QTM RT TCP address), then runs until Ctrl-C. Any client
can connect: this ground station (``fasthex fly`` with a hardware session naming these paths),
``fasthex mocap watch``, Qualisys' SDK, the Dynamixel Wizard, a serial terminal.
"""

from __future__ import annotations

import argparse
import contextlib
import sys
import tempfile
from pathlib import Path

NAME = "emulate"
HELP = "run the emulated FAST-Hex and print its device addresses (until Ctrl-C)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("session", nargs="?", default="exp1-emulated",
                        help="emulated session name or YAML file (default exp1-emulated)")
    parser.add_argument("--clock", choices=("realtime", "lockstep"), default="realtime",
                        help="realtime (default: any client) or lockstep (steps per `w`)")
    parser.add_argument("--link-dir", default=str(Path(tempfile.gettempdir()) / "fasthex"),
                        help="directory for the stable device links (default: %(default)s)")
    parser.add_argument("--mocap", choices=("natnet", "qtm"), default=None,
                        help="emulated MoCap server: natnet (Motive) or qtm (Qualisys QTM RT) "
                        "(default: the session's, natnet unless it says otherwise)")


def run(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from config import find_config
    from controller.missions import Mission
    from groundstation.cli import UserError
    from groundstation.configs import load_mission
    from groundstation.session import EmulatorProcess, SessionError, device_uris
    from groundstation.session_config import EmulatedBackend, load_session, resolve_reference
    from groundstation.signals import StopSignals

    path = find_config("sessions", args.session)
    cfg = load_session(path)
    if not isinstance(cfg.backend, EmulatedBackend):
        raise UserError(f"{path}: not an emulated session (backend kind "
                        f"{cfg.backend.kind!r})")
    backend = replace(cfg.backend, clock=args.clock, mocap=args.mocap or cfg.backend.mocap)
    mission = Mission(load_mission(resolve_reference(path, cfg.mission)))
    link_dir = Path(args.link_dir)
    link_dir.mkdir(parents=True, exist_ok=True)
    try:
        emulator = EmulatorProcess(backend, cfg.vehicle, mission.start_pos_w_m, link_dir)
    except SessionError as exc:
        raise UserError(str(exc)) from None
    # SIGINT, SIGTERM, SIGHUP: stop the emulator in order (the handler only counts)
    signals = StopSignals().install()
    try:
        uris = device_uris(replace(cfg, backend=backend), emulator)
        print(f"flight-ctrl  pty  {emulator.devices['flight-ctrl']}  (tk3, {backend.clock})")
        print(f"servo        pty  {emulator.devices['servo']}  (MX-28T, Protocol 1.0, id 1, "
              "1 Mbaud)")
        if backend.mocap == "qtm":
            print(f"mocap        tcp  {emulator.devices['mocap']}  (QTM RT, little-endian; "
                  f"{uris.mocap})", flush=True)
        else:
            print(f"mocap        udp  {emulator.devices['mocap']}  (NatNet 4.1 command port; "
                  f"{uris.mocap})", flush=True)
        print("running; Ctrl-C to stop", flush=True)
        was_stopped = False
        while not signals.wait(0.5):
            if emulator.proc.poll() is not None:
                raise UserError(f"the emulated vehicle exited (code {emulator.proc.returncode})")
            stopped = _is_stopped(emulator.proc.pid)
            if stopped != was_stopped:
                print("the emulated vehicle is stopped (SIGSTOP): its devices do not answer "
                      "until it is continued (SIGCONT)" if stopped else
                      "the emulated vehicle runs again", file=sys.stderr, flush=True)
                was_stopped = stopped
    finally:
        signals.restore()
        emulator.close()
    return 0


def _is_stopped(pid: int) -> bool:
    """Linux: the process is stopped by a signal (state ``T`` in ``/proc/PID/stat``)."""
    with contextlib.suppress(OSError, IndexError):
        stat = Path(f"/proc/{pid}/stat").read_text()
        return stat.rsplit(")", 1)[1].split()[0] in ("T", "t")
    return False

#!/usr/bin/env python3
"""Run the HIL tests against the emulated vehicle: one command, non-zero on any failure.

Starts ``fasthex emulate`` (realtime clock, so the emulated board free-runs like a real one) in
its own process group, reads the device addresses it prints, runs ``pytest -m hil tests/hil``
with ``FASTHEX_HIL_FLIGHT_CTRL``, ``FASTHEX_HIL_SERVO`` and ``FASTHEX_HIL_MOCAP`` pointing at
them (``FASTHEX_HIL_PROPS_OFF=1``: the emulated vehicle has no propellers;
``FASTHEX_HIL_REQUIRE=1``: every HIL test must run, none may skip), then stops the emulator on
every path (Ctrl-C and SIGTERM to this script included) and removes its device links.

Usage: ``python tests/hil/run_against_emulator.py [SESSION] [-- PYTEST-ARGS...]``. Exit code:
pytest's, or 3 when the emulator did not come up.
"""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from types import FrameType

ROOT = Path(__file__).resolve().parents[2]
READY_TIMEOUT_S = 120.0
STOP_TIMEOUT_S = 15.0

_DEVICE = re.compile(r"^(flight-ctrl|servo|mocap)\s+(pty|udp)\s+(\S+)\s*(?:\((.*)\))?")


def _devices(proc: subprocess.Popen[str]) -> dict[str, str]:
    """Read the emulator's device lines until it says it is running."""
    assert proc.stdout is not None
    found: dict[str, str] = {}
    deadline = time.monotonic() + READY_TIMEOUT_S
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line:
            raise RuntimeError(f"fasthex emulate exited (code {proc.wait()}) before it was ready")
        sys.stdout.write(f"emulate: {line}")
        m = _DEVICE.match(line.strip())
        if m:
            name, _kind, address, note = m.groups()
            if name == "mocap":
                uri = re.search(r"(natnet://\S+?)\)?$", note or "")
                found[name] = uri.group(1) if uri else f"natnet://{address}?local=127.0.0.1"
            elif name == "servo":
                found[name] = f"serial://{address}?baud=1000000&id=1"
            else:
                found[name] = f"pty://{address}"
        if line.startswith("running"):
            missing = {"flight-ctrl", "servo", "mocap"} - set(found)
            if missing:
                raise RuntimeError(f"fasthex emulate printed no address for {sorted(missing)}")
            return found
    raise RuntimeError(f"fasthex emulate not ready within {READY_TIMEOUT_S:.0f} s")


def _stop(proc: subprocess.Popen[str]) -> None:
    """Ctrl-C (its documented stop), then SIGTERM, then SIGKILL to its whole group."""
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGKILL):
        if proc.poll() is not None:
            return
        try:
            os.killpg(proc.pid, sig)
        except ProcessLookupError:
            return
        try:
            proc.wait(STOP_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            continue


def main(argv: list[str]) -> int:
    session = argv[0] if argv and argv[0] != "--" else "exp1-emulated"
    pytest_args = argv[argv.index("--") + 1:] if "--" in argv else []
    link_dir = Path(tempfile.mkdtemp(prefix="fasthex-hil-"))
    proc = subprocess.Popen(
        [sys.executable, "-m", "groundstation", "emulate", session, "--clock", "realtime",
         "--link-dir", str(link_dir)],
        cwd=ROOT, stdout=subprocess.PIPE, stdin=subprocess.DEVNULL, text=True,
        start_new_session=True)  # our own group: a terminal's Ctrl-C reaches us, we stop it

    def on_signal(signum: int, frame: FrameType | None) -> None:
        raise KeyboardInterrupt  # unwinds through the finally below

    previous = {s: signal.signal(s, on_signal) for s in (signal.SIGTERM, signal.SIGHUP)}
    try:
        try:
            devices = _devices(proc)
        except RuntimeError as exc:
            print(f"run_against_emulator: {exc}", file=sys.stderr)
            return 3
        env = dict(os.environ, FASTHEX_HIL_FLIGHT_CTRL=devices["flight-ctrl"],
                   FASTHEX_HIL_SERVO=devices["servo"], FASTHEX_HIL_MOCAP=devices["mocap"],
                   FASTHEX_HIL_PROPS_OFF="1", FASTHEX_HIL_REQUIRE="1")
        for key in ("FASTHEX_HIL_FLIGHT_CTRL", "FASTHEX_HIL_SERVO", "FASTHEX_HIL_MOCAP"):
            print(f"{key}={env[key]}", flush=True)
        return subprocess.call([sys.executable, "-m", "pytest", "-m", "hil", "tests/hil",
                                "-p", "no:cacheprovider", "-rs", *pytest_args],
                               cwd=ROOT, env=env)
    except KeyboardInterrupt:
        print("run_against_emulator: interrupted", file=sys.stderr)
        return 130
    finally:
        _stop(proc)
        if proc.stdout is not None:
            proc.stdout.close()
        for s, handler in previous.items():
            signal.signal(s, handler)
        shutil.rmtree(link_dir, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))

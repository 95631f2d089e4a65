"""Stop signals at random moments of a flight: each of SIGINT, SIGTERM and SIGHUP sent to the
process group of `fasthex fly` (a short lockstep session) at N random times from start-up to
touchdown. Counts hangs, unexpected cuts, unreadable records and leftovers (processes, temp dirs).

Run by hand (not in CI; about 5 s per flight):

    python tools/signal_stress.py [--n 20] [--seed 1]
"""

from __future__ import annotations

import argparse
import collections
import os
import random
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from flight_support import SESSION, SHORT_MISSION

from groundstation.record import read_record


def _processes_mentioning(text: str) -> int:
    n = 0
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                cmd = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode(
                    errors="replace")
            except OSError:
                continue
            n += text in cmd
    return n


def one_flight(workdir: Path, sig: int, at_s: float) -> str:
    tmp = workdir / "tmp"
    tmp.mkdir()
    (workdir / "short-hover.yaml").write_text(SHORT_MISSION)
    session = workdir / "s.yaml"
    session.write_text(SESSION.format(seed=2, faults="", corrupt=0.0, zmax=2.5,
                                      servo_action="hold"))
    record = workdir / "s.fhr"
    proc = subprocess.Popen([sys.executable, "-m", "groundstation", "fly", str(session),
                             "--record", str(record), "--rerun", "off", "--quiet"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            env=dict(os.environ, TMPDIR=str(tmp)), start_new_session=True)
    try:
        proc.wait(timeout=at_s)
        return "ended before the signal"
    except subprocess.TimeoutExpired:
        pass
    os.killpg(proc.pid, sig)
    try:
        _, err = proc.communicate(timeout=90)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.communicate()
        return "HANG"
    events = Path(str(record) + ".events.txt")
    text = events.read_text() if events.exists() else ""
    if "Traceback" in err:
        return "TRACEBACK"
    if "-> CUT" in text:
        return "UNEXPECTED CUT"
    deadline = time.monotonic() + 10
    while _processes_mentioning(str(tmp)) and time.monotonic() < deadline:
        time.sleep(0.05)
    if _processes_mentioning(str(tmp)) or list(tmp.iterdir()):
        return "LEFTOVERS"
    if not record.exists():
        if "nothing was armed" in err or "interrupted" in err:
            return "stopped during start-up (no record: nothing flown)"
        if proc.returncode == -sig and not err.strip():
            # the signal's default action: it came before `fly` had opened anything
            return "killed before the session started (nothing opened)"
        return f"NO RECORD (exit {proc.returncode}): {err.strip()[-200:]}"
    try:
        read_record(record)
    except (OSError, ValueError) as exc:
        return f"UNREADABLE RECORD: {exc}"
    if "stop before arming" in text or "land before takeoff" in text:
        return "stopped before take-off"
    if "LANDING -> DISARMED: touchdown" in text and "operator stop: landing" in text:
        return "landed on the signal"
    if "LANDING -> DISARMED: touchdown" in text:
        return "signal during the planned landing: landed"
    return f"OTHER (exit {proc.returncode}): {text.strip().splitlines()[-1:]}"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=20, help="flights per signal")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--max-s", type=float, default=7.0,
                    help="latest signal time after start (s of wall time; ~touchdown)")
    args = ap.parse_args()
    rng = random.Random(args.seed)
    bad = 0
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        outcomes: collections.Counter[str] = collections.Counter()
        for _ in range(args.n):
            at_s = rng.uniform(0.0, args.max_s)
            with tempfile.TemporaryDirectory(prefix="signal-stress-") as d:
                out = one_flight(Path(d), sig, at_s)
            outcomes[out] += 1
            bad += out.isupper() or out.startswith(("NO RECORD", "UNREADABLE", "OTHER"))
        print(f"{signal.Signals(sig).name}: " + "; ".join(f"{k}: {v}"
                                                        for k, v in sorted(outcomes.items())),
              flush=True)
    print(f"failures (hang, unexpected cut, traceback, leftovers, unreadable record): {bad}")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())

"""``fasthex fly [SESSION]``: one flight session on real or emulated hardware.

Preflight checks, arm, take off, fly the mission, land, disarm; failsafes on the way. Ctrl-C
lands, a second Ctrl-C cuts the motors; Ctrl-Z is refused (the motors need a command every tick).
The flight record is written as the flight goes.

On a terminal, events (preflight results, state changes, faults) scroll as they happen above a
live status line (:mod:`groundstation.console`); the end-of-flight summary follows
(:mod:`groundstation.summary`). The record goes to ``--record``, else the session's
``telemetry.record``, else ``flights/<session>-<time>.fhr`` under the working directory.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from groundstation.signals import StopSignals

NAME = "fly"
HELP = "fly a session (default: the paper's Experiment 1 on the emulated vehicle)"
DEFAULT_SESSION = "exp1-emulated"


def _shipped_sessions() -> str:
    from config import available, config_root, find_config

    names = []
    for name in available("sessions"):
        try:  # the description line of the file, if it has one
            import yaml

            text = find_config("sessions", name).read_text(encoding="utf-8")
            desc = str(yaml.safe_load(text).get("description", ""))
        except Exception:
            desc = ""
        names.append(f"  {name:22s} {desc}".rstrip())
    return ("shipped sessions (in " + str(config_root() / "sessions") + "):\n"
            + "\n".join(names))


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.epilog = _shipped_sessions()
    parser.add_argument("session", nargs="?", default=DEFAULT_SESSION,
                        help=f"shipped session name (listed below) or a session YAML file "
                        f"(default {DEFAULT_SESSION})")
    parser.add_argument("--clock", choices=("realtime", "lockstep"), default=None,
                        help="emulated backend: override the session's clock")
    from groundstation.cli import seed_arg

    parser.add_argument("--seed", type=seed_arg, default=None,
                        help="emulated backend: seed, 0 .. 2^32-1")
    parser.add_argument("--record", default=None, metavar="PATH",
                        help="flight-record path; overrides the session's telemetry.record "
                        "(default flights/<session>-<time>.fhr)")
    parser.add_argument("--json", action="store_true",
                        help="print the exit summary as one JSON object")
    parser.add_argument("--quiet", action="store_true", help="no live status or event lines")
    parser.add_argument("--realtime-settings", action=argparse.BooleanOptionalAction,
                        default=None, help="CPU pinning, SCHED_FIFO for every loop thread, "
                        "locked memory, a frozen GC and the CPU wake-up latency held at 0, each "
                        "where permitted (default: on for hardware and realtime sessions; in "
                        "lockstep the wake-up latency only)")
    parser.add_argument("--rerun", choices=("spawn", "serve", "save", "off", "auto"),
                        default=None, help="live dashboard: spawn the viewer, serve the web "
                        "viewer, save RECORD.rrd, or off (default: the session's; auto = spawn "
                        "with a display, else none: `fasthex replay RECORD` shows or saves it "
                        "later)")
    parser.add_argument("--mavlink", default=None, metavar="URI",
                        help="MAVLink endpoint for a GCS, e.g. udpout:127.0.0.1:14550 "
                        "(default: the session's; '' to switch off)")
    parser.add_argument("--mavlink-key-file", default=None, metavar="PATH",
                        help="MAVLink signing key file (64 hex digits or a passphrase); "
                        "overrides the session's telemetry.mavlink_key_file and "
                        "$FASTHEX_MAVLINK_KEY. Without a key, flight-changing commands are "
                        "refused")
    parser.add_argument("--props-off", action="store_true",
                        help="bench test with the propellers off: preflight, arm, spin every "
                        "motor at idle for a few seconds, disarm; never takes off")
    parser.add_argument("--corrupt-prob", type=float, default=0.0,
                        help="emulated backend: byte corruption on the Flight-Ctrl link")


def run(args: argparse.Namespace) -> int:
    from groundstation.signals import StopSignals

    # First of all: SIGINT (Ctrl-C), SIGTERM, SIGHUP and SIGQUIT (Ctrl-\) are requests from
    # here on (the first lands, a second cuts), so that one during the start-up (the files
    # load, the devices open: a second or more) ends it as every stopped start-up does (one
    # line saying nothing was armed, exit code 1), not as a KeyboardInterrupt (exit 130);
    # Ctrl-Z is refused (a suspended ground station stops commanding the motors)
    signals = StopSignals(flight=True).install()
    try:
        return _fly(args, signals)
    finally:
        signals.restore()


def _fly(args: argparse.Namespace, signals: StopSignals) -> int:
    from dataclasses import replace

    from config import find_config
    from controller.missions import Mission
    from groundstation.cli import UserError
    from groundstation.configs import load_mission, load_vehicle, preflight_warnings
    from groundstation.console import Console
    from groundstation.gcs import summary_lines as mavlink_summary_lines
    from groundstation.session import FlightSession, SessionError, SessionInterruptedError
    from groundstation.session_config import EmulatedBackend, load_session, resolve_reference
    from groundstation.summary import json_ready, summary_text

    path = find_config("sessions", args.session)
    cfg = load_session(path)
    backend = cfg.backend
    if isinstance(backend, EmulatedBackend):
        if args.clock:
            backend = replace(backend, clock=args.clock)
        if args.seed is not None:
            backend = replace(backend, seed=args.seed)
        cfg = replace(cfg, backend=backend)
    elif args.clock or args.seed is not None:
        raise UserError("--clock and --seed apply to emulated sessions only")
    params = load_vehicle(resolve_reference(path, cfg.vehicle))
    mission = Mission(load_mission(resolve_reference(path, cfg.mission)))
    for line in preflight_warnings(mission, params):  # before anything is armed
        print(line, file=sys.stderr)
    if args.mavlink:  # as telemetry.mavlink is checked at load: before anything opens
        from drivers.errors import TransportUriError
        from drivers.mavlink.link import parse_mavlink_uri

        try:
            parse_mavlink_uri(args.mavlink)
        except TransportUriError as exc:
            raise UserError(f"--mavlink {exc}") from None
    record = record_path(args.record, cfg.telemetry.record, path, cfg.name)
    make_record_folder(record)
    check_record_path(record)
    show = not args.quiet and not args.json
    console = Console(sys.stderr, status=lambda: session.loop.status if session.loop else "")
    session = FlightSession(cfg, params, mission, record_path=record,
                            echo_events=show, on_event=console.event if show else None,
                            corrupt_prob=args.corrupt_prob,
                            realtime_settings=args.realtime_settings,
                            dashboard=args.rerun, mavlink=args.mavlink,
                            mavlink_key_file=args.mavlink_key_file, props_off=args.props_off)
    session.requests = signals.requests  # one deque from the start-up's first instruction
    session.stop_signals = signals
    if show:
        console.start()
    try:
        if signals.count:  # while the files loaded: nothing was started
            raise SessionInterruptedError("stopped while loading the session: nothing was "
                                          "armed")
        outcome = session.run()
    except SessionInterruptedError as exc:
        console.stop()  # its last lines first; this one after, on a line of its own
        print(f"fasthex: {signals.describe()}: {exc}", file=sys.stderr)
        return 1
    except SessionError as exc:
        raise UserError(str(exc)) from None
    finally:
        if signals.hangup:  # the terminal is gone: print nothing more to it
            console.broken = True
        console.stop()
    summary = flight_summary(outcome, params, cfg.name)
    try:
        if args.json:
            json.dump(json_ready(summary), sys.stdout, indent=2)
            sys.stdout.write("\n")
        else:
            requested = args.rerun or cfg.telemetry.rerun
            mode = ("auto-headless" if requested == "auto" and outcome.dashboard_mode == "off"
                    else outcome.dashboard_mode)
            sys.stdout.write(summary_text(
                summary, clock=getattr(cfg.backend, "clock", "realtime"),
                rate_hz=cfg.backend.imu_rate_hz, dashboard_mode=mode,
                dashboard_file=str(outcome.dashboard_file) if outcome.dashboard_file
                else None, extra=mavlink_summary_lines(outcome.record_path)))
        sys.stdout.flush()
    except OSError:  # stdout was the terminal that hung up: the record and events stand
        pass
    planned = summary["end_reason"] in ("touchdown", "mission complete") or (
        args.props_off and summary["end_reason"].startswith("props-off bench test complete"))
    # an emulated flight that ended "normally" may still have come down hard (a rotor lost):
    # its truth says so
    return 0 if planned and not summary.get("truth_crash") else 1


def record_path(cli: str | None, configured: str, session_file: Path, session: str) -> Path:
    """Where the flight record goes: ``--record``, else the session's ``telemetry.record``
    (relative to the session file, like its other paths), else
    ``flights/<session>-<time>.fhr`` under the working directory. ``{session}`` and ``{time}``
    in the configured path are replaced, so one session file can keep every flight."""
    stamp = time.strftime("%Y%m%d-%H%M%S")
    if cli:
        return Path(cli)
    if configured:
        path = Path(configured.replace("{session}", session).replace("{time}", stamp))
        path = path.expanduser()
        return path if path.is_absolute() else session_file.parent / path
    return Path("flights") / f"{session}-{stamp}.fhr"


def check_record_path(record: Path) -> None:
    """The flight record and its events file can be written, before anything opens (the
    telemetry process could not open them mid-start-up; /dev/full took all the memory when
    the summary read it back). A ``UserError`` otherwise; nothing is left behind."""
    from groundstation.cli import UserError

    if record.is_dir():
        raise UserError(f"the flight record {record} is a folder; expected a file path "
                        "(--record or telemetry.record)")
    if record.exists() and not record.is_file():
        raise UserError(f"the flight record {record} is not a regular file (a device or a "
                        "pipe); expected a file path (--record or telemetry.record)")
    for path in (record, record.with_name(record.name + ".events.txt")):
        existed = path.exists()
        try:
            path.open("ab").close()
            if not existed:
                path.unlink()
        except OSError as exc:
            raise UserError(f"cannot write the flight record's file {path}: "
                            f"{exc.strerror or exc}") from None


def make_record_folder(record: Path, what: str = "the record's") -> None:
    """Create the flight record's folder and its parents (``what``: whose folder, for the
    message); a ``UserError`` if that fails."""
    from groundstation.cli import UserError

    try:
        record.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"cannot create {what} folder {record.parent}: "
                        f"{exc.strerror}") from None


def flight_summary(outcome: Any, params: Any, session: str) -> dict[str, Any]:
    from groundstation.metrics import flight_metrics
    from groundstation.record import read_record

    r = outcome.result
    t = r.timing
    out: dict[str, Any] = {
        "session": session, "end_reason": r.end_reason, "ticks": r.ticks,
        "flight_time_s": r.flight_time_s, "wall_time_s": outcome.wall_time_s,
        "deadline_misses": t.deadline_misses, "compute_p50_ms": t.compute_p50_ms,
        "compute_p99_ms": t.compute_p99_ms, "period_p50_ms": t.period_p50_ms,
        "jitter_p99_ms": t.jitter_p99_ms, "latency_p50_ms": t.latency_p50_ms,
        "latency_p99_ms": t.latency_p99_ms, "compute_mean_ms": t.compute_mean_ms,
        "numerics_p50_ms": t.numerics_p50_ms, "numerics_mean_ms": t.numerics_mean_ms,
        "faults": list(r.faults),
        "transitions": [f"{tr.t_s:.3f} s {tr.from_state.name} -> {tr.to_state.name}: "
                        f"{tr.reason}" for tr in r.transitions],
        "poses_rejected": r.estimator_poses_rejected,
        "fusion_delay_ms": 1e3 * r.estimator_fusion_delay_s,
        "telemetry_dropped": r.telemetry_dropped,
        # realtime: the longest wait between two IMU samples on the host clock (gaps below
        # imu_timeout_s are bridged with the last command), and the empty waits it took
        "imu_gap_max_ms": r.counters.get("imu_gap_max_us", 0) / 1000.0,
        "imu_gap_max_at_s": r.counters.get("imu_gap_max_at_ms", 0) / 1000.0,
        "imu_waits_empty": r.counters.get("imu_missing", 0),
        # lockstep: samples counted lost after LOCKSTEP_LOST_S of wall time (not reproducible)
        "lockstep_stalls": r.counters.get("lockstep_stalls", 0),
        "record": str(outcome.record_path),
        "preflight": [{"check": n, "pass": ok, "value": v} for n, ok, v in outcome.preflight],
    }
    truth = getattr(outcome, "truth", None) or {}
    if truth:  # the emulated vehicle's own account (no such thing on hardware)
        speeds = truth.get("touchdown_speeds_m_s") or []
        out["truth_touchdowns"] = len(speeds)
        out["truth_touchdown_max_m_s"] = max(speeds, default=0.0)
        out["truth_landed"] = bool(truth.get("landed"))
        out["truth_height_m"] = float(truth.get("height_m", 0.0))
        out["truth_crash"] = str(truth.get("crash", ""))
    from groundstation.gcs import summary_fields

    out.update(summary_fields(outcome.record_path))  # mavlink_*: the link's counters, if on
    try:
        rec = read_record(outcome.record_path)
    except (OSError, ValueError) as exc:  # e.g. the telemetry process was killed: say so
        out["state_source"] = f"none: the flight record cannot be read ({exc})"
        return out
    out["state_source"] = rec.metadata.get("state", "ground-station estimate")
    if len(rec.rows):
        out.update(flight_metrics(rec.rows, min_spin_hz=params.rotors.min_spin_hz,
                                  max_spin_hz=params.rotors.max_spin_hz))
    return out

"""``fasthex replay RECORD``: stream a flight record into the live dashboard again.

Works on records of ``fasthex fly`` (with their ``RECORD.events.txt``) and of
``fasthex simulate --log``. ``--speed realtime`` paces the blocks by the record's clock,
``--speed max`` sends them as fast as rerun takes them. ``--rerun`` chooses the output as in a
flight: ``spawn`` the native viewer, ``serve`` the web viewer on localhost (the URL is printed;
the server stays up until Ctrl-C), ``save`` an ``.rrd`` (``--out``, default ``RECORD.rrd``),
or ``off``. Default: ``spawn`` with a display, ``save`` without.
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
from pathlib import Path

NAME = "replay"
HELP = "stream a flight record into the rerun dashboard (viewer, web viewer or .rrd)"

BLOCK_S = 0.1  # the telemetry process's drain period


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("record", help="flight record file (from fly or simulate --log)")
    parser.add_argument("--speed", choices=("realtime", "max"), default="realtime",
                        help="pace by the record's clock (default) or as fast as possible")
    parser.add_argument("--rerun", choices=("spawn", "serve", "save", "off"), default=None,
                        help="dashboard output (default: spawn with a display, else save)")
    parser.add_argument("--out", default=None, metavar="FILE.rrd",
                        help="also save the dashboard here (with save: default RECORD.rrd)")
    parser.add_argument("--grpc-port", type=int, default=9876, metavar="PORT",
                        help="rerun gRPC port for spawn/serve (default 9876)")
    parser.add_argument("--web-port", type=int, default=9090, metavar="PORT",
                        help="web viewer HTTP port for serve (default 9090)")


def run(args: argparse.Namespace) -> int:
    from groundstation.cli import UserError
    from groundstation.dashboard import Dashboard, default_mode, parse_events
    from groundstation.record import RecordFormatError, read_record

    path = Path(args.record)
    if not path.is_file():
        raise UserError(f"no such flight record: {path}")
    try:
        record = read_record(path)
    except RecordFormatError as exc:
        raise UserError(str(exc)) from None
    mode = args.rerun or default_mode()
    out = Path(args.out) if args.out else (path.with_suffix(".rrd") if mode == "save" else None)
    events_file = path.with_name(path.name + ".events.txt")
    events = parse_events(events_file.read_text(encoding="utf-8", errors="replace")) \
        if events_file.is_file() else []
    try:
        dash = Dashboard(mode, out, metadata=record.metadata, grpc_port=args.grpc_port,
                         web_port=args.web_port)
    except (OSError, RuntimeError) as exc:
        raise UserError(f"cannot start the rerun dashboard ({mode}): {exc}") from None
    if dash.viewer_url:
        print(f"web viewer: {dash.viewer_url}", flush=True)
    rows = record.rows
    t = rows["t_s"]
    n = len(rows)
    ev_i = 0
    start = 0
    wall0 = time.monotonic()
    t0 = float(t[0]) if n else 0.0
    while start < n:
        stop = int(min(n, max(start + 1, int(start + 500 * BLOCK_S))))
        # blocks end on the record's clock, so gaps (dropped telemetry) stay gaps
        t_end = float(t[stop - 1])
        if args.speed == "realtime":
            delay = (t_end - t0) - (time.monotonic() - wall0)
            if delay > 0:
                time.sleep(delay)
        dash.log_rows(rows[start:stop])
        while ev_i < len(events) and events[ev_i][0] <= t_end:
            dash.log_event(*events[ev_i])
            ev_i += 1
        start = stop
    for ev in events[ev_i:]:
        dash.log_event(*ev)
    dash.close()
    what = {"spawn": "native viewer", "serve": "web viewer", "save": str(out),
            "off": "nowhere (off)"}[mode]
    print(f"replayed {n} rows ({(float(t[-1]) - t0) if n else 0.0:.1f} s) and "
          f"{len(events)} events to {what}" + (f"; saved {out}" if out and mode != "save"
                                                 else ""), flush=True)
    if mode == "serve":
        print("serving the web viewer; Ctrl-C to stop", file=sys.stderr, flush=True)
        try:
            threading.Event().wait()
        except KeyboardInterrupt:
            return 0
    return 0

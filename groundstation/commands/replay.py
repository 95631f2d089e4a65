"""``fasthex replay RECORD``: stream a flight record into the live dashboard again.

Works on records of ``fasthex fly`` (with their ``RECORD.events.txt``) and of
``fasthex simulate --log``. ``--speed realtime`` paces the blocks by the record's clock,
``--speed max`` sends them as fast as rerun takes them. By default a live viewer (``spawn``,
``serve``) is paced, so the flight plays as it was flown, and a file (``save``, ``off``) is
written at full speed with a progress bar on the terminal. ``--rerun`` chooses the output as in a
flight: ``spawn`` the native viewer, ``serve`` the web viewer on localhost (the URL is printed;
the server stays up until Ctrl-C), ``save`` an ``.rrd`` (``--out``, default ``RECORD.rrd``),
or ``off``. Default: ``spawn`` with a display, ``save`` without.
"""

from __future__ import annotations

import argparse
import contextlib
import sys
import threading
import time
from pathlib import Path
from typing import TextIO

NAME = "replay"
HELP = "stream a flight record into the rerun dashboard (viewer, web viewer or .rrd)"

BLOCK_S = 0.1  # the telemetry process's drain period


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("record", help="flight record file (from fly or simulate --log)")
    parser.add_argument("--speed", choices=("realtime", "max"), default=None,
                        help="pace by the record's clock or as fast as possible (default: "
                        "realtime for spawn and serve, max for save and off)")
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
    # pacing only means something to someone watching a viewer
    speed = args.speed or ("realtime" if mode in ("spawn", "serve") else "max")
    out = Path(args.out) if args.out else (path.with_suffix(".rrd") if mode == "save" else None)
    if out is not None:  # a bad path fails here, not as a warning of rerun's after the replay
        from groundstation.commands.fly import make_record_folder

        make_record_folder(out, "the dashboard file's")
        try:
            out.open("wb").close()
        except OSError as exc:
            raise UserError(f"--out {out}: cannot write the dashboard file ({exc.strerror}); "
                            "expected a file path") from None
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
    progress = Progress(sys.stderr, n, float(t[-1]) - t0 if n else 0.0)
    while start < n:
        stop = int(min(n, max(start + 1, int(start + 500 * BLOCK_S))))
        # blocks end on the record's clock, so gaps (dropped telemetry) stay gaps
        t_end = float(t[stop - 1])
        if speed == "realtime":
            delay = (t_end - t0) - (time.monotonic() - wall0)
            if delay > 0:
                time.sleep(delay)
        dash.log_rows(rows[start:stop])
        while ev_i < len(events) and events[ev_i][0] <= t_end:
            dash.log_event(*events[ev_i])
            ev_i += 1
        start = stop
        progress.update(stop, t_end - t0)
    for ev in events[ev_i:]:
        dash.log_event(*ev)
    dash.close()
    progress.done()
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


class Progress:
    """A one-line progress bar on a terminal (nothing otherwise), redrawn at most 10 times a
    second: rows done of the record, and the record time they reach."""

    WIDTH = 30

    def __init__(self, stream: TextIO, rows: int, duration_s: float) -> None:
        self._stream = stream
        self._rows = max(rows, 1)
        self._duration_s = duration_s
        self._shown_at = 0.0
        try:
            self._live = stream.isatty()
        except (AttributeError, ValueError, OSError):
            self._live = False

    def update(self, done: int, t_s: float, *, force: bool = False) -> None:
        now = time.monotonic()
        if not self._live or (now - self._shown_at < 0.1 and not force):
            return
        self._shown_at = now
        frac = min(max(done / self._rows, 0.0), 1.0)
        bar = "#" * round(frac * self.WIDTH)
        with contextlib.suppress(OSError, ValueError):
            self._stream.write(f"\r\x1b[2Kreplay [{bar:<{self.WIDTH}}] {100 * frac:3.0f} %  "
                               f"{t_s:6.1f} of {self._duration_s:.1f} s")
            self._stream.flush()

    def done(self) -> None:
        if self._live:  # the bar gives way to the result line
            with contextlib.suppress(OSError, ValueError):
                self._stream.write("\r\x1b[2K")
                self._stream.flush()

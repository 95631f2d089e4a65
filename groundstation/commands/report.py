"""``fasthex report RECORD [--out DIR]``: the paper-style figure and the metrics of a flight.

Writes ``DIR/plots.png`` (eight stacked panels, red while under-actuated, green while fully
actuated), ``DIR/metrics.json`` (the keys and values of ``fasthex simulate --json``'s metrics)
and ``DIR/metrics.md`` (the same as a markdown table). ``DIR`` defaults to ``RECORD.report/``
next to the record (a missing folder is made). ``--out`` naming a file, a path under a file or a
folder that cannot be made or written is refused before the record is read, like a record without
rows (a header only).
Works on records of ``fasthex simulate --log`` and ``fasthex fly``.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

NAME = "report"
HELP = "write the paper-style figure and the metrics table of a flight record"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("record", help="flight record file (from simulate --log or fly)")
    parser.add_argument("--out", default=None, metavar="DIR",
                        help="output folder (default: RECORD.report next to the record)")


def run(args: argparse.Namespace) -> int:
    from groundstation.cli import UserError
    from groundstation.record import RecordFormatError
    from groundstation.report import write_report

    record = Path(args.record)
    if not record.is_file():
        raise UserError(f"no such flight record: {record}")
    out = Path(args.out) if args.out else record.with_name(record.name + ".report")
    made = make_report_folder(out)
    try:
        files = write_report(record, out)
    except RecordFormatError as exc:
        remove_made_folders(made)  # a refused record leaves no report folder behind
        raise UserError(str(exc)) from None
    print(f"figure:  {files.figure}")
    print(f"metrics: {files.metrics_md}, {files.metrics_json}")
    return 0


def make_report_folder(out: Path) -> list[Path]:
    """Create the report folder ``out`` (and its parents) and check a file can be written in it,
    before any work; a ``UserError`` naming ``--out`` otherwise. Returns the folders it made,
    deepest first."""
    from groundstation.cli import UserError

    if out.exists() and not out.is_dir():
        raise UserError(f"--out {out}: is a file; expected a folder for the report")
    made = [p for p in (out, *out.parents) if not p.exists()]
    try:
        out.mkdir(parents=True, exist_ok=True)
        tempfile.TemporaryFile(dir=out).close()  # /proc, a read-only mount: refused here
    except OSError as exc:
        remove_made_folders(made)
        raise UserError(f"--out {out}: cannot create the report folder ({exc.strerror}); "
                        "expected a folder path") from None
    return made


def remove_made_folders(made: list[Path]) -> None:
    """Remove the (still empty) folders :func:`make_report_folder` made."""
    for folder in made:
        try:
            folder.rmdir()
        except OSError:
            return

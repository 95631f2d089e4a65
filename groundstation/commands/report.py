"""``fasthex report RECORD [--out DIR]``: the paper-style figure and the metrics of a flight.

Writes ``DIR/plots.png`` (eight stacked panels, red while under-actuated, green while fully
actuated), ``DIR/metrics.json`` (the keys and values of ``fasthex simulate --json``'s metrics)
and ``DIR/metrics.md`` (the same as a markdown table). ``DIR`` defaults to ``RECORD.report/``
next to the record. Works on records of ``fasthex simulate --log`` and ``fasthex fly``; one
without rows (a header only) is refused.
"""

from __future__ import annotations

import argparse
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
    try:
        files = write_report(record, out)
    except RecordFormatError as exc:
        raise UserError(str(exc)) from None
    print(f"figure:  {files.figure}")
    print(f"metrics: {files.metrics_md}, {files.metrics_json}")
    return 0

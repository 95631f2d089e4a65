"""``fasthex analyze``: the vehicle model's numbers over the tilt range, as a table or JSON."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

NAME = "analyze"
HELP = "print the vehicle model over the tilt range (rank, efficiency, force bounds, Cardan)"

#: the finest tilt grid: the analysis's own Cardan-error grid (at most 9001 rows at 90 deg)
MIN_STEP_DEG = 0.01


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--vehicle", default="fasthex",
                        help="shipped vehicle name or a vehicle YAML file (default: fasthex)")
    parser.add_argument("--step-deg", type=float, default=5.0,
                        help=f"tilt grid step in degrees, at least {MIN_STEP_DEG:g} "
                        "(default: 5)")
    parser.add_argument("--json", action="store_true", help="print one JSON object instead")
    parser.add_argument("--plots", metavar="DIR", help="also write PNG figures into DIR")


def run(args: argparse.Namespace) -> int:
    from groundstation.analysis import analyze, format_table, write_plots
    from groundstation.cli import UserError
    from groundstation.configs import load_vehicle

    if not args.step_deg >= MIN_STEP_DEG:
        raise UserError(f"--step-deg must be at least {MIN_STEP_DEG:g} deg, got "
                        f"{args.step_deg:g}")
    params = load_vehicle(args.vehicle)
    if args.plots:  # before the table, so a bad folder costs no output
        plots = Path(args.plots)
        if plots.exists() and not plots.is_dir():
            raise UserError(f"--plots {plots}: is a file; expected a folder for the PNG figures")
        try:
            plots.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise UserError(f"--plots {plots}: cannot create the folder ({exc.strerror}); "
                            "expected a folder for the PNG figures") from None
    result = analyze(params, step_deg=args.step_deg)
    if args.json:
        json.dump(result.to_json(), sys.stdout, indent=2)
        sys.stdout.write("\n")
    else:
        print(format_table(result))
    if args.plots:
        try:
            paths = write_plots(params, result, args.plots)
        except OSError as exc:
            raise UserError(f"--plots {args.plots}: cannot write the figures "
                            f"({exc.strerror})") from None
        print("wrote " + ", ".join(paths), file=sys.stderr if args.json else sys.stdout)
    return 0

"""``fasthex analyze``: the vehicle model's numbers over the tilt range, as a table or JSON."""

from __future__ import annotations

import argparse
import json
import sys

NAME = "analyze"
HELP = "print the vehicle model over the tilt range (rank, efficiency, force bounds, Cardan)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--vehicle", default="fasthex",
                        help="shipped vehicle name or a vehicle YAML file (default: fasthex)")
    parser.add_argument("--step-deg", type=float, default=5.0,
                        help="tilt grid step in degrees (default: 5)")
    parser.add_argument("--json", action="store_true", help="print one JSON object instead")
    parser.add_argument("--plots", metavar="DIR", help="also write PNG figures into DIR")


def run(args: argparse.Namespace) -> int:
    from groundstation.analysis import analyze, format_table, write_plots
    from groundstation.cli import UserError
    from groundstation.configs import load_vehicle

    if not args.step_deg > 0.0:
        raise UserError(f"--step-deg must be positive, got {args.step_deg}")
    params = load_vehicle(args.vehicle)
    result = analyze(params, step_deg=args.step_deg)
    if args.json:
        json.dump(result.to_json(), sys.stdout, indent=2)
        sys.stdout.write("\n")
    else:
        print(format_table(result))
    if args.plots:
        paths = write_plots(params, result, args.plots)
        print("wrote " + ", ".join(paths), file=sys.stderr if args.json else sys.stdout)
    return 0

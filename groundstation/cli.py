"""The ``fasthex`` command line: one subcommand per module of :mod:`groundstation.commands`.

Errors a user can fix (a bad config file, a port that cannot be opened) are printed as one line
without a traceback and give exit code 2; Ctrl-C gives 130 (``fly`` takes its stop signals
itself from its first instruction on: a stopped session exits 1).
"""

from __future__ import annotations

import argparse
import importlib
import logging
import os
import pkgutil
import sys
from types import ModuleType

import groundstation.commands as commands_pkg
from config.schema import ConfigError


class UserError(Exception):
    """A problem the user can fix (missing file, unknown device); printed without traceback."""


def seed_arg(text: str) -> int:
    """``type`` of every ``--seed``: the range of ``backend.seed`` in a session file."""
    from groundstation.session_config import SEED_MAX

    try:
        seed = int(text)
    except ValueError:
        seed = -1
    if not 0 <= seed <= SEED_MAX:
        raise argparse.ArgumentTypeError(f"expected an integer 0 .. {SEED_MAX} (as backend.seed "
                                         f"in a session file), got {text!r}")
    return seed


def _command_modules() -> list[ModuleType]:
    mods = []
    for info in sorted(pkgutil.iter_modules(commands_pkg.__path__), key=lambda i: i.name):
        if not info.name.startswith("_"):
            mods.append(importlib.import_module(f"{commands_pkg.__name__}.{info.name}"))
    return mods


def version() -> str:
    """The installed package's version (``pyproject.toml``)."""
    from importlib.metadata import PackageNotFoundError
    from importlib.metadata import version as dist_version

    try:
        return dist_version("fasthex")
    except PackageNotFoundError:  # run from a source tree that was never installed
        return "unknown (not installed)"


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="fasthex",
        description="Ground station for the FAST-Hex tilting hexarotor (500 Hz, real or "
        "emulated hardware).",
    )
    parser.add_argument("--version", action="version", version=f"fasthex {version()}")
    parser.add_argument("-v", "--verbose", action="count", default=0,
                        help="more log output (-vv for debug)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for mod in _command_modules():
        p = sub.add_parser(mod.NAME, help=mod.HELP, description=mod.HELP)
        mod.add_arguments(p)
        p.set_defaults(_run=mod.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=[logging.WARNING, logging.INFO, logging.DEBUG][min(args.verbose, 2)],
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    if not getattr(args, "_run", None):
        parser.print_help()
        return 2
    try:
        return int(args._run(args))
    except ConfigError as exc:
        print(f"fasthex: config error: {exc}", file=sys.stderr)
        return 2
    except UserError as exc:
        print(f"fasthex: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("fasthex: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # output piped into e.g. `head`: not an error of ours
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 0


if __name__ == "__main__":
    sys.exit(main())

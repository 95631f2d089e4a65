"""``fasthex`` subcommands, one module each, found automatically by :mod:`groundstation.cli`.

A command module defines ``NAME`` (the subcommand), ``HELP`` (one line),
``add_arguments(parser: argparse.ArgumentParser) -> None`` and
``run(args: argparse.Namespace) -> int`` (the exit code). Keep module imports light: import
heavy libraries (rerun, matplotlib, serial) inside ``run`` so ``fasthex --help`` stays fast.
"""

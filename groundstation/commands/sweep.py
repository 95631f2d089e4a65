"""``fasthex sweep CAMPAIGN``: fly every run of a campaign, in parallel, into one table;
``fasthex sweep report TABLE``: the table's plots (metric versus parameter, heat maps, the
failure map) and a summary.

The campaign file (:mod:`groundstation.campaign`) names the mission, the scenarios, the
parameters and the seeds; the runs execute on every local core by default (``--workers N``),
or on Dask (``--scheduler local`` for a ``LocalCluster``, ``--scheduler tcp://HOST:8786`` for
a cluster): :mod:`groundstation.sweep`. The table (Parquet, default ``NAME.parquet`` for the
campaign's ``name``) is resumable: run the same command again after a Ctrl-C, a ``kill`` or a
crash and only the missing runs fly.

Exit codes: 0 when every run has a row (whatever its verdict), 130 when interrupted by
Ctrl-C, SIGTERM or the terminal closing (the rows done so far are in the table; the runs in
flight are dropped and every worker process is ended), 2 for a problem with the campaign file
or the options. The same signal again within 0.1 s is the same stop (``timeout`` sends its
signal to the command and then to its process group): it does not interrupt the clean-up.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
from pathlib import Path

NAME = "sweep"
HELP = "fly a campaign of simulated flights in parallel into a results table (or: sweep report)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("campaign", metavar="CAMPAIGN|report",
                        help="campaign name or YAML file; or 'report' followed by a table")
    parser.add_argument("table", nargs="?", default=None, metavar="TABLE",
                        help="with 'report': the results table (.parquet) to draw")
    parser.add_argument("--out", default=None, metavar="PATH",
                        help="results table to write (default NAME.parquet for the campaign's "
                        "name); with 'report': the directory for the plots (default "
                        "TABLE-report/)")
    parser.add_argument("--workers", type=int, default=None, metavar="N",
                        help="worker processes (default: every core; 1 flies in this "
                        "process); at most one per run left to fly and 4 per core")
    parser.add_argument("--scheduler", default=None, metavar="URI",
                        help="run on Dask: 'local' starts a LocalCluster of --workers "
                        "processes; tcp://HOST:PORT (e.g. tcp://HOST:8786) uses that "
                        "scheduler's cluster; anything else is refused")
    parser.add_argument("--retry-errors", action="store_true",
                        help="fly again the runs whose row is an error (a crash is a result "
                        "and is kept)")
    parser.add_argument("--flush-s", type=float, default=None, metavar="SECONDS",
                        help="how often finished rows are journaled to TABLE.parts/ (default "
                        "2; 0 writes each row as it arrives): a sweep killed outright loses at "
                        "most this much work")
    parser.add_argument("--dry-run", action="store_true",
                        help="list the runs (and which are already in the table), fly nothing")
    parser.add_argument("--metric", action="append", default=None, metavar="KEY",
                        help="with 'report': a metric to draw (repeatable; default the mean "
                        "position error and any disturbance recovery time)")


def run(args: argparse.Namespace) -> int:
    if args.campaign == "report":
        return _report(args)
    if args.table is not None:
        from groundstation.cli import UserError
        raise UserError(f"sweep takes one campaign; got an extra argument {args.table!r} "
                        "(for plots: fasthex sweep report TABLE)")
    return _sweep(args)


def _sweep(args: argparse.Namespace) -> int:
    from config import find_config
    from groundstation.campaign import load_campaign
    from groundstation.cli import UserError, version
    from groundstation.signals import stop_signals_blocked, stop_signals_interrupt
    from groundstation.sweep import (
        FLUSH_INTERVAL_S,
        Progress,
        ResultsTable,
        Runner,
        check_scheduler,
        local_workers,
        make_runner,
        sweep,
    )

    if args.workers is not None and args.workers < 1:
        raise UserError(f"--workers must be at least 1, got {args.workers}")
    if args.scheduler is not None:
        try:
            check_scheduler(args.scheduler)
        except ValueError as exc:
            raise UserError(str(exc)) from None
    if args.flush_s is not None and not (0.0 <= args.flush_s <= 3600.0):
        raise UserError(f"--flush-s must be between 0 and 3600 seconds, got {args.flush_s}")
    campaign = load_campaign(find_config("campaigns", args.campaign))
    runs = list(campaign.runs())
    table_path = Path(args.out) if args.out else Path(f"{campaign.name}.parquet")
    meta = {"campaign": campaign.name, "campaign_sha256": campaign.text_sha256,
            "parameters": campaign.parameter_names(), "fasthex_version": version()}
    try:
        table = ResultsTable(table_path, meta, flush_interval_s=(
            FLUSH_INTERVAL_S if args.flush_s is None else args.flush_s),
            set_aside=not args.dry_run)
    except Exception as exc:  # not a Parquet file
        raise UserError(f"{table_path}: cannot read the results table ({exc})") from None
    for part, why in table.unreadable:  # cut short by a crash: its runs fly again
        print(f"note: an unreadable part of the results table {part} ({why}); "
              + ("a sweep sets it aside and flies its runs again" if args.dry_run
                 else "set aside, its runs fly again"), file=sys.stderr)
    done = table.done_ids(retry_errors=args.retry_errors)
    ids = {r.run_id for r in runs}
    foreign = sum(1 for rid in table.rows if rid not in ids)
    todo = sum(1 for r in runs if r.run_id not in done)
    bad = sum(1 for r in runs if r.config_error is not None)
    print(f"campaign {campaign.name}: {len(runs)} runs ({len(campaign.spec.scenarios)} "
          f"scenario(s) x {len(campaign.points())} point(s) x {len(campaign.spec.seeds)} "
          f"seed(s)); {len(runs) - todo} already in {table_path}, {todo} to fly"
          + (f"; {bad} point(s) with a config error (recorded, not flown)" if bad else ""),
          file=sys.stderr)
    if foreign:
        print(f"note: {foreign} row(s) of {table_path} are not runs of this campaign (kept)",
              file=sys.stderr)
    if args.dry_run:
        for r in runs:
            state = "done" if r.run_id in done else "todo"
            point = ", ".join(f"{k}={v}" for k, v in r.params.items())
            print(f"{r.run_index:5d} {r.run_id} {state} scenario={r.scenario_label or 'none'} "
                  f"seed={r.seed} {point}" + (f"  CONFIG ERROR: {r.config_error}"
                                              if r.config_error else ""))
        return 0
    workers, capped = args.workers, ""
    if args.scheduler in (None, "local"):  # a scheduler's cluster has the workers it has
        workers, capped = local_workers(args.workers, todo)
    runner: Runner | None = None
    with stop_signals_interrupt():  # SIGTERM, SIGHUP: as Ctrl-C; a repeat is the same stop
        try:
            with stop_signals_blocked():  # worker processes start with the stop signals held
                # in this process only if asked for (--workers 1, or one core), not capped to it
                runner = make_runner(workers, args.scheduler, in_process=(
                    (args.workers or os.cpu_count() or 1) == 1))
            print(f"running on {runner.description}{capped}", file=sys.stderr)
            progress = Progress(todo, label=campaign.name)
            flown, skipped = sweep(runs, table, runner, retry_errors=args.retry_errors,
                                   progress=progress)
        except KeyboardInterrupt:
            have = len(table.rows)
            with contextlib.suppress(OSError):  # SIGHUP: the terminal is gone
                print(f"fasthex: sweep interrupted: "
                      f"{sum(1 for r in runs if r.run_id in table.rows)} of {len(runs)} runs are "
                      f"in {table_path} ({have} rows); run the same command again to fly the rest",
                      file=sys.stderr)
            return 130
        except OSError as exc:
            raise UserError(f"sweep: {exc}") from None
        finally:
            if runner is not None:  # sweep() closed it, unless the interrupt came before it ran
                runner.close()
    verdicts: dict[str, int] = {}
    for r in runs:
        row = table.rows.get(r.run_id)
        if row is not None:
            v = str(row.get("verdict"))
            verdicts[v] = verdicts.get(v, 0) + 1
    counts = ", ".join(f"{n} {v}" for v, n in sorted(verdicts.items()))
    print(f"{table_path}: {len(runs)} runs ({counts}); flew {flown} now, {skipped} were "
          "already there")
    return 0


def _report(args: argparse.Namespace) -> int:
    from groundstation.cli import UserError

    if args.table is None:
        raise UserError("sweep report needs the results table: fasthex sweep report TABLE")
    try:
        from groundstation.sweep_report import ReportError, write_report
    except ImportError as exc:  # pragma: no cover
        raise UserError(f"sweep report is not available: {exc}") from None
    table = Path(args.table)
    out = Path(args.out) if args.out else table.with_name(table.stem + "-report")
    try:
        files = write_report(table, out, args.metric)
    except ReportError as exc:
        raise UserError(f"sweep report: {exc}") from None
    for f in files:
        print(f)
    return 0

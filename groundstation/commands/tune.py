"""``fasthex tune CAMPAIGN``: search controller gains with Optuna over a campaign's flights,
check the best on seeds never tuned on, and write a vehicle file with them and a report.

The campaign's ``tune:`` section names the gains, their ranges, the constraints and the
held-out check (:mod:`groundstation.tune`). Trials fly on the same executors as ``fasthex
sweep`` (``--workers``, ``--scheduler``).

Exit codes: 0 when the tuned gains pass every held-out check, 1 when they do not (the files
are written all the same, the report says which check failed), 2 for a problem with the
campaign or the options, 130 when interrupted.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

NAME = "tune"
HELP = "tune controller gains with Optuna over a campaign's flights (writes a vehicle file)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("campaign", help="campaign name or YAML file with a tune: section")
    parser.add_argument("--trials", type=int, default=None, metavar="N",
                        help="trials (default: the campaign's tune.trials)")
    parser.add_argument("--workers", type=int, default=None, metavar="N",
                        help="worker processes (default: every core)")
    parser.add_argument("--scheduler", default=None, metavar="URI",
                        help="Dask: 'local' (LocalCluster) or tcp://HOST:PORT (e.g. "
                        "tcp://HOST:8786); anything else is refused")
    parser.add_argument("--out", default=None, metavar="FILE",
                        help="tuned vehicle file (default VEHICLE-CAMPAIGN.yaml); the report "
                        "and the trials table are written beside it")
    parser.add_argument("--storage", default=None, metavar="URL",
                        help="Optuna storage (e.g. sqlite:///tune.db) to keep the study")


def run(args: argparse.Namespace) -> int:
    import os

    import pyarrow.parquet as pq
    import yaml

    from config import find_config
    from groundstation.campaign import load_campaign
    from groundstation.cli import UserError
    from groundstation.signals import stop_signals_blocked, stop_signals_interrupt
    from groundstation.sweep import (
        MAX_WORKERS_PER_CPU,
        check_scheduler,
        make_runner,
        rows_to_table,
    )
    from groundstation.tune import (
        best_trial,
        report_markdown,
        search,
        trials_table,
        tuned_vehicle_text,
        validate,
    )

    if args.trials is not None and args.trials < 1:
        raise UserError(f"--trials must be at least 1, got {args.trials}")
    if args.workers is not None and args.workers < 1:
        raise UserError(f"--workers must be at least 1, got {args.workers}")
    if args.scheduler is not None:
        try:
            check_scheduler(args.scheduler)
        except ValueError as exc:
            raise UserError(str(exc)) from None
    campaign = load_campaign(find_config("campaigns", args.campaign))
    if campaign.spec.tune is None:
        raise UserError(f"{campaign.path}: no tune: section; fasthex tune needs the gains to "
                        "search (see the shipped campaign gust-recovery)")
    vehicle_name = yaml.safe_load(campaign.base_texts["vehicle"][0]).get("name", "vehicle")
    out = Path(args.out) if args.out else Path(f"{vehicle_name}-{campaign.name}.yaml")
    workers = args.workers if args.workers is not None else (os.cpu_count() or 1)
    capped = ""
    cpus = os.cpu_count() or 1
    if args.scheduler in (None, "local") and workers > MAX_WORKERS_PER_CPU * cpus:
        # as sweep caps its local pool (a trial flies a whole campaign, so runs are never few)
        capped = (f" (--workers {workers} capped at {MAX_WORKERS_PER_CPU} per core on {cpus} "
                  "core(s))")
        workers = MAX_WORKERS_PER_CPU * cpus
    with stop_signals_blocked():
        runner = make_runner(workers, args.scheduler)
    print(f"tuning {', '.join(p.name for p in campaign.spec.tune.parameters)} on "
          f"{campaign.name}: {campaign.n_runs()} runs per trial, on {runner.description}"
          f"{capped}", file=sys.stderr)
    with stop_signals_interrupt():  # SIGTERM, SIGHUP: as Ctrl-C; a repeat is the same stop
        try:
            try:
                results, baseline = search(campaign, runner, workers=workers, trials=args.trials,
                                           storage=args.storage,
                                           log=lambda line: print(line, file=sys.stderr))
            except ValueError as exc:
                raise UserError(f"{campaign.path}: {exc}") from None
            best = best_trial(results)
            if best is None:
                print("fasthex: tune: no feasible trial; nothing written (the report of the "
                      "trials is on stderr above)", file=sys.stderr)
                return 1
            print(f"best: trial {best.number}, objective {best.objective:.3f}; flying the held-out "
                  "check", file=sys.stderr)
            # the gains as the vehicle file will hold them (4 decimals) are the ones checked
            gains = {k: round(v, 4) for k, v in best.gains.items()}
            checks, _ = validate(campaign, runner, baseline, gains)
        except KeyboardInterrupt:
            print("\nfasthex: tune interrupted; nothing written", file=sys.stderr)
            return 130
        finally:
            runner.close()
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(tuned_vehicle_text(campaign, gains, trials=len(results),
                                      objective=best.objective))
    report = out.with_name(out.stem + "-report.md")
    text = report_markdown(campaign, results, best, baseline, checks)
    report.write_text(text)
    trials = out.with_name(out.stem + "-trials.parquet")
    pq.write_table(rows_to_table(trials_table(results), {"campaign": campaign.name}), trials)
    print(text)
    print(f"tuned vehicle: {out}\nreport: {report}\ntrials: {trials}")
    failed = [c.name for c in checks if not c.passed]
    if failed:
        print("fasthex: tune: the tuned gains fail the held-out check: " + "; ".join(failed),
              file=sys.stderr)
        return 1
    return 0

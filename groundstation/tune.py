"""``fasthex tune``: controller gains searched with Optuna over a campaign's runs.

The campaign's ``tune:`` section (:class:`groundstation.campaign.TuneSpec`) names the gains and
their ranges. Each trial sets them on every run of the campaign (its scenarios x points x
seeds) and flies those runs on the sweep's executor (:mod:`groundstation.sweep`: local
processes or Dask), so trials run in parallel batches of one per worker.

**Objective** (lower is better): the mean over the trial's runs of the first disturbance's
recovery time (``dist0_recovery_s``, back under 10 mm; a run that never comes back counts
``unrecovered_penalty_s``) plus ``calm_error_weight_s_per_mm`` times the mean position error
of the calm hover before it (``calm_pos_err_mean_mm``).

**Constraints** (Optuna's constrained TPE: a trial is feasible when every value is <= 0):

1. every run flies (no crash, no error);
2. no rotor at a spin limit for more than ``max_saturated_frac`` of the measured ticks;
3. the linearised position loop's least damped pole has a damping ratio of at least
   ``min_pos_damping`` (:mod:`controller.loop_margins`);
4. the attitude loop at least ``min_separation`` times faster than the position loop;
5. the calm hover's mean error no worse than the shipped gains' (trial 0 flies those).

A trial that breaks 3 or 4 is not flown (its margins are known before any flight).

**After the search** the best feasible gains and the shipped ones fly the held-out check: the
campaign's runs with ``validation_seeds`` (seeds never tuned on) and the
``validation_mission`` (default Exp. 1) with the same seeds. The report compares them against
the targets: every held-out run back under 10 mm within ``recovery_target_s``, the validation
mission's mean position error (mean over the seeds) no worse, no saturation. Written: the
vehicle file with the tuned gains, the report (Markdown) and every trial (Parquet).
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import yaml

from groundstation.campaign import Campaign, RunSpec, TuneSpec
from groundstation.sweep import Runner

#: objective of a trial that could not be flown (its margins fail): above any real one
INFEASIBLE_OBJECTIVE = 1e3


@dataclass
class TrialResult:
    number: int
    gains: dict[str, float]
    objective: float
    constraints: list[float]
    rows: list[dict[str, Any]] = field(default_factory=list)
    margins: dict[str, float] = field(default_factory=dict)
    flown: bool = True

    @property
    def feasible(self) -> bool:
        return all(c <= 0.0 for c in self.constraints)


def overrides(tune: TuneSpec, gains: dict[str, float]) -> dict[str, Any]:
    """Dotted path -> value of a trial's gains."""
    out: dict[str, Any] = {}
    for p in tune.parameters:
        for path in p.paths:
            out[path] = gains[p.name]
    return out


def shipped_gains(campaign: Campaign, tune: TuneSpec) -> dict[str, float]:
    """The base vehicle's value of each searched gain (the first item of a list, which a
    broadcast path sets whole)."""
    data = yaml.safe_load(campaign.base_texts["vehicle"][0])
    out = {}
    for p in tune.parameters:
        node: Any = data
        for key in p.paths[0].split(".")[1:]:
            node = node[int(key)] if isinstance(node, list) else node[key]
        while isinstance(node, list):
            node = node[0]
        out[p.name] = float(node)
    return out


def trial_margins(campaign: Campaign, tune: TuneSpec, gains: dict[str, float]
                  ) -> dict[str, float] | str:
    """The linearised margins of the vehicle with ``gains``; the config error text if the
    vehicle file refuses them."""
    from config.schema import ConfigError, load_config_text
    from controller.loop_margins import loop_margins
    from controller.params import VEHICLE_SCHEMA, VehicleParams
    from groundstation.campaign import apply_overrides

    items = [(path.split(".")[1:], value, path)
             for path, value in overrides(tune, gains).items()]
    try:
        text = apply_overrides(campaign.base_texts["vehicle"][0], items)
        vehicle = load_config_text(text, VehicleParams, schema=VEHICLE_SCHEMA,
                                   file_label=str(campaign.base_texts["vehicle"][1]))
    except (ConfigError, ValueError) as exc:
        return str(exc)
    m = loop_margins(vehicle)
    return {"pos_min_damping": m.pos_min_damping, "att_min_damping": m.att_min_damping,
            "separation": m.separation, "routh_ratio": m.routh_ratio,
            "slowest_pole_rad_s": m.slowest_pole_rad_s}


def score(tune: TuneSpec, rows: list[dict[str, Any]], margins: dict[str, float],
          calm_reference_mm: float | None) -> tuple[float, list[float]]:
    """Objective and constraint values of a flown trial (module docstring)."""
    not_ok = sum(1 for r in rows if r.get("verdict") != "ok")
    recov = []
    calm = []
    sat = 0.0
    for r in rows:
        v = _num(r.get("dist0_recovery_s"))
        recov.append(v if math.isfinite(v) else tune.unrecovered_penalty_s)
        c = _num(r.get("calm_pos_err_mean_mm"))
        if math.isfinite(c):
            calm.append(c)
        s = r.get("all_spin_saturated_frac")
        sat = max(sat, 1.0 if s is None or math.isnan(float(s)) else float(s))
    calm_mm = sum(calm) / len(calm) if calm else math.inf
    objective = (sum(recov) / len(recov) if recov else tune.unrecovered_penalty_s) \
        + tune.calm_error_weight_s_per_mm * (calm_mm if math.isfinite(calm_mm) else 100.0)
    if not_ok or not rows:
        objective = INFEASIBLE_OBJECTIVE
    constraints = [
        float(not_ok) if rows else 1.0,
        sat - tune.max_saturated_frac,
        tune.min_pos_damping - margins["pos_min_damping"],
        tune.min_separation - margins["separation"],
        0.0 if calm_reference_mm is None else calm_mm - calm_reference_mm,
    ]
    return objective, constraints


def _gains_text(gains: dict[str, float]) -> str:
    return ", ".join(f"{k}={v:.4g}" for k, v in gains.items())


def _constrain(trial: Any, values: list[float]) -> None:
    """Optuna's constrained TPE reads these (feasible: every value <= 0)."""
    for name, value in zip(CONSTRAINT_NAMES, values, strict=True):
        trial.set_constraint(name, float(value))
    trial.set_user_attr("constraints", [float(v) for v in values])


def _suggest(trial: Any, tune: TuneSpec) -> dict[str, float]:
    return {p.name: float(trial.suggest_float(p.name, p.low, p.high, log=p.log))
            for p in tune.parameters}


def _key(campaign: Campaign, number: int) -> str:
    return f"{campaign.name}-trial{number}"


def search(campaign: Campaign, runner: Runner, *, workers: int,
           trials: int | None = None, storage: str | None = None,
           log: Callable[[str], None] = print) -> tuple[list[TrialResult], dict[str, float]]:
    """Run the Optuna study; every trial's result and the shipped gains."""
    import optuna

    tune = campaign.spec.tune
    assert tune is not None
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    sampler = optuna.samplers.TPESampler(
        seed=tune.sampler_seed, n_startup_trials=min(10, max(1, (trials or tune.trials) // 4)))
    study = optuna.create_study(direction="minimize", sampler=sampler, storage=storage,
                                study_name=_key(campaign, 0) if storage else None,
                                load_if_exists=storage is not None)
    baseline = shipped_gains(campaign, tune)
    for p in tune.parameters:
        if not p.low <= baseline[p.name] <= p.high:
            raise ValueError(f"tune.parameters {p.name}: the shipped value {baseline[p.name]:g}"
                             f" is outside its range {p.low:g} .. {p.high:g}")
    if not study.trials:
        study.enqueue_trial(baseline)  # trial 0: the reference the calm error is held to
    n_trials = trials if trials is not None else tune.trials
    results: list[TrialResult] = []
    calm_reference: float | None = None
    batch = max(1, workers)
    t0 = time.monotonic()
    while len(results) < n_trials:
        size = 1 if not results else min(batch, n_trials - len(results))
        asked = [study.ask() for _ in range(size)]
        pending: dict[int, tuple[Any, dict[str, float], dict[str, float]]] = {}
        specs: list[RunSpec] = []
        owner: dict[str, list[int]] = {}  # run id -> trials (equal gains fly once)
        for trial in asked:
            gains = _suggest(trial, tune)
            margins = trial_margins(campaign, tune, gains)
            if isinstance(margins, str):  # the vehicle file refuses these gains
                res = TrialResult(trial.number, gains, INFEASIBLE_OBJECTIVE,
                                  [1.0, 0.0, 1.0, 1.0, 0.0], flown=False)
                res.margins = {}
                _constrain(trial, res.constraints)
                trial.set_user_attr("note", margins)
                study.tell(trial, res.objective)
                results.append(res)
                log(f"trial {trial.number:3d}: {_gains_text(gains)} -> not flown: {margins}")
                continue
            if (margins["pos_min_damping"] < tune.min_pos_damping
                    or margins["separation"] < tune.min_separation):
                res = TrialResult(trial.number, gains, INFEASIBLE_OBJECTIVE,
                                  [0.0, 0.0, tune.min_pos_damping - margins["pos_min_damping"],
                                   tune.min_separation - margins["separation"], 0.0],
                                  margins=margins, flown=False)
                _constrain(trial, res.constraints)
                study.tell(trial, res.objective)
                results.append(res)
                log(f"trial {trial.number:3d}: {_gains_text(gains)} -> not flown: linearised "
                    f"position damping {margins['pos_min_damping']:.2f} (at least "
                    f"{tune.min_pos_damping:g}), loop separation {margins['separation']:.2f} "
                    f"(at least {tune.min_separation:g})")
                continue
            pending[trial.number] = (trial, gains, margins)
            for spec in campaign.runs(overrides(tune, gains)):
                if spec.run_id not in owner:
                    specs.append(spec)
                owner.setdefault(spec.run_id, []).append(trial.number)
        rows: dict[int, list[dict[str, Any]]] = {n: [] for n in pending}
        got = 0
        for row in runner.run(specs):
            got += 1
            for number in owner[row["run_id"]]:
                rows[number].append(row)
        if got != len(specs):
            raise RuntimeError(f"the executor returned {got} rows for {len(specs)} runs")
        for number, (trial, gains, margins) in sorted(pending.items()):
            objective, constraints = score(tune, rows[number], margins, calm_reference)
            if number == 0 and calm_reference is None:
                calm_reference = _calm(rows[number])
                constraints[4] = 0.0
            _constrain(trial, constraints)
            study.tell(trial, objective)
            res = TrialResult(number, gains, objective, constraints, rows[number], margins)
            results.append(res)
            log(f"trial {number:3d}: {_gains_text(gains)}"
                + f" -> objective {objective:.3f}"
                + ("" if res.feasible else " (infeasible: "
                   + ", ".join(n for n, c in zip(CONSTRAINT_NAMES, constraints, strict=True)
                               if c > 0) + ")")
                + f" [{len(results)}/{n_trials}, {time.monotonic() - t0:.0f} s]")
    return results, baseline


CONSTRAINT_NAMES = ("flights fail", "saturation", "position damping", "loop separation",
                    "calm error")


def _calm(rows: list[dict[str, Any]]) -> float:
    vals = [float(r["calm_pos_err_mean_mm"]) for r in rows
            if r.get("calm_pos_err_mean_mm") is not None
            and not math.isnan(float(r["calm_pos_err_mean_mm"]))]
    return sum(vals) / len(vals) if vals else math.inf


def best_trial(results: list[TrialResult]) -> TrialResult | None:
    feasible = [r for r in results if r.feasible and r.flown]
    return min(feasible, key=lambda r: r.objective) if feasible else None


# -- the held-out check ------------------------------------------------------------------------

@dataclass
class Check:
    name: str
    shipped: str
    tuned: str
    target: str
    passed: bool


def validate(campaign: Campaign, runner: Runner, baseline: dict[str, float],
             tuned: dict[str, float]) -> tuple[list[Check], dict[str, list[dict[str, Any]]]]:
    """Fly the shipped and the tuned gains on the held-out seeds (module docstring)."""
    tune = campaign.spec.tune
    assert tune is not None
    held = campaign.derived(name=f"{campaign.name}-check", seeds=tune.validation_seeds)
    flights: dict[str, list[dict[str, Any]]] = {}
    specs: list[RunSpec] = []
    owner: dict[str, list[str]] = {}  # run id -> sets (the shipped and tuned gains may agree)
    sets: list[tuple[str, Campaign, dict[str, float]]] = [
        ("shipped", held, baseline), ("tuned", held, tuned)]
    if tune.validation_mission:
        mission = held.derived(name=f"{campaign.name}-mission-check",
                               mission=tune.validation_mission, scenarios=["none"],
                               parameters=())
        sets += [("shipped-mission", mission, baseline), ("tuned-mission", mission, tuned)]
    for label, camp, gains in sets:
        flights[label] = []
        for spec in camp.runs(overrides(tune, gains)):
            if spec.run_id not in owner:
                specs.append(spec)
            owner.setdefault(spec.run_id, []).append(label)
    got = 0
    for row in runner.run(specs):
        got += 1
        for label in owner[row["run_id"]]:
            flights[label].append(row)
    if got != len(specs):
        raise RuntimeError("the executor lost runs of the held-out check")
    for rows in flights.values():
        rows.sort(key=lambda r: r["run_index"])
    checks: list[Check] = []
    target = tune.recovery_target_s
    groups: dict[str, list[str]] = {}
    for row in flights["tuned"]:
        groups.setdefault(_point_label(row, campaign), []).append(row["run_id"])
    for label in groups:
        ship = [r for r in flights["shipped"] if _point_label(r, campaign) == label]
        tun = [r for r in flights["tuned"] if _point_label(r, campaign) == label]
        checks.append(Check(
            f"recovery {label} [s], seeds {', '.join(str(r['seed']) for r in tun)}",
            _list(ship, "dist0_recovery_s"), _list(tun, "dist0_recovery_s"),
            f"< {target:g} each",
            all(_num(r.get("dist0_recovery_s")) < target for r in tun)))
    sat_t = max((_num(r.get("all_spin_saturated_frac"), 1.0) for rows in
                 (flights["tuned"], flights.get("tuned-mission", [])) for r in rows),
                default=0.0)
    sat_s = max((_num(r.get("all_spin_saturated_frac"), 1.0) for rows in
                 (flights["shipped"], flights.get("shipped-mission", [])) for r in rows),
                default=0.0)
    checks.append(Check("largest saturated fraction of ticks", f"{sat_s:.4f}", f"{sat_t:.4f}",
                        f"<= {tune.max_saturated_frac:g}", sat_t <= tune.max_saturated_frac))
    not_ok = [r for rows in flights.values() for r in rows if r.get("verdict") != "ok"]
    checks.append(Check("flights not ok", str(sum(1 for rows in ("shipped", "shipped-mission")
                                                   for r in flights.get(rows, [])
                                                   if r.get("verdict") != "ok")),
                        str(sum(1 for rows in ("tuned", "tuned-mission")
                                for r in flights.get(rows, []) if r.get("verdict") != "ok")),
                        "0", not any(label.startswith("tuned") for r in not_ok
                                     for label in owner.get(r["run_id"], []))))
    if tune.validation_mission:
        ship_m = flights["shipped-mission"]
        tun_m = flights["tuned-mission"]
        mean_s = _mean(ship_m, "all_pos_err_mean_mm")
        mean_t = _mean(tun_m, "all_pos_err_mean_mm")
        checks.append(Check(
            f"{tune.validation_mission} mean position error [mm], mean of seeds "
            f"({_list(ship_m, 'all_pos_err_mean_mm')} / {_list(tun_m, 'all_pos_err_mean_mm')})",
            f"{mean_s:.2f}", f"{mean_t:.2f}", "no worse", mean_t <= mean_s))
    return checks, flights


def _point_label(row: dict[str, Any], campaign: Campaign) -> str:
    parts = [f"{k.split('.')[-1]}={row.get(k)}" for k in campaign.parameter_names()]
    scen = row.get("scenario")
    return " ".join(([str(scen)] if scen else []) + parts) or "base"


def _num(v: Any, default: float = math.inf) -> float:
    if v is None:
        return default
    f = float(v)
    return default if math.isnan(f) else f


def _list(rows: list[dict[str, Any]], key: str) -> str:
    return ", ".join("never" if _num(r.get(key)) == math.inf else f"{_num(r.get(key)):.2f}"
                     for r in rows)


def _mean(rows: list[dict[str, Any]], key: str) -> float:
    vals = [_num(r.get(key)) for r in rows]
    return sum(vals) / len(vals) if vals else math.nan


# -- outputs -----------------------------------------------------------------------------------

def tuned_vehicle_text(campaign: Campaign, tuned: dict[str, float], *, trials: int,
                       objective: float) -> str:
    """The base vehicle file with the tuned gains, renamed, with a header saying so."""
    from groundstation.campaign import apply_overrides

    tune = campaign.spec.tune
    assert tune is not None
    text, file = campaign.base_texts["vehicle"]
    base = yaml.safe_load(text)
    name = f"{base.get('name', 'vehicle')}-{campaign.name}"
    items: list[tuple[list[str], Any, str]] = [
        (path.split(".")[1:], round(value, 4), path)
        for path, value in overrides(tune, tuned).items()]
    items.append((["name"], name, "vehicle.name"))
    items.append((["description"], f"{base.get('description', '')} (gains tuned by fasthex tune "
                  f"{campaign.name})".strip(), "vehicle.description"))
    body = apply_overrides(text, items)
    header = (f"# {file.name} with the controller gains tuned by `fasthex tune "
              f"{campaign.path.name}`\n# ({trials} trials, best objective {objective:.3f}):\n"
              + "".join(f"#   {k} = {v:.4g}\n" for k, v in tuned.items())
              + "# Everything else is the base file's. Search, constraints and the held-out\n"
              "# check: the tune report.\n")
    return header + body


def report_markdown(campaign: Campaign, results: list[TrialResult], best: TrialResult | None,
                    baseline: dict[str, float], checks: list[Check]) -> str:
    tune = campaign.spec.tune
    assert tune is not None
    lines = [f"# fasthex tune {campaign.name}", "",
             f"{len(results)} trials, {sum(1 for r in results if r.flown)} flown, "
             f"{sum(1 for r in results if r.feasible and r.flown)} feasible; each trial flies "
             f"{campaign.n_runs()} runs (scenarios {', '.join(campaign.spec.scenarios)}; seeds "
             f"{', '.join(map(str, campaign.spec.seeds))}).", "",
             "| gain | range | shipped | tuned |", "|---|---|---|---|"]
    for p in tune.parameters:
        tuned = "-" if best is None else f"{best.gains[p.name]:.4g}"
        lines.append(f"| {p.name} ({', '.join(p.paths)}) | {p.low:g} .. {p.high:g}"
                     f"{' (log)' if p.log else ''} | {baseline[p.name]:.4g} | {tuned} |")
    if best is not None:
        shipped = next((r for r in results if r.number == 0), None)
        lines += ["", f"Objective (tuning seeds): shipped "
                  f"{shipped.objective:.3f}" if shipped else "", f"tuned {best.objective:.3f} "
                  f"(trial {best.number}); linearised margins of the tuned gains: "
                  + ", ".join(f"{k} {v:.3g}" for k, v in best.margins.items())]
    lines += ["", f"## Held-out check (seeds {', '.join(map(str, tune.validation_seeds))}, "
              "not used in tuning)", "", "| check | shipped | tuned | target | |",
              "|---|---|---|---|---|"]
    for c in checks:
        lines.append(f"| {c.name} | {c.shipped} | {c.tuned} | {c.target} | "
                     f"{'pass' if c.passed else 'FAIL'} |")
    return "\n".join(lines) + "\n"


def trials_table(results: list[TrialResult]) -> list[dict[str, Any]]:
    rows = []
    for r in results:
        row: dict[str, Any] = {"trial": r.number, "objective": r.objective,
                               "feasible": r.feasible, "flown": r.flown}
        row.update({f"gain.{k}": v for k, v in r.gains.items()})
        row.update({f"constraint.{n}": c for n, c in zip(CONSTRAINT_NAMES, r.constraints,
                                                          strict=True)})
        row.update({f"margin.{k}": v for k, v in r.margins.items()})
        rec = [_num(x.get("dist0_recovery_s")) for x in r.rows]
        row["recovery_mean_s"] = sum(rec) / len(rec) if rec else math.nan
        row["calm_pos_err_mean_mm"] = _calm(r.rows) if r.rows else math.nan
        row["runs"] = json.dumps([x["run_id"] for x in r.rows])
        rows.append(row)
    return rows

"""Campaign files (``schema: fasthex.campaign``): many simulated flights from one description.

A campaign names a mission, a vehicle, a disturbance preset and the scenarios to fly, the
parameters to vary and the flight seeds. Its runs are every scenario x every parameter point x
every seed; each run is one in-process flight (:func:`groundstation.simulation.simulate_flight`)
and gives one row of the results table (:mod:`groundstation.sweep`).

Parameters are dotted paths into the configuration a run is built from:

- ``vehicle.<key>...``, ``mission.<key>...``, ``preset.<key>...``, ``scenario.<key>...``: a key of
  that YAML file, list items by their index (``scenario.disturbances.0.force_n.1``,
  ``vehicle.controller.kp_pos.2``). A number set on a list of numbers sets every item
  (``vehicle.controller.ki_pos: 30`` is ``[30, 30, 30]``). Keys missing along the path are
  created as mappings (``scenario.plant.payload_kg`` on a scenario without ``plant``).
- ``run.<key>``: the flight itself: ``tilt_deg`` (a constant tilt instead of the mission's alpha
  profile), ``duration_s``, ``estimator`` (``truth`` or ``ukf``), ``max_touchdown_speed_m_s``.

Each modified file is validated again, exactly as if it had been written that way: a point
outside a field's range is a run whose row carries the config error, not a crashed campaign.
What no point could fly is refused at load instead, at the parameter's line: a path that is no
key of its file's schema (nor an item of its list), a value of the wrong type.

Values: ``values: [...]`` (a list, any YAML values) or ``range: [lo, hi]`` (numbers) with
``num`` points for a grid, ``log: true`` for log spacing and ``integer: true`` to round. A grid
flies each point once: a value listed twice, or a ``num`` larger than the distinct integers
its rounded range holds, is refused at load.
Sampling (``sampling``): ``grid`` (the Cartesian product of every parameter's values),
``random`` (``samples`` points, each parameter drawn uniformly, or from its ``values``) or
``lhs`` (a Latin hypercube of ``samples`` points: each parameter's range cut in ``samples``
strata, each stratum used once). Random and Latin-hypercube points come from
``sampling_seed``; the points and so the run identities are the same on every machine.

A run's identity (``run_id``) is a hash of what it flies (scenario, parameter values, seed),
so that a rerun of the same campaign finds the rows it already has.
"""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import itertools
import json
import math
import traceback
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import yaml

from config import find_config
from config.schema import (
    ConfigError,
    ConfigValueError,
    field_type,
    line_of,
    load_config,
    load_config_text,
    spec,
    type_error,
)

CAMPAIGN_SCHEMA = "fasthex.campaign"
NAMESPACES = ("vehicle", "mission", "preset", "scenario", "run")
#: the type of each ``run.<key>`` (checked at load; a value outside its range is a run's error)
RUN_TYPES: dict[str, Any] = {"tilt_deg": float, "duration_s": float,
                             "estimator": Literal["truth", "ukf"],
                             "max_touchdown_speed_m_s": float}
RUN_KEYS = tuple(RUN_TYPES)
#: the scenario entry that means "no scenario" (the vehicle as the controller knows it)
NO_SCENARIO = "none"
#: runs a campaign may expand to: beyond this a typo in ``num`` is more likely than intent
MAX_RUNS = 200_000


@dataclass(frozen=True, kw_only=True)
class Parameter:
    """One varied parameter (module docstring)."""

    path: str = spec(doc="dotted config path, e.g. vehicle.controller.ki_pos")
    values: tuple[Any, ...] | None = spec(None, doc="the values to fly")
    range: tuple[float, float] | None = spec(None, doc="[lo, hi]")
    num: int | None = spec(None, ge=1, le=10_000, doc="grid points over range")
    log: bool = spec(False, doc="log spacing / log-uniform draws over range")
    integer: bool = spec(False, doc="round values to integers")

    def __post_init__(self) -> None:
        parts = self.path.split(".")
        if len(parts) < 2 or parts[0] not in NAMESPACES or not all(parts):
            from config.schema import ConfigValueError
            raise ConfigValueError("path", "expected NAMESPACE.KEY[.KEY...] with NAMESPACE one "
                                   f"of {', '.join(NAMESPACES)}, got {self.path!r}")
        if parts[0] == "run" and (len(parts) != 2 or parts[1] not in RUN_KEYS):
            from config.schema import ConfigValueError
            raise ConfigValueError("path", f"run takes one of {', '.join(RUN_KEYS)}, got "
                                   f"{self.path!r}")
        if (self.values is None) == (self.range is None):
            from config.schema import ConfigValueError
            raise ConfigValueError("values", "expected either values: [...] or range: [lo, hi]")
        if self.values is not None and not self.values:
            from config.schema import ConfigValueError
            raise ConfigValueError("values", "expected at least one value")
        if self.range is not None:
            lo, hi = self.range
            from config.schema import ConfigValueError
            if not lo <= hi:
                raise ConfigValueError("range", f"expected lo <= hi, got [{lo:g}, {hi:g}]")
            if not math.isfinite(hi - lo):  # its points would be inf and NaN
                raise ConfigValueError("range", f"expected hi - lo to be a finite number, got "
                                       f"[{lo:g}, {hi:g}]")
            if self.log and lo <= 0.0:
                raise ConfigValueError("range", "a log range needs lo > 0")
            if self.integer and self.num is not None:  # a grid: its rounded points distinct
                distinct = len(set(_grid_values(self)))
                if distinct < self.num:
                    raise ConfigValueError("num", f"num {self.num} integer values in "
                                           f"[{lo:g}, {hi:g}] repeat: at most {distinct} "
                                           "distinct")


@dataclass(frozen=True, kw_only=True)
class TuneParameter:
    """One gain ``fasthex tune`` searches: a value in [low, high] set on every path."""

    name: str = spec(doc="label in the report, e.g. kp_pos")
    paths: tuple[str, ...] = spec(doc="vehicle paths set to the value, e.g. "
                                  "vehicle.controller.kp_pos (every axis)")
    low: float = spec(gt=0.0)
    high: float = spec(gt=0.0)
    log: bool = spec(False, doc="search on a log scale")

    def __post_init__(self) -> None:
        from config.schema import ConfigValueError
        if not self.low < self.high:
            raise ConfigValueError("high", f"expected low < high, got {self.low:g} .. "
                                   f"{self.high:g}")
        if not self.paths:
            raise ConfigValueError("paths", "expected at least one vehicle path")
        for i, path in enumerate(self.paths):
            if not path.startswith("vehicle.controller."):
                raise ConfigValueError(f"paths[{i}]", "tune searches controller gains: expected "
                                       f"vehicle.controller.KEY[.AXIS], got {path!r}")


@dataclass(frozen=True, kw_only=True)
class TuneSpec:
    """``fasthex tune``'s section of a campaign (:mod:`groundstation.tune`)."""

    parameters: tuple[TuneParameter, ...] = spec(doc="the gains searched")
    trials: int = spec(40, ge=1, le=10_000, doc="Optuna trials")
    sampler_seed: int = spec(0, ge=0, doc="seed of Optuna's TPE sampler")
    unrecovered_penalty_s: float = spec(10.0, gt=0.0,
                                        doc="recovery time counted for a run that never came "
                                        "back under 10 mm")
    calm_error_weight_s_per_mm: float = spec(0.1, ge=0.0,
                                             doc="objective weight of the calm hover's mean "
                                             "position error")
    max_saturated_frac: float = spec(0.0, ge=0.0, le=1.0,
                                     doc="largest fraction of ticks with a rotor at a limit")
    min_pos_damping: float = spec(0.45, ge=0.0, le=1.0,
                                  doc="smallest damping ratio of the linearised position loop")
    min_separation: float = spec(2.5, ge=1.0, doc="attitude over position natural frequency")
    recovery_target_s: float = spec(2.0, gt=0.0, doc="the held-out check's recovery bound")
    validation_seeds: tuple[int, ...] = spec((1001, 1002, 1003), ge=0,
                                             doc="seeds of the held-out check (not tuned on)")
    validation_mission: str | None = spec("exp1-hover-tilt-steps",
                                          doc="mission whose mean position error the tuned "
                                          "gains must not worsen (null: none)")

    def __post_init__(self) -> None:
        from config.schema import ConfigValueError
        if not self.parameters:
            raise ConfigValueError("parameters", "expected at least one gain to search")
        if not self.validation_seeds:
            raise ConfigValueError("validation_seeds", "expected at least one seed")


@dataclass(frozen=True, kw_only=True)
class CampaignSpec:
    """A campaign file (module docstring)."""

    name: str
    description: str = spec("")
    mission: str = spec(doc="mission name or file (relative to the campaign file)")
    vehicle: str = spec("fasthex", doc="vehicle name or file")
    preset: str = spec("paper-calibrated", doc="disturbance preset name or file")
    estimator: Literal["truth", "ukf"] = "truth"
    duration_s: float | None = spec(None, gt=0.0, le=3600.0, doc="cut every flight short")
    scenarios: tuple[str, ...] = spec((NO_SCENARIO,), doc="scenario names or files; none")
    parameters: tuple[Parameter, ...] = spec(())
    sampling: Literal["grid", "random", "lhs"] = "grid"
    samples: int | None = spec(None, ge=1, le=MAX_RUNS, doc="points for random and lhs")
    sampling_seed: int = spec(0, ge=0)
    seeds: tuple[int, ...] = spec((0,), ge=0, doc="flight seeds: every point flies each")
    tune: TuneSpec | None = spec(None, doc="fasthex tune's section (groundstation.tune)")

    def __post_init__(self) -> None:
        from config.schema import ConfigValueError
        if not self.scenarios:
            raise ConfigValueError("scenarios", f"expected at least one ({NO_SCENARIO!r}: none)")
        if not self.seeds:
            raise ConfigValueError("seeds", "expected at least one seed")
        if self.tune is not None:
            for i, seed in enumerate(self.tune.validation_seeds):
                if seed in self.seeds:
                    raise ConfigValueError(f"tune.validation_seeds[{i}]",
                                           f"seed {seed} is also a tuning seed; the check "
                                           "must fly seeds not used in tuning")
        if len(set(self.seeds)) != len(self.seeds):
            raise ConfigValueError("seeds", "a seed is listed twice")
        paths = [p.path for p in self.parameters]
        for i, name in enumerate(paths):
            if name in paths[:i]:
                raise ConfigValueError(f"parameters[{i}].path", f"{name} is varied twice")
        if self.sampling == "grid":
            for i, p in enumerate(self.parameters):
                if p.range is not None and p.num is None:
                    raise ConfigValueError(f"parameters[{i}].num",
                                           "a grid over a range needs num (points)")
                values = p.values or ()
                for j, value in enumerate(values):
                    if value in values[:j]:  # the same point twice: one run_id flown twice
                        raise ConfigValueError(f"parameters[{i}].values",
                                               f"{_short(value)} is listed twice")
            if self.samples is not None:
                raise ConfigValueError("samples", "a grid has its size from the parameters; "
                                       "samples is for random and lhs")
        else:
            if self.samples is None:
                raise ConfigValueError("samples", f"{self.sampling} sampling needs samples "
                                       "(the number of points)")
            for i, p in enumerate(self.parameters):
                if p.num is not None:
                    raise ConfigValueError(f"parameters[{i}].num", "num is for grids; random "
                                           "and lhs draw samples points")
                if self.sampling == "lhs" and p.range is None:
                    raise ConfigValueError(f"parameters[{i}].range",
                                           "a Latin hypercube needs a range per parameter")


@dataclass(frozen=True)
class RunSpec:
    """Everything one run needs, as plain data (it travels to worker processes and hosts):
    the YAML texts of the configs it flies, after the parameter point was applied."""

    run_id: str
    run_index: int
    campaign: str
    seed: int
    scenario_label: str | None
    params: dict[str, Any]
    vehicle_text: str
    mission_text: str
    mission_dir: str
    preset_text: str
    scenario_text: str | None
    labels: dict[str, str] = field(default_factory=dict)
    run_options: dict[str, Any] = field(default_factory=dict)
    #: the config error this point gives (it is recorded as the run's row, never flown)
    config_error: str | None = None


@dataclass(frozen=True)
class Campaign:
    """A loaded campaign: its spec, where it lives and the base configs' texts."""

    spec: CampaignSpec
    path: Path
    text_sha256: str
    base_texts: dict[str, tuple[str, Path]]  # namespace -> (text, file), scenario by label
    lines: dict[str, int]

    @property
    def name(self) -> str:
        return self.spec.name

    def parameter_names(self) -> list[str]:
        return [p.path for p in self.spec.parameters]

    def points(self) -> list[dict[str, Any]]:
        """The parameter points, in campaign order (module docstring)."""
        return sample_points(self.spec)

    def runs(self, extra: dict[str, Any] | None = None) -> Iterator[RunSpec]:
        """Every run: scenarios outermost, then points, then seeds. ``extra`` (dotted path ->
        value) is set on top of every point (``fasthex tune``'s trial gains)."""
        index = 0
        points = self.points()
        for label in self.spec.scenarios:
            for point in points:
                for seed in self.spec.seeds:
                    yield self.build_run(index, label, {**point, **(extra or {})}, seed)
                    index += 1

    def derived(self, *, name: str | None = None, mission: str | None = None,
                scenarios: Sequence[str] | None = None, seeds: Sequence[int] | None = None,
                parameters: Sequence[Parameter] | None = None) -> Campaign:
        """The same campaign with some of its choices replaced (configs found as
        :func:`load_campaign` finds them)."""
        changes: dict[str, Any] = {"tune": None}  # a derived campaign is flown, not tuned
        base = dict(self.base_texts)
        if name is not None:
            changes["name"] = name
        if mission is not None:
            changes["mission"] = mission
            file = _find("missions", mission, self.path.parent, str(self.path), self.lines,
                         "mission")
            base["mission"] = (file.read_text(encoding="utf-8"), file)
        if scenarios is not None:
            changes["scenarios"] = tuple(scenarios)
            for label in scenarios:
                if label != NO_SCENARIO and f"scenario:{label}" not in base:
                    file = _find("scenarios", label, self.path.parent, str(self.path),
                                 self.lines, "scenarios")
                    base[f"scenario:{label}"] = (file.read_text(encoding="utf-8"), file)
        if seeds is not None:
            changes["seeds"] = tuple(seeds)
        if parameters is not None:
            changes["parameters"] = tuple(parameters)
        return Campaign(dataclasses.replace(self.spec, **changes), self.path, self.text_sha256,
                        base, self.lines)

    def n_runs(self) -> int:
        return len(self.spec.scenarios) * len(self.points()) * len(self.spec.seeds)

    def build_run(self, index: int, scenario_label: str, point: dict[str, Any],
                  seed: int) -> RunSpec:
        """One run's spec: the point applied to the base configs' YAML, each re-validated."""
        scen = None if scenario_label == NO_SCENARIO else scenario_label
        run_id = run_identity(scen, point, seed)
        texts: dict[str, str | None] = {}
        error: str | None = None
        options: dict[str, Any] = {"estimator": self.spec.estimator,
                                   "duration_s": self.spec.duration_s}
        by_ns: dict[str, list[tuple[list[str], Any, str]]] = {}
        for path, value in point.items():
            ns, *rest = path.split(".")
            if ns == "run":
                options[rest[0]] = value
            else:
                by_ns.setdefault(ns, []).append((rest, value, path))
        for ns in ("vehicle", "mission", "preset", "scenario"):
            key = f"scenario:{scen}" if ns == "scenario" else ns
            if ns == "scenario" and scen is None:
                texts[ns] = None
                if by_ns.get(ns) and error is None:
                    error = (f"{by_ns[ns][0][2]} varies a scenario, but this run flies none "
                             f"({NO_SCENARIO!r})")
                continue
            text, file = self.base_texts[key]
            if by_ns.get(ns):
                try:
                    text = apply_overrides(text, by_ns[ns])
                except OverrideError as exc:
                    error = error or f"{file}: {exc}"
            texts[ns] = text
        if error is None:
            error = self._validate(texts, options, point)
        return RunSpec(
            run_id=run_id, run_index=index, campaign=self.name, seed=seed,
            scenario_label=scen, params=dict(point),
            vehicle_text=texts["vehicle"] or "", mission_text=texts["mission"] or "",
            mission_dir=str(self.base_texts["mission"][1].parent.resolve()),
            preset_text=texts["preset"] or "", scenario_text=texts["scenario"],
            labels={ns: str(self.base_texts[f"scenario:{scen}" if ns == "scenario" else ns][1])
                    for ns in ("vehicle", "mission", "preset", "scenario")
                    if ns != "scenario" or scen is not None},
            run_options=options, config_error=error)

    def _validate(self, texts: dict[str, str | None], options: dict[str, Any],
                  point: dict[str, Any]) -> str | None:
        """The config error of a run, as one line naming the point (None: it flies)."""
        labels = {ns: str(self.base_texts[key][1]) for ns, key in
                  (("vehicle", "vehicle"), ("mission", "mission"), ("preset", "preset"))}
        where = ", ".join(f"{k}={_short(v)}" for k, v in point.items()) or "the base configs"
        try:
            build_configs(texts, options, str(self.base_texts["mission"][1].parent.resolve()),
                          labels=labels)
        except ConfigError as exc:  # the line is of the varied text, not of the file: left out
            key = f"{exc.key}: " if exc.key else ""
            return f"{where}: {exc.file}: {key}{exc.message}"
        except ValueError as exc:
            return f"{where}: {exc}"
        return None


class OverrideError(ValueError):
    """A dotted path that does not fit the file it points into."""


def apply_overrides(text: str, overrides: Sequence[tuple[list[str], Any, str]]) -> str:
    """The YAML ``text`` with each ``(keys, value, full_path)`` set (module docstring)."""
    data = yaml.safe_load(text)
    for keys, value, full in overrides:
        data = _set_path(data, keys, value, full)
    # lists of numbers on one line ([0.089, 0.091, 0.164]), as the shipped files write them
    return yaml.safe_dump(data, sort_keys=False, default_flow_style=None, width=100)


def _set_path(node: Any, keys: list[str], value: Any, full: str) -> Any:
    if not keys:
        if (isinstance(node, list) and node and all(_is_number(v) for v in node)
                and _is_number(value)):
            return [value] * len(node)  # a number on a list of numbers sets every item
        return copy.deepcopy(value)
    key, rest = keys[0], keys[1:]
    if isinstance(node, list):
        if not key.isdigit():
            raise OverrideError(f"{full}: {key!r} indexes a list; expected an item number")
        i = int(key)
        if i >= len(node):
            raise OverrideError(f"{full}: item {i} of a list of {len(node)}")
        node[i] = _set_path(node[i], rest, value, full)
        return node
    if node is None:
        node = {}
    if not isinstance(node, dict):
        raise OverrideError(f"{full}: {key!r} goes into a single value ({_short(node)})")
    node[key] = _set_path(node.get(key), rest, value, full)
    return node


def _is_number(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool)


def _short(v: Any) -> str:
    text = json.dumps(v) if not isinstance(v, str) else v
    return text if len(text) <= 40 else text[:37] + "..."


def build_configs(texts: dict[str, str | None], options: dict[str, Any], mission_dir: str,
                  labels: dict[str, str]) -> tuple[Any, Any, Any, Any]:
    """Vehicle, mission, preset and scenario of a run, parsed and cross-checked like
    ``fasthex simulate`` does (raises :class:`ConfigError`)."""
    from controller.missions import MISSION_SCHEMA, Mission, MissionSpec
    from controller.params import VEHICLE_SCHEMA, VehicleParams
    from controller.trajectory_csv import mission_base_dir
    from groundstation.configs import check_mission_against_vehicle, check_mission_lands
    from sim_backend.disturbances import DISTURBANCES_SCHEMA, DisturbancePreset
    from sim_backend.scenario import (
        SCENARIO_SCHEMA,
        Scenario,
        check_scenario_against_mission,
        check_scenario_against_vehicle,
    )

    def label(ns: str) -> str:
        return labels.get(ns, ns)

    vehicle = load_config_text(texts["vehicle"] or "", VehicleParams, schema=VEHICLE_SCHEMA,
                               file_label=label("vehicle"))
    lines: dict[str, int] = {}
    with mission_base_dir(Path(mission_dir)):
        mission_spec = load_config_text(texts["mission"] or "", MissionSpec,
                                        schema=MISSION_SCHEMA, file_label=label("mission"),
                                        lines=lines)
    check_mission_lands(mission_spec, label("mission"), lines)
    check_mission_against_vehicle(mission_spec, vehicle, label("mission"), lines)
    mission = Mission(mission_spec)
    preset = load_config_text(texts["preset"] or "", DisturbancePreset,
                              schema=DISTURBANCES_SCHEMA, file_label=label("preset"))
    scenario = None
    if texts.get("scenario") is not None:
        s_lines: dict[str, int] = {}
        scenario = load_config_text(texts["scenario"] or "", Scenario, schema=SCENARIO_SCHEMA,
                                    file_label=label("scenario"), lines=s_lines)
        check_scenario_against_vehicle(scenario, vehicle, label("scenario"), s_lines)
        check_scenario_against_mission(scenario, mission.duration_s, label("scenario"), s_lines)
    tilt = options.get("tilt_deg")
    if tilt is not None and not (_is_number(tilt) and vehicle.tilt.min_tilt_deg <= tilt
                                 <= vehicle.tilt.max_tilt_deg):
        raise ValueError(f"run.tilt_deg {_short(tilt)}: outside the tilt range of vehicle "
                         f"{vehicle.name!r} ({vehicle.tilt.min_tilt_deg:g} .. "
                         f"{vehicle.tilt.max_tilt_deg:g} deg)")
    duration = options.get("duration_s")
    if duration is not None and not (_is_number(duration) and duration > 0):
        raise ValueError(f"run.duration_s {_short(duration)}: expected a positive duration")
    if options.get("estimator", "truth") not in ("truth", "ukf"):
        raise ValueError(f"run.estimator {_short(options.get('estimator'))}: expected truth "
                         "or ukf")
    speed = options.get("max_touchdown_speed_m_s")
    if speed is not None and not (_is_number(speed) and speed > 0):
        raise ValueError(f"run.max_touchdown_speed_m_s {_short(speed)}: expected a positive "
                         "speed")
    return vehicle, mission, preset, scenario


def run_identity(scenario: str | None, point: dict[str, Any], seed: int) -> str:
    """A stable 16-hex-digit identity of what a run flies."""
    blob = json.dumps({"scenario": scenario, "point": point, "seed": seed}, sort_keys=True,
                      default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


# -- points ------------------------------------------------------------------------------------

def _grid_values(p: Parameter) -> list[Any]:
    if p.values is not None:
        return list(p.values)
    assert p.range is not None and p.num is not None
    lo, hi = p.range
    if p.num == 1:
        vals = np.array([lo])
    elif p.log:
        vals = np.geomspace(lo, hi, p.num)
    else:
        vals = np.linspace(lo, hi, p.num)
    return [_as_value(float(v), p) for v in vals]


def _as_value(v: float, p: Parameter) -> Any:
    if p.integer:
        return round(v)
    return float(f"{v:.12g}")  # the same text on every machine, and in the table


def _from_unit(u: float, p: Parameter) -> Any:
    """A value of ``p`` from a number in [0, 1)."""
    if p.values is not None:
        return p.values[min(int(u * len(p.values)), len(p.values) - 1)]
    assert p.range is not None
    lo, hi = p.range
    v = math.exp(math.log(lo) + u * (math.log(hi) - math.log(lo))) if p.log else lo + u * (hi - lo)
    return _as_value(v, p)


def sample_points(spec: CampaignSpec) -> list[dict[str, Any]]:
    """The campaign's parameter points (an empty point when nothing varies)."""
    params = spec.parameters
    if not params:
        return [{}]
    if spec.sampling == "grid":
        grids = [_grid_values(p) for p in params]
        n = math.prod(len(g) for g in grids)
        if n * len(spec.seeds) * len(spec.scenarios) > MAX_RUNS:
            raise ValueError(f"the grid has {n} points; at most {MAX_RUNS} runs")
        return [{p.path: v for p, v in zip(params, combo, strict=True)}
                for combo in itertools.product(*grids)]
    assert spec.samples is not None
    rng = np.random.default_rng(spec.sampling_seed)
    n = spec.samples
    if spec.sampling == "random":
        units = rng.random((n, len(params)))
    else:  # lhs: one draw per stratum, strata shuffled per parameter
        units = np.empty((n, len(params)))
        for j in range(len(params)):
            units[:, j] = (rng.permutation(n) + rng.random(n)) / n
    return [{p.path: _from_unit(float(units[i, j]), p) for j, p in enumerate(params)}
            for i in range(n)]


# -- loading -----------------------------------------------------------------------------------

def load_campaign(path: str | Path) -> Campaign:
    """Read and check a campaign file and the configs it names (:class:`ConfigError`)."""
    path = Path(path)
    lines: dict[str, int] = {}
    spec_ = load_config(path, CampaignSpec, schema=CAMPAIGN_SCHEMA, versions=(1,), lines=lines)
    label = str(path)
    base: dict[str, tuple[str, Path]] = {}
    for kind, ns, name in (("missions", "mission", spec_.mission),
                           ("vehicles", "vehicle", spec_.vehicle),
                           ("disturbances", "preset", spec_.preset)):
        file = _find(kind, name, path.parent, label, lines, ns)
        base[ns] = (file.read_text(encoding="utf-8"), file)
    for i, name in enumerate(spec_.scenarios):
        if name == NO_SCENARIO:
            continue
        file = _find("scenarios", name, path.parent, label, lines, f"scenarios[{i}]")
        base[f"scenario:{name}"] = (file.read_text(encoding="utf-8"), file)
    campaign = Campaign(spec_, path, hashlib.sha256(path.read_bytes()).hexdigest(), base, lines)
    # the base configs (no parameter applied) must fly: a mistake there is the user's, at once
    from controller.missions import Mission
    from groundstation.configs import (
        load_disturbances,
        load_mission,
        load_scenario,
        load_vehicle,
    )
    vehicle = load_vehicle(base["vehicle"][1])
    mission = Mission(load_mission(base["mission"][1], vehicle=vehicle))
    load_disturbances(base["preset"][1])
    for key, (_, file) in base.items():
        if key.startswith("scenario:"):
            load_scenario(file, vehicle=vehicle, mission_duration_s=mission.duration_s)
    try:
        n = campaign.n_runs()
    except ValueError as exc:
        raise ConfigError(label, line_of(lines, "parameters"), "parameters", str(exc)) from None
    if n > MAX_RUNS:
        raise ConfigError(label, line_of(lines, "parameters"), "parameters",
                          f"{n} runs; expected at most {MAX_RUNS}")
    for i, p in enumerate(spec_.parameters):
        ns = p.path.split(".")[0]
        if ns == "scenario" and all(s == NO_SCENARIO for s in spec_.scenarios):
            key = f"parameters[{i}].path"
            raise ConfigError(label, line_of(lines, key), key,
                              f"{p.path} varies a scenario, but the campaign flies none")
        problem = _parameter_problem(campaign, p)
        if problem is not None:
            key = f"parameters[{i}].{problem[0]}"
            raise ConfigError(label, line_of(lines, key), key, problem[1])
    return campaign


def _parameter_problem(campaign: Campaign, p: Parameter) -> tuple[str, str] | None:
    """What fails every point of ``p`` whatever its value, as (field, message): a path that is
    no key of its file's schema (nor an item of its list), or a value of the wrong type. A
    value outside a field's range stays the config error of its runs: the others fly."""
    from controller.missions import MissionSpec
    from controller.params import VehicleParams
    from sim_backend.disturbances import DisturbancePreset
    from sim_backend.scenario import Scenario

    classes: dict[str, Any] = {"vehicle": VehicleParams, "mission": MissionSpec,
                               "preset": DisturbancePreset, "scenario": Scenario}
    ns, *keys = p.path.split(".")
    targets: list[tuple[Any, Any]] = []  # (field type, the base file's value there)
    if ns == "run":
        targets.append((RUN_TYPES[keys[0]], None))
    for name, (text, file) in campaign.base_texts.items():
        if name == ns or name.startswith(f"{ns}:"):  # scenario:LABEL, each flown scenario
            data = yaml.safe_load(text)
            try:
                targets.append((field_type(classes[ns], data, keys), _get_path(data, keys)))
            except ConfigValueError as exc:
                return "path", f"{ns}.{exc.key}: {exc.message} (in {file})"
    if p.values is not None:
        field_name, values = "values", list(p.values)
    else:
        assert p.range is not None
        field_name, values = "range", [_as_value(v, p) for v in p.range]
    for tp, base in targets:
        for value in values:
            setting = value
            if (_is_number(value) and isinstance(base, list) and base
                    and all(_is_number(v) for v in base)):
                setting = [value] * len(base)  # a number on a list of numbers sets every item
            problem = type_error(tp, setting)
            if problem is not None:
                return field_name, f"{p.path}={_short(value)}: {problem}"
    return None


def _get_path(data: Any, keys: list[str]) -> Any:
    """The value at ``keys`` in parsed YAML (None where there is none)."""
    for key in keys:
        if isinstance(data, dict):
            data = data.get(key)
        elif isinstance(data, list) and key.isdigit() and int(key) < len(data):
            data = data[int(key)]
        else:
            return None
    return data


def _find(kind: str, name: str, base_dir: Path, label: str, lines: dict[str, int],
          key: str) -> Path:
    local = base_dir / name
    if local.suffix in (".yaml", ".yml") and local.is_file():
        return local
    try:
        return find_config(kind, name)
    except ConfigError as exc:
        raise ConfigError(label, line_of(lines, key), key, exc.message + f" ({name})") from None


# -- one run -----------------------------------------------------------------------------------

def execute_run(run: RunSpec) -> dict[str, Any]:
    """Fly one run; its row (identity, parameters, verdict and metrics). Never raises for a
    problem of the run: an exception becomes ``verdict: error`` with its text."""
    import time

    from groundstation.cli import version
    row: dict[str, Any] = {"run_id": run.run_id, "run_index": run.run_index,
                           "campaign": run.campaign, "seed": run.seed,
                           "scenario": run.scenario_label, "fasthex_version": version()}
    row.update(run.params)
    t0 = time.perf_counter()
    if run.config_error is not None:
        row.update(verdict="error", error=f"config: {run.config_error}", wall_time_s=0.0)
        return row
    try:
        summary = _fly(run)
    except Exception as exc:  # a run's failure is its row, never the campaign's end
        tb = traceback.extract_tb(exc.__traceback__)
        where = f" (at {Path(tb[-1].filename).name}:{tb[-1].lineno})" if tb else ""
        row.update(verdict="error", error=f"{type(exc).__name__}: {exc}{where}",
                   wall_time_s=time.perf_counter() - t0)
        return row
    for key in ("scenario", "seed"):
        summary.pop(key, None)
    row.update(summary)
    row.setdefault("error", None)
    return row


def _fly(run: RunSpec) -> dict[str, Any]:
    from groundstation.simulation import simulate_flight
    from sim_backend.closed_loop import SAFE_TOUCHDOWN_SPEED_M_S, CrashLimits

    texts: dict[str, str | None] = {"vehicle": run.vehicle_text, "mission": run.mission_text,
                                    "preset": run.preset_text, "scenario": run.scenario_text}
    vehicle, mission, preset, scenario = build_configs(texts, run.run_options, run.mission_dir,
                                                       run.labels)
    opts = run.run_options
    from groundstation.session_config import SafetyConfig
    safety = SafetyConfig()
    limits = CrashLimits(
        max_touchdown_speed_m_s=opts.get("max_touchdown_speed_m_s") or SAFE_TOUCHDOWN_SPEED_M_S,
        workspace_min_w_m=safety.geofence_min_m, workspace_max_w_m=safety.geofence_max_m)
    tilt = opts.get("tilt_deg")
    return simulate_flight(vehicle, mission, preset, seed=run.seed, scenario=scenario,
                           estimator=opts.get("estimator") or "truth",
                           duration_s=opts.get("duration_s"),
                           tilt_override_rad=None if tilt is None else math.radians(tilt),
                           crash_limits=limits)

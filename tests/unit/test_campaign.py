"""Campaign files: whatever bytes a campaign file holds, loading it fails with a
:class:`ConfigError` or succeeds, never anything else; and the values of the parameter points
(grid order, log spacing, integer rounding, Latin-hypercube strata, reproducible draws), of
the dotted-path overrides and of the run identities."""

from __future__ import annotations

import itertools
import math
import os
import subprocess
import sys
from collections import Counter
from pathlib import Path
from typing import Any

import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from config.schema import ConfigError
from groundstation.campaign import (
    MAX_RUNS,
    CampaignSpec,
    OverrideError,
    Parameter,
    apply_overrides,
    load_campaign,
    run_identity,
    sample_points,
)

HOP = """\
schema: fasthex.mission
version: 1
name: hop
start_pos_w_m: [0.0, 0.0, 0.1]
segments:
  - kind: takeoff
    duration_s: 1.0
    height_m: 0.3
    alpha: {kind: constant, value_deg: 0.0}
  - kind: hold
    duration_s: 0.6
  - kind: land
    duration_s: 3.0
"""

GUST = """\
schema: fasthex.scenario
version: 1
name: gust
disturbances:
  - kind: step
    frame: world
    force_n: [0.0, 2.0, 0.0]
    start_s: 1.0
    duration_s: 0.5
"""

VALID = """\
schema: fasthex.campaign
version: 1
name: fuzz
mission: hop.yaml
preset: paper-calibrated
duration_s: 1.6
scenarios: [none, gust.yaml]
parameters:
  - path: vehicle.controller.ki_pos
    range: [5.0, 50.0]
    num: 3
    log: true
  - path: run.tilt_deg
    values: [0.0, 30.0]
  - path: scenario.disturbances.0.force_n.1
    values: [1.0, 2.0]
seeds: [0, 1]
"""

FUZZ = settings(max_examples=150, deadline=None, derandomize=True, database=None,
                suppress_health_check=[HealthCheck.function_scoped_fixture,
                                       HealthCheck.too_slow])


def load_text(folder: Path, data: bytes | str) -> Any:
    """``load_campaign`` on ``data`` written to a file next to the hop mission and a gust
    scenario: the campaign, or the ConfigError it raised (anything else fails the test)."""
    (folder / "hop.yaml").write_text(HOP)
    (folder / "gust.yaml").write_text(GUST)
    path = folder / "c.yaml"
    path.write_bytes(data if isinstance(data, bytes) else data.encode("utf-8", "surrogatepass"))
    try:
        campaign = load_campaign(path)
    except ConfigError as exc:
        assert exc.message and "\n" not in str(exc), str(exc)  # one line for the terminal
        return exc
    assert campaign.n_runs() <= MAX_RUNS
    return campaign


# -- the fuzzing ---------------------------------------------------------------------------


def test_that_the_valid_campaign_of_the_fuzzing_loads(tmp_path: Path) -> None:
    campaign = load_text(tmp_path, VALID)
    assert not isinstance(campaign, ConfigError), campaign
    assert campaign.n_runs() == 2 * 3 * 2 * 2 * 2


@FUZZ
@given(data=st.binary(max_size=400))
def test_that_random_bytes_are_a_config_error_or_a_campaign(tmp_path: Path, data: bytes) -> None:
    load_text(tmp_path, data)


@st.composite
def mutated(draw: st.DrawFn, text: str) -> str:
    """``text`` with a few characters changed, cut or added (YAML's own punctuation likely)."""
    chars = list(text)
    alphabet = st.sampled_from(list(":-[]{},#&*!|>'\"%@` \n\t.0123456789eE+naifTF~\\"))
    for _ in range(draw(st.integers(1, 6))):
        pos = draw(st.integers(0, len(chars)))
        op = draw(st.integers(0, 2))
        if op == 0 and pos < len(chars):
            chars[pos] = draw(st.one_of(alphabet, st.characters()))
        elif op == 1:
            chars[pos:pos] = draw(st.lists(alphabet, min_size=1, max_size=6))
        else:
            del chars[pos:pos + draw(st.integers(1, 12))]
    return "".join(chars)


@FUZZ
@given(text=mutated(VALID))
def test_that_a_mutated_campaign_is_a_config_error_or_a_campaign(tmp_path: Path,
                                                                  text: str) -> None:
    load_text(tmp_path, text)


SCALARS = st.one_of(
    st.none(), st.booleans(), st.integers(-10**20, 10**20), st.text(max_size=12),
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([0, 1, -1, 0.0, 1e308, -1e308, 5e-324, 2**63, "nan", "inf", "1e999", ""]))
VALUES = st.recursive(SCALARS, lambda inner: st.one_of(
    st.lists(inner, max_size=4), st.dictionaries(st.text(max_size=6), inner, max_size=3)),
    max_leaves=8)


def mostly(good: st.SearchStrategy[Any], bad: st.SearchStrategy[Any] = VALUES
           ) -> st.SearchStrategy[Any]:
    """``good`` about nine times in ten, else ``bad``: most examples get past the first
    check (not on 0 nor 9: hypothesis favours the ends of a range)."""
    return st.integers(0, 9).flatmap(lambda i: bad if i == 5 else good)


PATHS = mostly(st.sampled_from([
    "vehicle.controller.ki_pos", "vehicle.controller.kp_pos.1", "vehicle.controller.kp_pos.9",
    "vehicle.mass_kg", "vehicle.name.x", "vehicle.new.deep.key", "mission.segments.0.duration_s",
    "mission.segments.5.kind", "mission.segments.1", "mission.name", "preset.mocap",
    "scenario.plant.payload_kg", "scenario.disturbances.0.force_n", "scenario.disturbances",
    "run.tilt_deg", "run.duration_s", "run.estimator", "run.max_touchdown_speed_m_s"]),
    st.one_of(st.sampled_from(["run.seed", "run", "vehicle.", ".x", "mission..a"]),
              st.text(max_size=20)))
NUMBERS = st.one_of(st.floats(-1e3, 1e3), st.integers(-10, 10**4),
                    st.sampled_from([1e308, -1e308, 5e-324, 0.0]))


@st.composite
def parameters(draw: st.DrawFn, sampling: str) -> dict[str, Any]:
    p: dict[str, Any] = {"path": draw(PATHS)}
    if draw(st.booleans()):
        p["values"] = draw(mostly(st.lists(VALUES, min_size=1, max_size=4)))
    else:
        p["range"] = draw(mostly(st.lists(NUMBERS, min_size=2, max_size=2).map(sorted),
                                 st.one_of(st.lists(NUMBERS, max_size=3), VALUES)))
        if sampling == "grid" or draw(st.integers(0, 9)) == 7:
            p["num"] = draw(mostly(st.integers(1, 4), st.one_of(
                st.integers(-2, 12), st.sampled_from([10_000, 10_001]), SCALARS)))
    for flag in ("log", "integer"):
        if draw(st.booleans()):
            p[flag] = draw(mostly(st.booleans(), SCALARS))
    if draw(st.integers(0, 19)) == 7:
        p[draw(st.text(max_size=6))] = draw(VALUES)
    return p


@st.composite
def campaigns(draw: st.DrawFn) -> str:
    """A campaign mapping: the real keys with plausible values mostly, absurd ones and stray
    keys at times."""
    sampling = draw(mostly(st.sampled_from(["grid", "random", "lhs"]),
                           st.sampled_from(["sobol", None, 3])))
    doc: dict[str, Any] = {
        "schema": draw(mostly(st.just("fasthex.campaign"), st.sampled_from(["fasthex.mission",
                                                                            7]))),
        "version": draw(mostly(st.just(1), st.sampled_from([2, "1", None]))),
        "name": draw(mostly(st.just("fuzz"), st.text(max_size=8))),
        "mission": draw(mostly(st.just("hop.yaml"), st.sampled_from([
            "gust-hover", "fasthex", "nope.yaml", "../hop.yaml", "", "c.yaml", "gust.yaml"]))),
    }
    optional: dict[str, st.SearchStrategy[Any]] = {
        "vehicle": mostly(st.sampled_from(["fasthex", "fasthex-mini"]),
                          st.sampled_from(["hop.yaml", "gust-hover", 3])),
        "preset": mostly(st.sampled_from(["paper-calibrated", "ideal"]),
                         st.sampled_from(["fasthex", 3])),
        "estimator": mostly(st.sampled_from(["truth", "ukf"]),
                            st.sampled_from(["kalman", None])),
        "duration_s": mostly(st.floats(0.1, 2.0), st.one_of(st.floats(-1, 5000), SCALARS)),
        "scenarios": mostly(st.lists(st.sampled_from(["none", "gust.yaml"]), min_size=1,
                                     max_size=2, unique=True),
                            st.lists(st.sampled_from(["step-gust-2n", "nope", "none"]),
                                     max_size=3)),
        "parameters": mostly(st.lists(parameters(sampling), min_size=1, max_size=3)),
        "samples": mostly(st.integers(1, 6), st.one_of(
            st.integers(-1, 50), st.sampled_from([MAX_RUNS, MAX_RUNS + 1]), SCALARS)),
        "sampling_seed": mostly(st.integers(0, 2**64), st.one_of(st.integers(-5, 2**70),
                                                                  SCALARS)),
        "seeds": mostly(st.lists(st.integers(0, 2**32), min_size=1, max_size=3, unique=True),
                        st.lists(st.integers(-3, 2**64), max_size=4)),
        "tune": mostly(st.dictionaries(st.text(max_size=6), VALUES, max_size=2)),
        "description": mostly(st.text(st.characters(codec="ascii", min_codepoint=32),
                                      max_size=20), SCALARS),
    }
    if sampling != "grid" or draw(st.integers(0, 9)) == 7:
        doc["sampling"] = sampling
    for key, strategy in optional.items():
        if (key == "samples" and sampling in ("random", "lhs")) or draw(st.booleans()):
            doc[key] = draw(strategy)
    if draw(st.integers(0, 19)) == 7:
        doc[draw(st.text(max_size=8))] = draw(VALUES)
    return yaml.safe_dump(doc, sort_keys=draw(st.booleans()), allow_unicode=True)


@FUZZ
@given(text=campaigns())
def test_that_a_random_campaign_mapping_is_a_config_error_or_a_campaign(tmp_path: Path,
                                                                        text: str) -> None:
    campaign = load_text(tmp_path, text)
    if isinstance(campaign, ConfigError):
        return
    # its runs build (the point applied, each file validated again): a bad point is the
    # run's config error, never an exception
    for run in itertools.islice(campaign.runs(), 3):
        assert run.config_error is None or isinstance(run.config_error, str)
        assert len(run.run_id) == 16


@pytest.mark.parametrize("parameter", [
    "{path: vehicle.controller.ki_pos, range: [-1.0e308, 1.0e308], num: 3, integer: true}",
    "{path: vehicle.controller.ki_pos, range: [-1.0e308, 1.0e308], num: 3}",
])
def test_that_a_range_too_wide_for_floats_is_a_config_error(tmp_path: Path,
                                                            parameter: str) -> None:
    result = load_text(tmp_path, VALID.replace(
        "parameters:\n", f"parameters:\n  - {parameter}\n").replace(
        "  - path: vehicle.controller.ki_pos\n    range: [5.0, 50.0]\n    num: 3\n"
        "    log: true\n", ""))
    assert isinstance(result, ConfigError)
    assert result.key == "parameters[0].range" and "finite" in result.message, result


def test_that_a_random_range_too_wide_for_floats_is_a_config_error(tmp_path: Path) -> None:
    result = load_text(tmp_path, VALID.replace(
        "seeds: [0, 1]", "seeds: [0, 1]\nsampling: random\nsamples: 4").replace(
        "    range: [5.0, 50.0]\n    num: 3\n    log: true\n",
        "    range: [-1.0e308, 1.0e308]\n    integer: true\n"))
    assert isinstance(result, ConfigError)
    assert result.key == "parameters[0].range" and "finite" in result.message, result


# -- points ----------------------------------------------------------------------------------


def spec(*params: Parameter, **kw: Any) -> CampaignSpec:
    return CampaignSpec(name="t", mission="hop", parameters=params, **kw)


def test_that_a_grid_is_the_product_in_parameter_order_the_last_varying_fastest() -> None:
    points = sample_points(spec(Parameter(path="vehicle.a", values=(1, 2)),
                                Parameter(path="vehicle.b", values=("x", "y", "z"))))
    assert points == [{"vehicle.a": a, "vehicle.b": b} for a in (1, 2) for b in "xyz"]


def test_that_no_parameter_is_one_empty_point() -> None:
    assert sample_points(spec()) == [{}]


def test_that_a_grid_range_is_evenly_spaced_ends_included() -> None:
    points = sample_points(spec(Parameter(path="vehicle.a", range=(0.0, 1.0), num=5)))
    assert [p["vehicle.a"] for p in points] == [0.0, 0.25, 0.5, 0.75, 1.0]
    one = sample_points(spec(Parameter(path="vehicle.a", range=(2.0, 9.0), num=1)))
    assert one == [{"vehicle.a": 2.0}]


def test_that_a_log_range_is_geometric_and_rounded_to_12_digits() -> None:
    points = sample_points(spec(Parameter(path="vehicle.a", range=(1.0, 1000.0), num=4,
                                          log=True)))
    values = [p["vehicle.a"] for p in points]
    assert values == [1.0, 10.0, 100.0, 1000.0]  # exactly: 12 significant digits, no 9.999...
    third = sample_points(spec(Parameter(path="vehicle.a", range=(1.0, 2.0), num=3, log=True)))
    assert third[1]["vehicle.a"] == float(f"{math.sqrt(2.0):.12g}")


def test_that_integer_rounds_to_ints() -> None:
    points = sample_points(spec(Parameter(path="vehicle.a", range=(0.0, 6.0), num=5,
                                          integer=True)))
    values = [p["vehicle.a"] for p in points]
    assert values == [0, 2, 3, 4, 6]  # 0, 1.5, 3, 4.5, 6 rounded half to even
    assert all(type(v) is int for v in values)
    drawn = sample_points(spec(Parameter(path="vehicle.a", range=(1.0, 100.0), integer=True,
                                         log=True), sampling="random", samples=50))
    assert all(type(p["vehicle.a"]) is int and 1 <= p["vehicle.a"] <= 100 for p in drawn)


@pytest.mark.parametrize(("parameter", "key", "message"), [
    ("{path: vehicle.controller.ki_pos, range: [10.0, 11.0], num: 5, integer: true}",
     "parameters[0].num", "num 5 integer values in [10, 11] repeat: at most 2 distinct"),
    ("{path: vehicle.controller.ki_pos, range: [0.6, 2.4], num: 3, integer: true}",
     "parameters[0].num", "num 3 integer values in [0.6, 2.4] repeat: at most 2 distinct"),
    ("{path: vehicle.controller.ki_pos, values: [10.0, 20.0, 10]}",
     "parameters[0].values", "10 is listed twice"),
])
def test_that_a_grid_whose_points_repeat_is_a_config_error_at_its_line(
        tmp_path: Path, parameter: str, key: str, message: str) -> None:
    # the same point twice is the same run_id flown twice, counted twice by the sweep
    text = VALID.replace("  - path: vehicle.controller.ki_pos\n    range: [5.0, 50.0]\n"
                         "    num: 3\n    log: true\n", f"  - {parameter}\n")
    result = load_text(tmp_path, text)
    assert isinstance(result, ConfigError), result
    assert (result.line, result.key, result.message) == (9, key, message), result


@pytest.mark.parametrize(("parameter", "key", "message"), [
    ("{path: vehicle.controler.ki_pos, values: [10.0, 20.0]}", "parameters[0].path",
     "vehicle.controler: unknown key; expected one of: controller, description, "),
    ("{path: vehicle.controller.ki_pos.7, values: [10.0, 20.0]}", "parameters[0].path",
     "vehicle.controller.ki_pos.7: expected an item number below 3 (in "),
    ("{path: vehicle.mass_kg.x, values: [1.0]}", "parameters[0].path",
     "vehicle.mass_kg.x: 'x' goes into a single value (a number) (in "),
    ("{path: mission.segments.1.duraton_s, range: [0.5, 1.0], num: 2}", "parameters[0].path",
     "mission.segments.1.duraton_s: unknown key; expected one of: accept_lateral_shortfall, "),
    ("{path: scenario.disturbances.0.forse_n, values: [[0.0, 1.0, 0.0]]}",
     "parameters[0].path", "scenario.disturbances.0.forse_n: unknown key; expected one of: "),
    ("{path: vehicle.controller.ki_pos, values: [a, b]}", "parameters[0].values",
     "vehicle.controller.ki_pos=a: expected a list of 3 (e.g. [1, 2, 3])"),
    ("{path: vehicle.controller.kp_pos.1, values: [10.0, x]}", "parameters[0].values",
     "vehicle.controller.kp_pos.1=x: expected a number, got 'x'"),
    ("{path: run.estimator, values: [truth, kalman]}", "parameters[0].values",
     "run.estimator=kalman: expected one of 'truth', 'ukf'; got 'kalman'"),
])
def test_that_a_parameter_no_point_can_fly_is_a_config_error_at_its_line(
        tmp_path: Path, parameter: str, key: str, message: str) -> None:
    # a path the file's schema does not have, or a value of the wrong type: every point
    # would be an error row, so the campaign is refused at load
    text = VALID.replace("  - path: vehicle.controller.ki_pos\n    range: [5.0, 50.0]\n"
                         "    num: 3\n    log: true\n", f"  - {parameter}\n")
    result = load_text(tmp_path, text)
    assert isinstance(result, ConfigError), result
    assert (result.line, result.key) == (9, key), result
    assert result.message.startswith(message), result


def test_that_a_point_outside_a_fields_range_still_loads_as_a_runs_error(
        tmp_path: Path) -> None:
    # the type fits, the value does not: that point's row carries the error, the others fly
    text = VALID.replace("range: [5.0, 50.0]\n    num: 3\n    log: true",
                         "values: [-1.0, 30.0]")
    campaign = load_text(tmp_path, text)
    assert not isinstance(campaign, ConfigError), campaign
    errors = {run.params["vehicle.controller.ki_pos"]: run.config_error
              for run in campaign.runs() if run.scenario_label is not None}
    assert errors[30.0] is None and "ki_pos" in str(errors[-1.0]), errors


def _lhs(samples: int, seed: int = 0) -> tuple[CampaignSpec, list[dict[str, Any]]]:
    s = spec(Parameter(path="vehicle.a", range=(0.0, 10.0)),
             Parameter(path="vehicle.b", range=(1.0, 1000.0), log=True),
             Parameter(path="run.tilt_deg", range=(-20.0, 20.0)),
             sampling="lhs", samples=samples, sampling_seed=seed)
    return s, sample_points(s)


def _stratum(value: float, p: Parameter, n: int) -> int:
    assert p.range is not None
    lo, hi = p.range
    u = (math.log(value / lo) / math.log(hi / lo)) if p.log else (value - lo) / (hi - lo)
    return min(int(u * n), n - 1)


@pytest.mark.parametrize("samples", [1, 7, 40])
def test_that_a_latin_hypercube_uses_every_stratum_of_every_parameter_once(
        samples: int) -> None:
    s, points = _lhs(samples)
    assert len(points) == samples
    for p in s.parameters:
        values = [pt[p.path] for pt in points]
        assert p.range is not None
        assert all(p.range[0] <= v <= p.range[1] for v in values)
        strata = Counter(_stratum(v, p, samples) for v in values)
        assert sorted(strata) == list(range(samples)) and set(strata.values()) == {1}


def test_that_a_latin_hypercube_is_random_within_its_strata_and_across_parameters() -> None:
    s, points = _lhs(40)
    a = [_stratum(pt["vehicle.a"], s.parameters[0], 40) for pt in points]
    b = [_stratum(pt["vehicle.b"], s.parameters[1], 40) for pt in points]
    assert a != sorted(a) and a != b  # strata shuffled, independently per parameter
    # not the strata's centres: each value somewhere in its stratum
    offsets = [pt["vehicle.a"] / 10.0 * 40 - k for pt, k in zip(points, a, strict=True)]
    assert all(0.0 <= o <= 1.0 for o in offsets) and len({round(o, 6) for o in offsets}) > 30


def test_that_random_points_stay_in_range_and_come_back_with_the_sampling_seed() -> None:
    def draw(seed: int) -> list[dict[str, Any]]:
        return sample_points(spec(Parameter(path="vehicle.a", range=(-1.0, 1.0)),
                                  Parameter(path="vehicle.b", values=("x", "y", "z")),
                                  Parameter(path="vehicle.c", range=(0.01, 100.0), log=True),
                                  sampling="random", samples=200, sampling_seed=seed))

    first = draw(3)
    assert first == draw(3)
    assert first != draw(4)
    assert all(-1.0 <= p["vehicle.a"] <= 1.0 and 0.01 <= p["vehicle.c"] <= 100.0 for p in first)
    assert Counter(p["vehicle.b"] for p in first).keys() == {"x", "y", "z"}
    # log-uniform: about as many draws in each decade
    decades = Counter(math.floor(math.log10(p["vehicle.c"])) for p in first)
    assert set(decades) == {-2, -1, 0, 1} and min(decades.values()) > 25
    lhs_first = _lhs(9, seed=5)[1]
    assert lhs_first == _lhs(9, seed=5)[1] and lhs_first != _lhs(9, seed=6)[1]


# -- overrides ---------------------------------------------------------------------------


BASE = """\
name: v
controller:
  kp_pos: [1.0, 2.0, 3.0]
  mixed: [1.0, two, 3]
  gain: 4.0
segments:
  - kind: hold
    duration_s: 2.0
  - kind: land
"""


def override(text: str, path: str, value: Any) -> dict[str, Any]:
    keys = path.split(".")
    return dict(yaml.safe_load(apply_overrides(text, [(keys, value, "vehicle." + path)])))


def test_that_a_list_item_is_set_by_its_index() -> None:
    data = override(BASE, "controller.kp_pos.1", 9.5)
    assert data["controller"]["kp_pos"] == [1.0, 9.5, 3.0]
    data = override(BASE, "segments.1.duration_s", 1.5)
    assert data["segments"][1] == {"kind": "land", "duration_s": 1.5}


def test_that_a_number_on_a_list_of_numbers_sets_every_item() -> None:
    assert override(BASE, "controller.kp_pos", 7)["controller"]["kp_pos"] == [7, 7, 7]
    # not a list of numbers, or not a number: replaced as a whole
    assert override(BASE, "controller.mixed", 7)["controller"]["mixed"] == 7
    assert override(BASE, "controller.kp_pos", [1, 2])["controller"]["kp_pos"] == [1, 2]
    assert override(BASE, "controller.kp_pos", True)["controller"]["kp_pos"] is True


def test_that_missing_mappings_along_the_path_are_created() -> None:
    data = override(BASE, "plant.payload.mass_kg", 0.3)
    assert data["plant"] == {"payload": {"mass_kg": 0.3}}
    assert data["controller"]["gain"] == 4.0  # the rest untouched, in order
    assert list(data) == ["name", "controller", "segments", "plant"]
    assert override("", "a.b", 1) == {"a": {"b": 1}}


@pytest.mark.parametrize(("path", "message"), [
    ("controller.kp_pos.3", "vehicle.controller.kp_pos.3: item 3 of a list of 3"),
    ("segments.2.kind", "vehicle.segments.2.kind: item 2 of a list of 2"),
    ("controller.kp_pos.x", "vehicle.controller.kp_pos.x: 'x' indexes a list; expected an "
     "item number"),
    ("controller.kp_pos.-1", "'-1' indexes a list"),
    ("controller.gain.x", "vehicle.controller.gain.x: 'x' goes into a single value (4.0)"),
    ("name.first", "'first' goes into a single value (v)"),
    ("controller.kp_pos.0.x", "'x' goes into a single value (1.0)"),
])
def test_that_a_path_past_a_list_or_into_a_value_is_refused(path: str, message: str) -> None:
    with pytest.raises(OverrideError) as err:
        override(BASE, path, 1.0)
    assert message in str(err.value)


def test_that_an_override_does_not_share_the_value_it_sets() -> None:
    value = {"a": [1, 2]}
    text = apply_overrides(BASE, [(["x"], value, "vehicle.x"), (["y"], value, "vehicle.y")])
    value["a"].append(3)
    data = yaml.safe_load(text)
    assert data["x"] == data["y"] == {"a": [1, 2]}


# -- identities ------------------------------------------------------------------------------


def test_that_a_run_identity_depends_on_what_it_flies_only() -> None:
    point = {"vehicle.controller.ki_pos": 30.0, "run.tilt_deg": 10.0}
    rid = run_identity(None, point, 0)
    assert len(rid) == 16 and int(rid, 16) >= 0
    assert rid == run_identity(None, dict(reversed(point.items())), 0)  # key order: same run
    assert rid == run_identity(None, dict(point), 0)
    others = {run_identity(None, point, 1), run_identity("step-gust-2n", point, 0),
              run_identity(None, point | {"run.tilt_deg": 10.5}, 0),
              run_identity(None, {"vehicle.controller.ki_pos": 30.0}, 0)}
    assert rid not in others and len(others) == 4


def test_that_a_run_identity_is_the_same_in_another_interpreter() -> None:
    point = {"vehicle.controller.ki_pos": 30.0, "run.tilt_deg": 10.0, "mission.name": "x"}
    code = ("from groundstation.campaign import run_identity; "
            f"print(run_identity('payload-gust', {point!r}, 7))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, env=dict(os.environ, PYTHONHASHSEED="12345")).stdout.strip()
    assert out == run_identity("payload-gust", point, 7)

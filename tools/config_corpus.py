"""A corpus of malformed config files, generated from the shipped ones, and a runner for it.

Every case is one broken file (a vehicle, a mission, a disturbance preset or a session) next
to the good files that refer to it, plus the ``fasthex`` command line that reads it: ``fly
SESSION`` (the session names the broken file) or ``simulate MISSION --vehicle V --preset P``.
Each case must end with exit code 2 and exactly one stderr line

    fasthex: config error: FILE:LINE: KEY: expectation        (a value, key or reference)
    fasthex: config error: FILE:LINE: expectation             (reader level: bytes, YAML)

naming the file at fault (and, where the mutation pins it, its line). Mutations:

- every number of the shipped files in turn: text, NaN, +-inf, 1e9, -1e9, a bool, a list
  (two of these on each number of the first file of a kind, one on each of the second);
- physically absurd values chosen per key (near-zero damping, 1e-12 s time constants,
  ``tikhonov_k1: 0``, a start 1e9 m away, ...);
- unknown, missing and duplicate keys, wrong schema/version, wrong literals;
- reader-level garbage: NUL and other control bytes, invalid UTF-8, tabs, deep nesting, huge
  files, alias bombs, several documents, empty files, syntax errors, tags;
- bad references (a missing vehicle, mission or preset, by name or file) and cross-file
  inconsistencies (waypoints outside the geofence, alpha beyond the vehicle's tilt range, a
  takeoff below the start, MoCap slower than the session's timeouts).

Run by hand: ``python tools/config_corpus.py [OUT_DIR]`` writes the corpus and runs every case
through ``groundstation.cli.main`` in this process, then prints the count and pass rate per
kind (``--keep`` keeps OUT_DIR). ``tests/unit/test_config_corpus.py`` runs the same cases.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import io
import re
import sys
import tempfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # run from a checkout without installing
    sys.path.insert(0, str(ROOT))

from config import config_root  # noqa: E402

KINDS = ("vehicles", "missions", "disturbances", "sessions")

#: the one line a refused config prints (key form and reader form)
LINE_RE = re.compile(r"^fasthex: config error: (?P<file>.+?):(?P<line>\d+): "
                     r"(?:(?P<key>[A-Za-z_][\w.\[\]]*): )?(?P<message>.+)$")


@dataclass(frozen=True)
class Case:
    """One malformed config and how to run it."""

    kind: str  # which kind of file is broken (KINDS)
    name: str  # what was done, e.g. "mass_kg = .nan"
    argv: tuple[str, ...]  # fasthex command line
    file: str  # the file the error must name
    line: int | None  # the line it must name (None: any)
    reader: bool  # a reader-level error (no KEY in the line)


@dataclass(frozen=True)
class Outcome:
    case: Case
    code: int | None
    stderr: str
    problem: str  # empty when the case passed

    @property
    def ok(self) -> bool:
        return not self.problem


# -- the shipped files and their numbers --------------------------------------------------------
def _shipped(kind: str, name: str) -> str:
    return (config_root() / kind / f"{name}.yaml").read_text(encoding="utf-8")


def _leaves(text: str) -> Iterator[tuple[str, yaml.ScalarNode]]:
    """(key path, node) of every scalar value in a YAML document, in file order."""
    def walk(node: yaml.Node, path: str) -> Iterator[tuple[str, yaml.ScalarNode]]:
        if isinstance(node, yaml.MappingNode):
            for k, v in node.value:
                yield from walk(v, f"{path}.{k.value}" if path else str(k.value))
        elif isinstance(node, yaml.SequenceNode):
            for i, v in enumerate(node.value):
                yield from walk(v, f"{path}[{i}]")
        elif isinstance(node, yaml.ScalarNode):
            yield path, node
    root = yaml.compose(text)
    assert root is not None
    yield from walk(root, "")


def _is_number(node: yaml.ScalarNode) -> bool:
    if node.style is not None:
        return False
    try:
        float(node.value)
    except ValueError:
        return False
    return True


def _splice(text: str, node: yaml.Node, new: str) -> str:
    return text[:node.start_mark.index] + new + text[node.end_mark.index:]


@functools.lru_cache(maxsize=64)
def _leaf_list(text: str) -> tuple[tuple[str, yaml.ScalarNode], ...]:
    return tuple(_leaves(text))


def _set(text: str, key: str, new: str) -> tuple[str, int]:
    """``text`` with the value at key path ``key`` replaced; and the value's line."""
    for path, node in _leaf_list(text):
        if path == key:
            return _splice(text, node, new), node.start_mark.line + 1
    raise KeyError(key)


def _line(text: str, fragment: str) -> int:
    return next(i for i, line in enumerate(text.splitlines(), 1) if fragment in line)


#: values no number of any schema accepts (every number has a finite range inside +-1e9)
BLANKET = ("abc", ".nan", ".inf", "-.inf", "1e9", "-1e9", "true", "[1, 2]")

#: physically absurd values per key path (each must be refused on its own)
ABSURD: dict[str, dict[str, tuple[str, ...]]] = {
    "vehicles": {
        "mass_kg": ("0", "1e-6", "500"),
        "inertia_diag_kg_m2[0]": ("0", "1e-9", "0.001"),
        "inertia_diag_kg_m2[2]": ("5.0", "0"),
        "gravity_m_s2": ("0", "1.62", "30"),
        "geometry.arm_length_m": ("0.001", "5"),
        "geometry.propeller_diameter_m": ("1.0", "0.001"),
        "geometry.ring_diameter_m": ("0.1",),
        "rotors.min_spin_hz": ("101.9", "-1"),
        "rotors.max_spin_hz": ("1", "0", "1000"),
        "rotors.thrust_coeff_n_per_hz2": ("0", "1e-12", "0.5"),
        "rotors.drag_coeff_m": ("0", "1e-9", "0.9"),
        "tilt.max_tilt_deg": ("80", "-5"),
        "tilt.mechanical_limit_deg": ("10", "120"),
        "tilt.max_rate_deg_s": ("0", "0.01", "1000"),
        "tilt.worm_ratio": ("0", "1e-9", "2"),
        "tilt.cardan_bend_deg": ("89", "90"),
        "controller.kp_pos[0]": ("0", "1e-6", "1e5", "5000"),
        "controller.kv_pos[0]": ("0", "0.01", "0.5", "1e6"),
        "controller.ki_pos[2]": ("1e4", "500", "-1"),
        "controller.kr_att[0]": ("0", "1e-6", "5000"),
        "controller.kw_att[0]": ("0", "0.001", "0.05"),
        "controller.kw_att[2]": ("0.01",),
        "controller.ki_att[0]": ("300", "-0.1"),  # d k / J = 253: beyond Hurwitz
        "controller.pos_integral_limit_m_s[0]": ("0", "1e-9", "1e6"),
        "controller.att_integral_limit_rad_s[1]": ("0", "1000"),
        "controller.bisection_iterations": ("0", "1000", "-3"),
        "controller.tikhonov_k1": ("0", "-4e-6", "1", "1e-3"),
        "controller.tikhonov_k2_rad": ("0", "1e-12", "10"),
        "controller.lateral_bound_scale": ("0", "0.001", "2"),
        "controller.lateral_bound_dead_zone_deg": ("45", "-1"),
    },
    "missions": {
        "start_pos_w_m[0]": ("1e9", "150", "-101"),
        "start_pos_w_m[2]": ("1e9",),
        "segments[0].duration_s": ("0", "1e-9", "-5", "0.2"),
        "segments[0].height_m": ("0.1", "0.0", "-1", "1e9", "150"),
        "segments[0].alpha.value_deg": ("-10", "91", "1e9"),
        "segments[1].duration_s": ("0", "86400"),
        "segments[2].alpha.times_s[1]": ("70", "1e6", "-1"),
        "segments[2].alpha.values_deg[1]": ("-1", "100"),
        "segments[3].duration_s": ("0.001",),
    },
    "disturbances": {
        "physics_rate_hz": ("0", "10", "1e6"),
        "rotor_time_constant_s": ("1e-12", "1e-5", "-0.03", "5"),
        "rotor_inertia_kg_m2": ("-1e-4", "1"),
        "misalignment_deg": ("45", "-1"),
        "thrust_coeff_spread": ("0.9", "-0.1"),
        "tether_force_n": ("1000", "-1"),
        "tether_anchor_w_m[0]": ("1e9", "-500"),
        "ou_force_rms_n": ("1000",),
        "ou_force_tau_s": ("0", "1e-12", "1e-4", "1e6"),
        "gyro_noise_density_rad_s_rthz": ("10", "-1"),
        "accel_bias_sigma_m_s2": ("100",),
        "imu_rate_hz": ("0", "1", "5000"),
        "mocap_rate_hz": ("0", "0.1", "1e5"),
        "mocap_latency_s": ("-0.01", "10"),
        "mocap_dropout_prob": ("1.0", "0.9", "-0.5"),
        "mocap_pos_noise_m": ("5",),
        "estimate_rate_noise_rad_s": ("100",),
    },
    "sessions": {
        "backend.imu_rate_hz": ("0", "1", "1e5"),
        "backend.seed": ("-1", "1.5", "99999999999"),
        "safety.geofence_min_m[0]": ("2.5", "1e9", "-1e3"),
        "safety.geofence_max_m[2]": ("-0.5", "-1", "500"),
        "safety.max_body_tilt_deg": ("0", "0.5", "180"),
        "safety.mocap_timeout_s": ("0", "1e-12", "3600"),
        "safety.imu_timeout_s": ("0", "1e-12", "0.003", "60"),
        "safety.min_battery_v": ("-1", "1000"),
        "estimator.force_cmd_lag_s": ("-0.03", "100"),
    },
}

#: wrong words for the literal-valued keys
LITERALS: dict[str, dict[str, tuple[str, ...]]] = {
    "missions": {"segments[0].kind": ("hover", "TAKEOFF", "1"),
                 "segments[0].alpha.kind": ("fixed",), "segments[2].alpha.kind": ("stairs",)},
    "sessions": {"backend.kind": ("simulated", "true"), "backend.clock": ("fast",),
                 "safety.failsafe_action": ("hover", "yes"),
                 "safety.servo_fault_action": ("ignore",), "telemetry.rerun": ("maybe",)},
    "vehicles": {"rotors.first_rotor_ccw": ("maybe", "1")},
    "disturbances": {"cardan_chain": ("sometimes", "0")},
}

#: the shipped file each kind's mutations start from, and the second one used for variety
BASES = {"vehicles": ("fasthex", "fasthex-mini"),
         "missions": ("exp1-hover-tilt-steps", "exp2a-sine-translation"),
         "disturbances": ("paper-calibrated", "ideal"),
         "sessions": ("exp1-emulated", "hardware-template")}

SCHEMAS = {"vehicles": "fasthex.vehicle", "missions": "fasthex.mission",
           "disturbances": "fasthex.disturbances", "sessions": "fasthex.session"}


def _reader_garbage(good: str) -> Iterator[tuple[str, bytes, int | None]]:
    """(name, bytes, line) of files that fail before any key is read."""
    raw = good.encode()
    cut = good.index("\n", good.index("version:")) + 1  # after the version line
    line_after = good[:cut].count("\n") + 1
    head, tail = raw[:cut], raw[cut:]
    yield "NUL byte", head + b"name: a\x00b\n" + tail, line_after
    yield "NUL at the start", b"\x00" + raw, 1
    yield "escape sequence", head + b"description: \x1b[31mred\n" + tail, line_after
    yield "DEL byte", head + b"x: \x7f\n" + tail, line_after
    yield "form feed", head + b"\x0c\n" + tail, line_after
    yield "invalid UTF-8", head + b"description: caf\xe9\n" + tail, line_after
    yield "truncated UTF-8", raw + b"# \xe2\x82\n", good.count("\n") + 1
    yield "UTF-16 file", good.encode("utf-16"), 1
    yield "tab indentation", head + b"geometry:\n\tarm_length_m: 1\n" + tail, line_after + 1
    yield "deep nesting (flow)", head + b"x: " + b"[" * 200 + b"]" * 200 + b"\n" + tail, \
        line_after
    yield "deep nesting (block)", head + b"".join(b" " * i + b"k:\n" for i in range(40)) + tail, \
        None
    yield "huge file", raw + b"#" + b"x" * (300 * 1024) + b"\n", 1
    yield "billion laughs", (head + b"a: &a [x, x, x, x, x, x, x, x, x]\n"
                             b"b: &b [*a, *a, *a, *a, *a, *a, *a, *a, *a]\n"
                             b"c: [*b, *b, *b, *b, *b, *b, *b, *b, *b]\n" + tail), line_after
    yield "merge key alias", raw.replace(b"name:", b"base: &b {q: 1}\nname:", 1), None
    yield "two documents", raw + b"---\nschema: x\n", None
    yield "document end then more", raw + b"...\n---\nfoo: 1\n", None
    yield "empty file", b"", 1
    yield "only comments", b"# nothing\n# here\n", 1
    yield "only whitespace", b"   \n\n  \n", 1
    yield "unclosed list", raw.replace(b"version: 1", b"version: [1", 1), None
    yield "unclosed quote", head + b'name: "abc\n' + tail, None
    yield "bad indentation", head + b"name: a\n   bad: 1\n  worse: 2\n" + tail, None
    yield "top-level list", b"- schema: x\n- version: 1\n", 1
    yield "top-level scalar", b"just some words\n", 1
    name_line = _line(good, "name:")
    for label, value in (("python tag", "!!python/object/apply:os.system [echo]"),
                         ("impossible date", "2021-13-45"), ("bad int tag", "!!int abc"),
                         ("NUL escape in a string", '"a\\0b"'),
                         ("escape escape in a string", '"\\e[2J"'),
                         ("line break in a name", '"a\\nb"')):
        yield label, _set(good, "name", value)[0].encode(), name_line
    yield "complex key", head + b"? [a, b]\n: 1\n" + tail, line_after


class _Builder:
    """Writes cases into ``out`` (one folder per case) and describes how to run them."""

    def __init__(self, out: Path) -> None:
        self.out = out
        self.cases: list[Case] = []
        self._n = 0

    def _dir(self, kind: str) -> Path:
        self._n += 1
        d = self.out / kind / f"{self._n:05d}"
        d.mkdir(parents=True, exist_ok=True)
        return d

    def broken(self, kind: str, name: str, data: str | bytes, line: int | None, *,
               reader: bool = False, via: str | None = None) -> None:
        """A broken file of ``kind``, run through a command that reads it."""
        d = self._dir(kind)
        target = d / f"broken-{kind[:-1]}.yaml"
        target.write_bytes(data.encode() if isinstance(data, str) else data)
        via = via or ("fly" if self._n % 2 else "simulate")
        if kind == "sessions":
            argv: tuple[str, ...] = ("fly", str(target))
        elif via == "fly":
            key = {"vehicles": "vehicle", "missions": "mission",
                   "disturbances": "disturbances"}[kind]
            session = _shipped("sessions", "exp1-emulated")
            indent = "  " if kind == "disturbances" else ""
            session = re.sub(rf"(?m)^{indent}{key}: .*$", f"{indent}{key}: {target.name}", session)
            (d / "session.yaml").write_text(session)
            argv = ("fly", str(d / "session.yaml"))
        else:
            option = {"vehicles": "--vehicle", "missions": None, "disturbances": "--preset"}[kind]
            argv = ("simulate", "--duration", "0.01")
            argv += (str(target),) if option is None else (option, str(target))
        self.cases.append(Case(kind, name, argv, str(target), line, reader))

    def session_error(self, name: str, session_text: str, line: int | None,
                      extra: dict[str, str] | None = None, *, blame: str = "session") -> None:
        """A session (with helper files) whose error is in the file named by ``blame``."""
        shipped = "/" in blame  # the error is in a shipped mission file
        d = self._dir("sessions" if blame == "session" else
                      "missions" if shipped else f"{blame}s")
        path = d / "session.yaml"
        path.write_text(session_text)
        for fname, text in (extra or {}).items():
            (d / fname).write_text(text)
        if blame == "session":
            file = str(path)
        elif shipped:
            file, blame = blame, "mission"
        else:
            file = str(d / f"{blame}.yaml")
        kind = "sessions" if blame == "session" else f"{blame}s"
        self.cases.append(Case(kind, name, ("fly", str(path)), file, line, False))

    def simulate_error(self, kind: str, name: str, files: dict[str, str], argv: list[str],
                       blame: str, line: int | None) -> None:
        d = self._dir(kind)
        for fname, text in files.items():
            (d / fname).write_text(text)
        full = ("simulate", "--duration", "0.01",
                *[str(d / a) if a in files else a for a in argv])
        self.cases.append(Case(kind, name, full, str(d / blame), line, False))


def _value_cases(b: _Builder, kind: str) -> None:
    rotation = 0
    for n_base, base in enumerate(BASES[kind]):
        good = _shipped(kind, base)
        for path, node in _leaves(good):
            if not _is_number(node):
                continue
            # every number gets two of the blanket values in the first file (the next two
            # on the next number), one in turn in the second: each value class meets every
            # kind of field while the corpus stays small enough to run in a test
            count = 2 if n_base == 0 else 1
            values = tuple(BLANKET[(rotation + k) % len(BLANKET)] for k in range(count))
            rotation += count
            for value in values:
                b.broken(kind, f"{base}: {path} = {value}", _splice(good, node, value),
                         node.start_mark.line + 1)
        for path, values in ABSURD[kind].items():
            for value in values:
                try:
                    text, line = _set(good, path, value)
                except KeyError:
                    continue  # e.g. a key only the first base file has
                # a cross-field check may point at the partner key: the file is what counts
                b.broken(kind, f"{base}: {path} = {value} (absurd)", text, None)
        for path, values in LITERALS[kind].items():
            for value in values:
                try:
                    text, line = _set(good, path, value)
                except KeyError:
                    continue
                b.broken(kind, f"{base}: {path} = {value} (literal)", text, line)


def _key_cases(b: _Builder, kind: str) -> None:
    good = _shipped(kind, BASES[kind][0])
    lines = good.splitlines(keepends=True)
    schema_line = _line(good, "schema:")
    version_line = _line(good, "version:")
    b.broken(kind, "wrong schema", good.replace(f"schema: {SCHEMAS[kind]}", "schema: "
             + next(s for k, s in SCHEMAS.items() if k != kind)), schema_line)
    b.broken(kind, "schema missing", good.replace(f"schema: {SCHEMAS[kind]}\n", ""), None)
    b.broken(kind, "version 2", good.replace("version: 1", "version: 2"), version_line)
    b.broken(kind, "version as text", good.replace("version: 1", 'version: "1"'), version_line)
    b.broken(kind, "version true", good.replace("version: 1", "version: true"), version_line)
    b.broken(kind, "version missing", good.replace("version: 1\n", ""), None)
    b.broken(kind, "name as a list", _set(good, "name", "[a, b]")[0], _line(good, "name:"))
    b.broken(kind, "name as a mapping", _set(good, "name", "{a: 1}")[0], _line(good, "name:"))
    b.broken(kind, "name empty", _set(good, "name", "")[0], _line(good, "name:"))
    # every key of the file in turn: renamed (unknown), doubled (duplicate)
    for i, text_line in enumerate(lines):
        m = re.match(r"^(\s*)(-\s+)?([a-z_]+):", text_line)
        if m is None or m.group(3) in ("schema", "version"):
            continue
        typo = text_line.replace(f"{m.group(3)}:", f"{m.group(3)}x:", 1)
        b.broken(kind, f"unknown key {m.group(3)}x (line {i + 1})",
                 "".join([*lines[:i], typo, *lines[i + 1:]]), i + 1)
        if m.group(2) is None and not text_line.rstrip().endswith(":"):
            dup = m.group(1) + text_line[len(m.group(1)):]
            b.broken(kind, f"duplicate key {m.group(3)} (line {i + 1})",
                     "".join([*lines[:i + 1], dup, *lines[i + 1:]]), i + 2)
    # required keys removed (keys with a default are not errors when missing)
    required = {"vehicles": ("mass_kg:", "  max_spin_hz:", "  kp_pos:", "geometry:"),
                "missions": ("start_pos_w_m:", "    duration_s: 5.0", "    height_m:",
                             "segments:"),
                "disturbances": ("name:",),
                "sessions": ("mission:", "  kind: emulated", "name:")}[kind]
    for prefix in required:
        i = next(j for j, text_line in enumerate(lines) if text_line.startswith(prefix))
        end = i + 1
        if lines[i].rstrip().endswith(":"):  # a whole section
            while end < len(lines) and lines[end].startswith("  "):
                end += 1
        b.broken(kind, f"missing {prefix.strip()}", "".join([*lines[:i], *lines[end:]]), None)


def _reader_cases(b: _Builder, kind: str) -> None:
    good = _shipped(kind, BASES[kind][0])
    for name, data, line in _reader_garbage(good):
        b.broken(kind, name, data, line, reader=True)


def _reference_and_cross_cases(b: _Builder) -> None:
    session = _shipped("sessions", "exp1-emulated")
    mission = _shipped("missions", "exp1-hover-tilt-steps")
    vehicle = _shipped("vehicles", "fasthex")
    vl, ml = _line(session, "vehicle:"), _line(session, "mission:")
    dl = _line(session, "disturbances:")

    def sess(**subs: str) -> str:
        text = session
        for key, value in subs.items():
            text = re.sub(rf"(?m)^(\s*){key}: .*$", rf"\g<1>{key}: {value}", text)
        return text

    # references that do not resolve: reported at the session's line of the key
    for ref in ("fasthex-maxi", "nope", "../fasthex", "missing.yaml", "sub/dir/v.yaml"):
        b.session_error(f"vehicle reference {ref!r}", sess(vehicle=ref), vl)
        b.session_error(f"mission reference {ref!r}", sess(mission=ref), ml)
        b.session_error(f"disturbances reference {ref!r}", sess(disturbances=ref), dl)
    b.session_error("vehicle reference names a mission", sess(vehicle="exp1-hover-tilt-steps"),
                    vl)
    b.session_error("mission reference is a folder", sess(mission="."), ml)
    # a referenced file of the wrong kind: its own error
    b.session_error("vehicle file is a mission", sess(vehicle="vehicle.yaml"),
                    _line(mission, "schema:"), {"vehicle.yaml": mission}, blame="vehicle")
    b.session_error("mission file is a vehicle", sess(mission="mission.yaml"),
                    _line(vehicle, "schema:"), {"mission.yaml": vehicle}, blame="mission")

    # the mission against the session's geofence (+-2.5 m, z -0.5..2.5, 0.1 m margin)
    def with_segment(seg: str, text: str = mission) -> str:
        return text.replace("  - kind: land\n", seg + "  - kind: land\n", 1)

    goto_line = _line(with_segment("  - kind: goto\n"), "- kind: goto")
    for pos in ("[2.45, 0.0, 1.0]", "[0.0, -2.45, 1.0]", "[0.0, 0.0, 2.45]", "[50.0, 0.0, 1.0]",
                "[0.0, 0.0, -0.45]", "[99.0, 99.0, 99.0]", "[-3.0, 0.0, 1.0]"):
        m = with_segment(f"  - kind: goto\n    duration_s: 60.0\n    pos_w_m: {pos}\n")
        far = "99" in pos  # the 6 s landing from 99 m is refused first, in the same file
        b.session_error(f"waypoint {pos} outside the geofence", sess(mission="mission.yaml"),
                        None if far else goto_line + 2, {"mission.yaml": m}, blame="mission")
    for amp in ("2.5", "3.0", "9.0"):
        m = with_segment(f"  - kind: sine\n    duration_s: 60.0\n    axis: x\n"
                         f"    amplitude_m: {amp}\n    frequency_hz: 0.01\n")
        b.session_error(f"x sine of {amp} m outside the geofence", sess(mission="mission.yaml"),
                        _line(m, f"amplitude_m: {amp}"), {"mission.yaml": m}, blame="mission")
    for start in ("[2.45, 0.0, 0.1]", "[-2.6, -0.05, 0.1]", "[0.0, 0.0, -0.45]"):
        m = mission.replace("start_pos_w_m: [-0.14, -0.05, 0.1]", f"start_pos_w_m: {start}")
        b.session_error(f"start {start} outside the geofence", sess(mission="mission.yaml"),
                        _line(m, "start_pos_w_m"), {"mission.yaml": m}, blame="mission")
    for height in ("2.45", "2.9", "20.0"):
        m = mission.replace("height_m: 1.0", f"height_m: {height}").replace(
            "duration_s: 5.0", "duration_s: 30.0", 1)
        fast = height != "2.45"  # their 6 s landings touch down too fast: refused first
        b.session_error(f"takeoff to {height} m above the geofence",
                        sess(mission="mission.yaml"), None if fast else _line(m, "height_m"),
                        {"mission.yaml": m}, blame="mission")
    # a narrower fence in the session makes the shipped mission leave it
    for fmin, fmax in (("[-2.5, -2.5, -0.5]", "[2.5, 2.5, 1.0]"),
                       ("[-0.1, -2.5, -0.5]", "[2.5, 2.5, 2.5]"),
                       ("[-2.5, -2.5, 0.15]", "[2.5, 2.5, 2.5]")):
        b.session_error(f"fence {fmin}..{fmax} excludes the mission",
                        sess(geofence_min_m=fmin, geofence_max_m=fmax), None,
                        blame=str(config_root() / "missions" / "exp1-hover-tilt-steps.yaml"))

    # alpha outside the vehicle's tilt range: an error, not a clamp
    steps_line = _line(mission, "values_deg:")
    for values in ("[0.0, 40.0, 0.0, 30.0]", "[0.0, 30.0, 0.0, 35.5]", "[0.0, 89.0, 0.0, 0.0]"):
        m = mission.replace("values_deg: [0.0, 30.0, 0.0, 30.0]", f"values_deg: {values}")
        b.session_error(f"alpha steps {values} beyond 35 deg", sess(mission="mission.yaml"),
                        steps_line, {"mission.yaml": m}, blame="mission")
        b.simulate_error("missions", f"simulate: alpha steps {values} beyond 35 deg",
                         {"mission.yaml": m}, ["mission.yaml", "--vehicle", "fasthex"],
                         "mission.yaml", steps_line)
    mini_alpha = mission.replace("values_deg: [0.0, 30.0, 0.0, 30.0]",
                                 "values_deg: [0.0, 31.0, 0.0, 30.0]")
    b.simulate_error("missions", "simulate: alpha 31 deg on fasthex-mini (max 30)",
                     {"mission.yaml": mini_alpha}, ["mission.yaml", "--vehicle", "fasthex-mini"],
                     "mission.yaml", steps_line)
    b.session_error("alpha 31 deg on fasthex-mini (max 30)",
                    sess(mission="mission.yaml", vehicle="fasthex-mini"), steps_line,
                    {"mission.yaml": mini_alpha}, blame="mission")
    ramp = _shipped("missions", "exp2a-sine-translation")
    for to in ("36.0", "60.0"):
        m = ramp.replace("to_deg: 30.0", f"to_deg: {to}")
        b.simulate_error("missions", f"simulate: alpha ramp to {to} deg",
                         {"mission.yaml": m}, ["mission.yaml"], "mission.yaml",
                         _line(m, "to_deg"))
    # a fixed-tilt vehicle (20 deg) cannot fly a mission that asks for alpha 0 or 30
    fixed = vehicle.replace("max_tilt_deg: 35.0           # |alpha| in [0, 35] deg",
                            "max_tilt_deg: 20.0\n  min_tilt_deg: 20.0").replace(
                                "max_rate_deg_s: 10.0", "max_rate_deg_s: 0.0")
    b.simulate_error("missions", "simulate: alpha 0 on a 20 deg fixed-tilt vehicle",
                     {"mission.yaml": mission, "vehicle.yaml": fixed},
                     ["mission.yaml", "--vehicle", "vehicle.yaml"], "mission.yaml",
                     _line(mission, "value_deg: 0.0"))
    b.session_error("alpha 0 on a 20 deg fixed-tilt vehicle", sess(vehicle="vehicle.yaml"),
                    _line(mission, "value_deg: 0.0"), {"vehicle.yaml": fixed},
                    blame=str(config_root() / "missions" / "exp1-hover-tilt-steps.yaml"))
    # fixed-tilt declarations that do not hold together
    for name, text in (
            ("fixed tilt with a rate", fixed.replace("max_rate_deg_s: 0.0",
                                                     "max_rate_deg_s: 10.0")),
            ("tilt range with rate 0", vehicle.replace("max_rate_deg_s: 10.0",
                                                       "max_rate_deg_s: 0")),
            ("min tilt above max tilt", vehicle.replace(
                "mechanical_limit_deg: 35.0", "mechanical_limit_deg: 35.0\n  min_tilt_deg: 36")),
            ("rate beyond the servo through the worms", vehicle.replace(
                "max_rate_deg_s: 10.0", "max_rate_deg_s: 100.0"))):
        b.broken("vehicles", name, text, None)

    # takeoff below or at the start
    for height in ("0.1", "0.12", "0.05"):
        m = mission.replace("height_m: 1.0", f"height_m: {height}")
        b.simulate_error("missions", f"takeoff to {height} m from a 0.1 m start",
                         {"mission.yaml": m}, ["mission.yaml"], "mission.yaml",
                         _line(m, "height_m"))
    high_start = mission.replace("start_pos_w_m: [-0.14, -0.05, 0.1]",
                                 "start_pos_w_m: [-0.14, -0.05, 1.5]")
    b.simulate_error("missions", "takeoff to 1 m from a 1.5 m start",
                     {"mission.yaml": high_start}, ["mission.yaml"], "mission.yaml",
                     _line(high_start, "height_m"))
    # a climb the rotors cannot lift: 5.77 * 0.9 m / (0.75 s)^2 = 9.2 m/s^2 > 8.1 on fasthex
    quick = mission.replace("duration_s: 5.0\n    height_m: 1.0",
                            "duration_s: 0.75\n    height_m: 1.0", 1)
    for via in ("simulate", "fly"):
        if via == "simulate":
            b.simulate_error("missions", "takeoff faster than the thrust allows",
                             {"mission.yaml": quick}, ["mission.yaml"], "mission.yaml",
                             _line(quick, "duration_s: 0.75"))
        else:
            b.session_error("takeoff faster than the thrust allows (session)",
                            sess(mission="mission.yaml"), _line(quick, "duration_s: 0.75"),
                            {"mission.yaml": quick}, blame="mission")
    # motions no vehicle can follow
    for seg, field in (("  - kind: goto\n    duration_s: 0.5\n    pos_w_m: [2.0, 0.0, 1.0]\n",
                        "pos_w_m"),
                       ("  - kind: sine\n    duration_s: 10.0\n    axis: x\n"
                        "    amplitude_m: 1.0\n    frequency_hz: 5.0\n", "amplitude_m"),
                       ("  - kind: attitude_sine\n    duration_s: 10.0\n    axis: roll\n"
                        "    amplitude_deg: 80.0\n    frequency_hz: 8.0\n", "amplitude_deg"),
                       ("  - kind: hold\n    duration_s: 5.0\n    alpha: {kind: ramp, "
                        "from_deg: 0, to_deg: 10, end_s: 9.0}\n", "end_s"),
                       ("  - kind: sine\n    duration_s: 4.0\n    axis: y\n"
                        "    amplitude_m: 0.1\n    frequency_hz: 0.5\n    fade_in_s: 3.0\n"
                        "    fade_out_s: 3.0\n", "fade_in_s")):
        m = with_segment(seg)
        b.simulate_error("missions", f"infeasible segment ({field})", {"mission.yaml": m},
                         ["mission.yaml"], "mission.yaml", None)
    # the emulated MoCap against the session's timeouts and the estimator's history
    preset = _shipped("disturbances", "paper-calibrated")
    for rate, stale in (("10.0", None), ("15.0", "0.06"), ("20.0", None)):
        p = preset.replace("mocap_rate_hz: 100.0", f"mocap_rate_hz: {rate}")
        text = sess(disturbances="preset.yaml")
        if stale is not None:
            text = text.replace("estimator:\n", f"estimator:\n  mocap_stale_s: {stale}\n")
        b.session_error(f"MoCap at {rate} Hz vs the stale timeout", text, None,
                        {"preset.yaml": p})
    p = preset.replace("mocap_latency_s: 0.01", "mocap_latency_s: 0.3")
    b.session_error("MoCap latency beyond the estimator's history",
                    sess(disturbances="preset.yaml"), None, {"preset.yaml": p})
    # estimator numbers a session may set (absent from the shipped sessions)
    est_line = _line(session, "estimator:") + 1
    for key, value in (("gate_nis", "1e6"), ("gate_nis", "0"), ("sigma_beta", "1e9"),
                       ("init_pos_sigma_m", "1e4"), ("min_variance", "1"), ("mass_kg", "0"),
                       ("mocap_stale_s", "0"), ("history_s", "1e-12"), ("init_rest_s", "1e5"),
                       ("force_walk_n_sqrt_s", "1e9"), ("max_pos_sigma_m", ".inf"),
                       ("diverged_att_sigma_deg", "720")):
        b.session_error(f"estimator.{key} = {value} (absurd)",
                        session.replace("estimator:\n", f"estimator:\n  {key}: {value}\n", 1),
                        est_line)
    b.session_error("IMU timeout shorter than two IMU periods",
                    sess(imu_timeout_s="0.002"), _line(session, "imu_timeout_s"))
    b.session_error("IMU timeout of one period at 500 Hz", sess(imu_timeout_s="0.003"),
                    _line(session, "imu_timeout_s"))
    b.session_error("geofence 0.2 m wide", sess(geofence_min_m="[-0.1, -2.5, -0.5]",
                                                 geofence_max_m="[0.1, 2.5, 2.5]"), None)
    b.session_error("fault that does not parse",
                    session.replace("  seed: 1\n", "  seed: 1\n  faults: [meteor@3]\n"), None)
    b.session_error("corruption 50 %",
                    session.replace("  seed: 1\n", "  seed: 1\n  corrupt_prob: 0.5\n"), None)
    hw = _shipped("sessions", "hardware-template")
    b.session_error("hardware URI without a scheme", hw.replace(
        "flight_ctrl_uri: serial:///dev/ttyUSB0?baud=500000", "flight_ctrl_uri: /dev/ttyUSB0"),
        _line(hw, "flight_ctrl_uri"))
    b.session_error("hardware backend with an emulated key", hw.replace(
        "  imu_rate_hz: 500.0", "  imu_rate_hz: 500.0\n  seed: 3"), _line(hw, "imu_rate_hz") + 1)


def generate(out: Path) -> list[Case]:
    """Write the corpus into ``out`` (created) and return its cases."""
    b = _Builder(out)
    for kind in KINDS:
        _value_cases(b, kind)
        _key_cases(b, kind)
        _reader_cases(b, kind)
    _reference_and_cross_cases(b)
    return b.cases


class FlightStartedError(AssertionError):
    """A case got past validation: a flight (and its emulator) would start."""


@contextlib.contextmanager
def no_flights() -> Iterator[None]:
    """While active, a flight session refuses to start (validation must come first)."""
    from groundstation.session import FlightSession

    def refuse(self: object, *args: object, **kwargs: object) -> None:
        raise FlightStartedError("the config passed validation; a flight would start")

    original = FlightSession.run
    FlightSession.run = refuse  # type: ignore[assignment,method-assign]
    try:
        yield
    finally:
        FlightSession.run = original  # type: ignore[method-assign]


def run_case(case: Case, main: Callable[[list[str]], int]) -> Outcome:
    """Run one case through ``main`` (the CLI entry point) and judge its stderr."""
    err = io.StringIO()
    out = io.StringIO()
    code: int | None = None
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(out):
            code = main(list(case.argv))
    except SystemExit as exc:  # argparse
        code = exc.code if isinstance(exc.code, int) else 1
    except Exception as exc:  # a traceback would have reached the user
        return Outcome(case, None, err.getvalue(), f"raised {type(exc).__name__}: {exc}")
    return Outcome(case, code, err.getvalue(), judge(case, code, err.getvalue()))


def judge(case: Case, code: int | None, stderr: str) -> str:
    """Empty when ``stderr``/``code`` are what ``case`` must give, else what is wrong."""
    if code != 2:
        return f"exit {code}, expected 2"
    lines = stderr.splitlines()
    if len(lines) != 1 or not stderr.endswith("\n"):
        return f"expected exactly one stderr line, got {len(lines)}"
    if "Traceback" in stderr:
        return "traceback"
    m = LINE_RE.match(lines[0])
    if m is None:
        return f"not FILE:LINE: [KEY: ]expectation: {lines[0]!r}"
    if m.group("file") != case.file:
        return f"names {m.group('file')}, expected {case.file}"
    if case.line is not None and int(m.group("line")) != case.line:
        return f"names line {m.group('line')}, expected {case.line}"
    if not case.reader and m.group("key") is None:
        return f"no KEY in {lines[0]!r}"
    return ""


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", nargs="?", default=None, help="corpus folder (default: a temp dir)")
    ap.add_argument("--keep", action="store_true", help="keep the corpus folder")
    ap.add_argument("-v", "--verbose", action="store_true", help="print every failing case")
    args = ap.parse_args(argv)
    from groundstation.cli import main as cli_main

    with contextlib.ExitStack() as stack:
        if args.out is None:
            out = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="config-corpus-"))
                       if not args.keep else tempfile.mkdtemp(prefix="config-corpus-"))
        else:
            out = Path(args.out)
        cases = generate(out)
        with no_flights():
            outcomes = [run_case(c, cli_main) for c in cases]
    print(f"{'kind':14s}{'cases':>8s}{'pass':>8s}{'rate':>9s}")
    for kind in KINDS:
        mine = [o for o in outcomes if o.case.kind == kind]
        good = sum(o.ok for o in mine)
        print(f"{kind:14s}{len(mine):8d}{good:8d}{good / max(len(mine), 1):9.1%}")
    good = sum(o.ok for o in outcomes)
    print(f"{'all':14s}{len(outcomes):8d}{good:8d}{good / max(len(outcomes), 1):9.1%}")
    for o in outcomes:
        if not o.ok and args.verbose:
            print(f"FAIL [{o.case.kind}] {o.case.name}: {o.problem}\n    {o.stderr.strip()}")
    return 0 if good == len(outcomes) else 1


if __name__ == "__main__":
    sys.exit(main())

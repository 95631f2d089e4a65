"""Malformed config files are refused with one precise message: file, line, key path and what
was expected; no traceback reaches the user."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from config import find_config
from config.schema import ConfigError
from groundstation.cli import main
from groundstation.configs import load_vehicle

GOOD = find_config("vehicles", "fasthex").read_text()


def _line_of(text: str, fragment: str) -> int:
    return next(i for i, line in enumerate(text.splitlines(), 1) if fragment in line)


def _write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "vehicle.yaml"
    path.write_text(text)
    return path


# (name, edit applied to the good file, line fragment the error points at, key, message)
CASES = [
    ("unknown key", ("mass_kg: 3.1", "mass_kgg: 3.1"), "mass_kgg", "mass_kgg",
     "unknown key; expected one of: controller, description, geometry, gravity_m_s2, "
     "inertia_diag_kg_m2, mass_kg, name, rotors, tilt"),
    ("wrong type", ("mass_kg: 3.1", "mass_kg: heavy"), "mass_kg", "mass_kg",
     "expected a number >= 0.1 and <= 100, got 'heavy'"),
    ("out of range", ("mass_kg: 3.1", "mass_kg: -3"), "mass_kg", "mass_kg",
     "expected a number >= 0.1 and <= 100, got -3"),
    ("bool for a number", ("mass_kg: 3.1", "mass_kg: yes"), "mass_kg", "mass_kg",
     "expected a number >= 0.1 and <= 100, got True"),
    ("quoted number", ("mass_kg: 3.1", 'mass_kg: "3.1"'), "mass_kg", "mass_kg",
     "expected a number >= 0.1 and <= 100, got '3.1'"),
    ("not finite", ("mass_kg: 3.1", "mass_kg: .nan"), "mass_kg", "mass_kg",
     "expected a finite number, got nan"),
    ("min spin >= max spin", ("min_spin_hz: 16.0", "min_spin_hz: 110.0"), "min_spin_hz",
     "rotors.min_spin_hz", "must be below max_spin_hz (102 Hz), got 110"),
    ("tilt beyond the mechanical limit", ("max_tilt_deg: 35.0", "max_tilt_deg: 40.0"),
     "max_tilt_deg", "tilt.max_tilt_deg", "exceeds the mechanical limit (35 deg), got 40"),
    ("short list", ("[0.089, 0.091, 0.164]", "[0.089, 0.091]"), "inertia_diag_kg_m2",
     "inertia_diag_kg_m2", "expected a list of 3 values, got 2"),
    ("mapping for a value", ("name: fasthex", "name:\n  first: fast\n  second: hex"),
     "first: fast", "name", "expected a single value, got a mapping"),
    ("integer expected", ("bisection_iterations: 20", "bisection_iterations: 20.5"),
     "bisection_iterations", "controller.bisection_iterations",
     "expected an integer >= 1 and <= 60, got 20.5"),
    ("wrong schema", ("schema: fasthex.vehicle", "schema: fasthex.session"), "schema:", "schema",
     "expected 'fasthex.vehicle', got 'fasthex.session' (wrong kind of file?)"),
    ("unsupported version", ("version: 1", "version: 7"), "version:", "version",
     "unsupported version 7; this fasthex reads 1"),
    ("duplicate key", ("mass_kg: 3.1", "mass_kg: 3.1\nmass_kg: 3.2"), "mass_kg: 3.2", "mass_kg",
     "duplicate key"),
    ("physically impossible inertia", ("[0.089, 0.091, 0.164]", "[0.01, 0.01, 0.164]"),
     "inertia_diag_kg_m2", "inertia_diag_kg_m2",
     "principal moments violate the triangle inequality (not a physical body)"),
    # the mirrored spin layout moves the paper's -3.56 deg yaw rank loss to +3.56 deg, inside
    # the tilt range (controller.params: VehicleParams._check_spin_layout)
    ("clockwise propeller 1 with tilts past the yaw cancellation",
     ("first_rotor_ccw: true", "first_rotor_ccw: false"), "first_rotor_ccw",
     "rotors.first_rotor_ccw",
     "propeller 1 clockwise turns the tilted thrust's yaw torque against the drag torque: they "
     "cancel at atan(c_tau/l) = 3.56 deg (no yaw authority) and above it the rotors' spin-up "
     "reaction yaws the body the wrong way first, which the paper's attitude law cannot fly; "
     "expected true (the paper's layout), or tilt.max_tilt_deg below 3.56 deg, got false with "
     "tilts up to 35 deg"),
    ("too heavy to fly", ("mass_kg: 3.1", "mass_kg: 5.0"), "mass_kg", "mass_kg",
     "weight 49.1 N needs >= 20 % thrust margin, but the rotors lift at most 50.6 N at the "
     "largest tilt"),
    # the tilt, not the mass, leaves no lift: at 90 deg no thrust is vertical
    ("tilt that leaves no lift", ("max_tilt_deg: 35.0           # |alpha| in [0, 35] deg\n"
                                  "  mechanical_limit_deg: 35.0",
                                  "max_tilt_deg: 90.0\n  mechanical_limit_deg: 90.0"),
     "max_tilt_deg", "tilt.max_tilt_deg",
     "at 90 deg the rotors lift at most 0.0 N, but the weight 30.4 N needs >= 20 % thrust "
     "margin; expected at most 53.8 deg"),
]


@pytest.mark.parametrize(("name", "edit", "fragment", "key", "message"), CASES,
                         ids=[c[0] for c in CASES])
def test_that_a_malformed_vehicle_file_gives_its_precise_message(
        tmp_path: Path, name: str, edit: tuple[str, str], fragment: str, key: str,
        message: str) -> None:
    # Fixture
    assert edit[0] in GOOD, name
    text = GOOD.replace(edit[0], edit[1], 1)
    path = _write(tmp_path, text)
    # Test
    with pytest.raises(ConfigError) as info:
        load_vehicle(path)
    # Assert
    line = _line_of(text, fragment) if name != "missing" else None
    assert str(info.value) == f"{path}:{line}: {key}: {message}"


def test_that_a_missing_key_names_the_enclosing_section(tmp_path: Path) -> None:
    text = GOOD.replace("  drag_coeff_m: 1.9e-2             # c_f^tau\n", "")
    path = _write(tmp_path, text)
    with pytest.raises(ConfigError) as info:
        load_vehicle(path)
    assert str(info.value) == (f"{path}:{_line_of(text, 'min_spin_hz')}: rotors.drag_coeff_m: "
                               "missing key; expected a number > 0 and <= 1")


def test_that_broken_yaml_syntax_gives_the_line(tmp_path: Path) -> None:
    text = GOOD.replace("mass_kg: 3.1", "mass_kg: [3.1")
    path = _write(tmp_path, text)
    with pytest.raises(ConfigError) as info:
        load_vehicle(path)
    assert str(info.value).startswith(f"{path}:")
    assert "not valid YAML" in str(info.value)
    assert info.value.line is not None and info.value.line >= _line_of(text, "mass_kg")


@pytest.mark.parametrize("key", ['""', '"  "', r'"\n\n  "', r'"a\rb"'])
def test_that_an_empty_or_multi_line_key_is_named_on_one_line(tmp_path: Path, key: str) -> None:
    # found by fuzzing: "tune.\n: unknown key" was a message over two lines
    path = _write(tmp_path, GOOD.replace("mass_kg: 3.1", f"mass_kg: 3.1\n{key}: 1"))
    with pytest.raises(ConfigError) as info:
        load_vehicle(path)
    message = str(info.value)
    assert "\n" not in message and "keys must be names, got " in message


def test_that_an_empty_file_is_refused(tmp_path: Path) -> None:
    path = _write(tmp_path, "# nothing here\n")
    with pytest.raises(ConfigError) as info:
        load_vehicle(path)
    assert str(info.value) == (f"{path}:1: empty file; expected a mapping with "
                               "'schema: fasthex.vehicle' and 'version'")


def test_that_yaml_exponents_without_a_dot_are_numbers(tmp_path: Path) -> None:
    # YAML 1.1 reads 4e-6 as text; the loader takes plain scalars Python can read.
    path = _write(tmp_path, GOOD.replace("tikhonov_k1: 4.0e-6", "tikhonov_k1: 4e-6"))
    assert load_vehicle(path).controller.tikhonov_k1 == 4e-6


def test_that_an_unknown_vehicle_name_lists_the_shipped_ones() -> None:
    with pytest.raises(ConfigError) as info:
        load_vehicle("nope")
    assert str(info.value) == ("nope: no such vehicle; shipped vehicles: fasthex, "
                               "fasthex-gust-recovery, fasthex-mini")


def test_that_the_cli_prints_one_line_and_exits_2(tmp_path: Path,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    path = _write(tmp_path, GOOD.replace("mass_kg: 3.1", "mass_kg: -3"))
    assert main(["analyze", "--vehicle", str(path)]) == 2
    err = capsys.readouterr().err
    assert err == (f"fasthex: config error: {path}:{_line_of(GOOD, 'mass_kg')}: mass_kg: "
                   "expected a number >= 0.1 and <= 100, got -3\n")


def test_that_the_installed_command_shows_no_traceback(tmp_path: Path) -> None:
    path = _write(tmp_path, GOOD.replace("max_tilt_deg: 35.0", "max_tilt_deg: 40.0"))
    proc = subprocess.run([sys.executable, "-m", "groundstation", "analyze", "--vehicle",
                           str(path)], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr
    assert proc.stderr.strip().endswith(
        "tilt.max_tilt_deg: exceeds the mechanical limit (35 deg), got 40")


@pytest.mark.parametrize(("data", "line", "message"), [
    (GOOD.replace("mass_kg: 3.1", "mass_kg: 3.1\x00").encode(), 7,
     "control character U+0000; expected plain text"),
    (GOOD.encode() + b"# caf\xe9\n", GOOD.count("\n") + 1,
     "invalid UTF-8 (byte 0xe9); expected a UTF-8 text file"),
    (GOOD.replace("  arm_length_m", "\tarm_length_m").encode(), 11,
     "tab in the indentation; YAML indents with spaces"),
    (("a: " + "[" * 100 + "]" * 100 + "\n").encode(), 1,
     "nested too deeply; expected at most 16 levels"),
    (b"a: &a [x, x, x, x]\nb: [*a, *a, *a, *a]\n", 1,
     "anchors and aliases (&name, *name) are not supported; expected plain values"),
    ((GOOD + "---\nschema: fasthex.vehicle\n").encode(), GOOD.count("\n") + 1,
     "a second YAML document ('---'); expected one document per file"),
    (GOOD.encode() + b"#" * (300 * 1024), 1, "file too large; expected at most 256 KiB of YAML"),
])
def test_that_reader_level_garbage_is_located_without_a_key(
        tmp_path: Path, data: bytes, line: int, message: str) -> None:
    path = tmp_path / "vehicle.yaml"
    path.write_bytes(data)
    with pytest.raises(ConfigError) as info:
        load_vehicle(path)
    assert str(info.value) == f"{path}:{line}: {message}"


@pytest.mark.parametrize(("value", "message"), [
    ("2021-13-45", "cannot read this value (month must be in 1..12)"),
    ("!!int abc", "cannot read this value (invalid literal for int() with base 10: 'abc')"),
    ('"fast\\0hex"', "expected one line of plain text, got U+0000"),
])
def test_that_values_pyyaml_cannot_build_are_located_at_their_key(
        tmp_path: Path, value: str, message: str) -> None:
    path = _write(tmp_path, GOOD.replace("name: fasthex", f"name: {value}"))
    with pytest.raises(ConfigError) as info:
        load_vehicle(path)
    assert str(info.value) == f"{path}:{_line_of(GOOD, 'name: fasthex')}: name: {message}"


@pytest.mark.parametrize(("edit", "key", "message"), [
    (("kv_pos: [14.14, 14.14, 14.14]", "kv_pos: [0.5, 14.14, 14.14]"), "controller.kv_pos[0]",
     "gives a damping ratio of 0.0201; expected 0.2..5 (near 0 the vehicle oscillates)"),
    (("tikhonov_k1: 4.0e-6", "tikhonov_k1: 0"), "controller.tikhonov_k1",
     "expected a number > 0 and <= 0.01, got 0"),
    (("ki_att: [1.0, 1.0, 1.0]", "ki_att: [300.0, 1.0, 1.0]"), "controller.ki_att[0]",
     "makes the loop unstable: expected < d k / (2 J) = 126, got 300"),
    (("kp_pos: [50.0, 50.0, 50.0]", "kp_pos: [5000.0, 50.0, 50.0]"), "controller.kp_pos[0]",
     "gives a natural frequency sqrt(k/m) of 40.2 rad/s; expected 0.5..30 rad/s"),
    (("thrust_coeff_n_per_hz2: 9.9e-4", "thrust_coeff_n_per_hz2: 9.9e-2"),
     "rotors.thrust_coeff_n_per_hz2", "means a thrust coefficient C_T = c_f/(rho D^4) = 9.34 "
     "for a 0.305 m propeller; real propellers have 0.02..0.4"),
])
def test_that_physically_absurd_vehicles_are_refused_with_the_reason(
        tmp_path: Path, edit: tuple[str, str], key: str, message: str) -> None:
    assert edit[0] in GOOD
    path = _write(tmp_path, GOOD.replace(*edit))
    with pytest.raises(ConfigError) as info:
        load_vehicle(path)
    assert (info.value.key, info.value.message) == (key, message)


def test_that_a_clockwise_propeller_1_is_accepted_below_the_yaw_cancellation(
        tmp_path: Path) -> None:
    # Fixture: tilts up to 3.5 deg < atan(c_tau/l) = 3.56 deg: the drag torque still dominates
    # the yaw and the rotors' spin-up reaction pushes the same way (no right-half-plane zero)
    text = GOOD.replace("first_rotor_ccw: true", "first_rotor_ccw: false").replace(
        "max_tilt_deg: 35.0", "max_tilt_deg: 3.5")
    # Test
    params = load_vehicle(_write(tmp_path, text))
    # Assert
    assert not params.rotors.first_rotor_ccw and params.tilt.max_tilt_deg == 3.5

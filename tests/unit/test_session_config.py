"""Session files: the shipped ones load; malformed ones are refused with a precise message
before anything is opened (including errors in the files a session refers to)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from config import available, find_config
from config.schema import ConfigError
from groundstation.session_config import EmulatedBackend, HardwareBackend, load_session

GOOD = find_config("sessions", "exp1-emulated").read_text()


def _line_of(text: str, fragment: str) -> int:
    return next(i for i, line in enumerate(text.splitlines(), 1) if fragment in line)


def test_that_every_shipped_session_loads() -> None:
    names = available("sessions")
    assert {"exp1-emulated", "exp2a-emulated", "exp2b-emulated", "hardware-template"} <= set(names)
    for name in names:
        session = load_session(name)
        assert session.name == name
    hw = load_session("hardware-template").backend
    assert isinstance(hw, HardwareBackend) and hw.flight_ctrl_uri.startswith("serial://")
    emu = load_session("exp1-emulated").backend
    assert isinstance(emu, EmulatedBackend) and emu.clock == "lockstep"


@pytest.mark.parametrize(("old", "new", "fragment", "message"), [
    ("kind: emulated", "kind: simulated", "kind:",
     "backend.kind: expected one of 'hardware', 'emulated'; got 'simulated'"),
    ("clock: lockstep", "clock: fast", "clock:",
     "backend.clock: expected one of 'realtime', 'lockstep'; got 'fast'"),
    ("geofence_min_m: [-2.5, -2.5, -0.5]", "geofence_min_m: [-2.5, 2.6, -0.5]",
     "geofence_min_m", "safety.geofence_min_m[1]: must be below geofence_max_m[1] (2.5 m)"),
    ("  seed: 1\n", "  seed: 1\n  faults: [mocap-dropout@x]\n", "faults",
     "backend.faults[0]: fault 'mocap-dropout@x': "),  # the parser's own wording follows
    ("failsafe_action: land", "failsafe_action: hover", "failsafe_action",
     "safety.failsafe_action: expected one of 'land', 'cut'; got 'hover'"),
    ("imu_rate_hz: 500.0", "imu_rate_hz: 5000.0", "imu_rate_hz",
     "backend.imu_rate_hz: expected a number >= 100 and <= 2000, got 5000.0"),
    ("  seed: 1\n", "  seed: 1\n  flight_ctrl_uri: /dev/ttyUSB0\n", "flight_ctrl_uri",
     "backend.flight_ctrl_uri: unknown key; expected one of: board_clock_ppm, clock, "
     "corrupt_prob, disturbances, faults, imu_rate_hz, kind, mocap, mocap_clock_offset_s, "
     "mocap_clock_ppm, scenario, seed"),
    ("  seed: 1\n", "  seed: 1\n  mocap: vicon\n", "mocap",
     "backend.mocap: expected one of 'natnet', 'qtm'; got 'vicon'"),
    ("telemetry:\n", 'telemetry:\n  record: "{sesion}-{time}.fhr"\n', "record:",
     "telemetry.record: unknown placeholder {sesion}; expected {session} and {time}"),
    # a bare true is no choice of rerun's; the message says why YAML saw a boolean
    ("rerun: auto", "rerun: true", "rerun:",
     "telemetry.rerun: expected one of 'off', 'save', 'serve', 'spawn', 'auto'; got true (YAML "
     "reads a bare true as True: write the value in quotes)"),
])
def test_that_a_malformed_session_gives_its_precise_message(
        tmp_path: Path, old: str, new: str, fragment: str, message: str) -> None:
    text = GOOD.replace(old, new, 1)
    path = tmp_path / "session.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as info:
        load_session(path)
    assert str(info.value).startswith(f"{path}:{_line_of(text, fragment)}: {message}")


def test_that_a_missing_backend_names_its_kinds_not_python_classes(tmp_path: Path) -> None:
    # the backend is a union of two dataclasses told apart by `kind`: the expectation names
    # the kinds a user can write, not "groundstation.session_config.HardwareBackend | ..."
    start = GOOD.index("backend:\n")
    end = GOOD.index("estimator:\n")
    text = GOOD[:start] + GOOD[end:]
    path = tmp_path / "session.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as info:
        load_session(path)
    assert str(info.value) == (f"{path}:{_line_of(text, 'schema:')}: backend: missing key; "
                               "expected a mapping with kind: hardware or kind: emulated")


def test_that_other_missing_keys_name_what_to_write_not_python_types(tmp_path: Path) -> None:
    from groundstation.configs import load_mission

    cases = [  # (file, text without the key, the message's tail)
        ("session.yaml", GOOD.replace("name: exp1-emulated\n", ""),
         "name: missing key; expected a text value"),
        ("mission.yaml", find_config("missions", "exp2a-sine-translation").read_text()
         .replace("    axis: x\n", ""),
         "missing key; expected one of 'x', 'y', 'z'")]
    for name, text, tail in cases:
        path = tmp_path / name
        path.write_text(text)
        with pytest.raises(ConfigError) as info:
            load_session(path) if name == "session.yaml" else load_mission(path)
        assert str(info.value).endswith(tail), str(info.value)


def test_that_a_session_naming_a_missing_mission_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "session.yaml"
    text = GOOD.replace("mission: exp1-hover-tilt-steps", "mission: exp9")
    path.write_text(text)
    with pytest.raises(ConfigError) as info:
        load_session(path)
    # the session file and the line of its key, not the bare name
    assert str(info.value) == (
        f"{path}:{_line_of(text, 'mission:')}: mission: no such mission 'exp9' (shipped: "
        f"{', '.join(available('missions'))})")


def test_that_errors_in_a_referenced_vehicle_file_name_that_file(tmp_path: Path) -> None:
    vehicle = tmp_path / "heavy.yaml"
    vehicle.write_text(find_config("vehicles", "fasthex").read_text()
                       .replace("mass_kg: 3.1", "mass_kg: 9.0"))
    path = tmp_path / "session.yaml"
    path.write_text(GOOD.replace("vehicle: fasthex", "vehicle: heavy.yaml"))
    with pytest.raises(ConfigError) as info:
        load_session(path)
    assert str(info.value).startswith(f"{vehicle}:")
    assert "mass_kg: weight 88.3 N needs >= 20 % thrust margin" in str(info.value)


@pytest.mark.parametrize(("key", "ref", "message"), [
    ("vehicle", "fasthex-maxi",
     "no such vehicle 'fasthex-maxi' (shipped: fasthex, fasthex-gust-recovery, fasthex-mini)"),
    ("disturbances", "windy", "no such disturbance 'windy' (shipped: ideal, paper-calibrated)"),
    ("mission", "mine.yaml", "no such file 'mine.yaml' (relative to the session file)"),
])
def test_that_a_missing_reference_names_the_session_file_and_line(
        tmp_path: Path, key: str, ref: str, message: str) -> None:
    text = "\n".join(
        (line.split(":")[0] + f": {ref}") if line.strip().startswith(f"{key}:") else line
        for line in GOOD.splitlines()) + "\n"
    path = tmp_path / "session.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as info:
        load_session(path)
    full_key = "backend.disturbances" if key == "disturbances" else key
    assert str(info.value) == f"{path}:{_line_of(text, key + ':')}: {full_key}: {message}"


def test_that_a_waypoint_outside_the_geofence_is_refused_at_the_mission_line(
        tmp_path: Path) -> None:
    # Fixture: the shipped Exp. 1 with one more waypoint, 2.45 m out: inside the 2.5 m fence
    # but not by the 0.1 m margin
    mission_text = find_config("missions", "exp1-hover-tilt-steps").read_text().replace(
        "  - kind: land\n", "  - kind: goto\n    duration_s: 10.0\n    pos_w_m: [2.45, 0, 1]\n"
        "  - kind: land\n", 1)
    (tmp_path / "m.yaml").write_text(mission_text)
    path = tmp_path / "session.yaml"
    path.write_text(GOOD.replace("mission: exp1-hover-tilt-steps", "mission: m.yaml"))
    # Test
    with pytest.raises(ConfigError) as info:
        load_session(path)
    # Assert
    assert str(info.value) == (
        f"{tmp_path / 'm.yaml'}:{_line_of(mission_text, 'pos_w_m: [2.45')}: segments[3].pos_w_m: "
        f"reaches x = 2.45 m, outside the geofence of {path} (line "
        f"{_line_of(GOOD, 'geofence_min_m')}) less 0.1 m (-2.4..2.4 m)")


def test_that_a_fence_below_the_mission_names_the_takeoff(tmp_path: Path) -> None:
    path = tmp_path / "session.yaml"
    path.write_text(GOOD.replace("geofence_max_m: [2.5, 2.5, 2.5]",
                                 "geofence_max_m: [2.5, 2.5, 0.8]"))
    mission = find_config("missions", "exp1-hover-tilt-steps")
    with pytest.raises(ConfigError) as info:
        load_session(path)
    assert str(info.value).startswith(
        f"{mission}:{_line_of(mission.read_text(), 'height_m')}: segments[0].height_m: "
        "reaches z = 1 m, outside the geofence")


def test_that_alpha_beyond_the_vehicles_tilt_is_an_error_not_a_clamp(tmp_path: Path) -> None:
    # Fixture: Exp. 1 steps to 30 deg; fasthex-mini tilts at most 30: 32 is beyond
    mission_text = find_config("missions", "exp1-hover-tilt-steps").read_text().replace(
        "values_deg: [0.0, 30.0, 0.0, 30.0]", "values_deg: [0.0, 30.0, 0.0, 32.0]")
    (tmp_path / "m.yaml").write_text(mission_text)
    path = tmp_path / "session.yaml"
    path.write_text(GOOD.replace("mission: exp1-hover-tilt-steps", "mission: m.yaml")
                    .replace("vehicle: fasthex", "vehicle: fasthex-mini"))
    with pytest.raises(ConfigError) as info:
        load_session(path)
    assert str(info.value) == (
        f"{tmp_path / 'm.yaml'}:{_line_of(mission_text, 'values_deg')}: "
        "segments[2].alpha.values_deg[3]: 32 deg is outside vehicle 'fasthex-mini''s tilt "
        "(a tilt range of 0..30 deg)")


def test_that_a_preset_file_is_validated_and_resolved_against_the_session(
        tmp_path: Path) -> None:
    # Fixture: a session in a folder next to its preset; loaded from elsewhere
    preset = find_config("disturbances", "paper-calibrated").read_text()
    (tmp_path / "slow-mocap.yaml").write_text(preset.replace("mocap_rate_hz: 100.0",
                                                             "mocap_rate_hz: 10.0"))
    (tmp_path / "good.yaml").write_text(preset)
    path = tmp_path / "session.yaml"
    # Test / Assert: a 10 Hz MoCap cannot keep the 0.05 s stale timeout quiet
    path.write_text(GOOD.replace("disturbances: paper-calibrated", "disturbances: slow-mocap.yaml"))
    with pytest.raises(ConfigError) as info:
        load_session(path)
    assert str(info.value).startswith(f"{path}:")
    assert "estimator.mocap_stale_s: 0.05 s is within one frame of the emulated MoCap" \
        in str(info.value)
    path.write_text(GOOD.replace("disturbances: paper-calibrated", "disturbances: good.yaml"))
    backend = load_session(path).backend
    assert isinstance(backend, EmulatedBackend)
    assert backend.disturbances == str(tmp_path / "good.yaml")


def test_that_an_imu_timeout_below_two_periods_is_refused(tmp_path: Path) -> None:
    text = re.sub(r"(?m)^  imu_timeout_s: .*$", "  imu_timeout_s: 0.003", GOOD)
    path = tmp_path / "session.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as info:
        load_session(path)
    assert str(info.value) == (f"{path}:{_line_of(text, 'imu_timeout_s')}: safety.imu_timeout_s: "
                               "expected >= two IMU periods at 500 Hz (0.004 s), got 0.003")


def test_that_the_record_placeholders_are_accepted(tmp_path: Path) -> None:
    text = GOOD.replace("telemetry:\n", 'telemetry:\n  record: "out/{session}-{time}.fhr"\n')
    path = tmp_path / "session.yaml"
    path.write_text(text)
    assert load_session(path).telemetry.record == "out/{session}-{time}.fhr"


def test_that_a_mavlink_key_file_is_relative_to_the_session_and_must_exist(
        tmp_path: Path) -> None:
    # Fixture: a session that names its key file next to itself
    text = GOOD.replace("telemetry:\n", "telemetry:\n  mavlink_key_file: gcs.key\n")
    path = tmp_path / "session.yaml"
    path.write_text(text)
    # Test / Assert: missing -> the session's line; present -> resolved next to the session
    with pytest.raises(ConfigError) as info:
        load_session(path)
    line = _line_of(text, "mavlink_key_file")
    assert str(info.value) == (f"{path}:{line}: telemetry.mavlink_key_file: no such key file "
                               "'gcs.key' (relative to the session file)")
    (tmp_path / "gcs.key").write_text("a" * 64)
    assert load_session(path).telemetry.mavlink_key_file == str(tmp_path / "gcs.key")


@pytest.mark.parametrize("command", ["fly", "simulate"])
@pytest.mark.parametrize("seed", ["-5", str(2**32), "99999999999999999999", "x"])
def test_that_a_cli_seed_outside_the_session_files_range_is_a_usage_error(
        command: str, seed: str, capsys: pytest.CaptureFixture[str]) -> None:
    from groundstation.cli import main

    # Test: refused by the parser, before any flight or emulator starts
    with pytest.raises(SystemExit) as exit_:
        main([command, "--seed", seed])
    # Assert
    assert exit_.value.code == 2
    err = capsys.readouterr().err.splitlines()[-1]
    assert err == (f"fasthex {command}: error: argument --seed: expected an integer 0 .. "
                   f"{2**32 - 1} (as backend.seed in a session file), got {seed!r}")


@pytest.mark.parametrize("command", ["fly", "simulate"])
def test_that_the_cli_seed_range_ends_where_the_session_files_range_ends(
        command: str, tmp_path: Path) -> None:
    from groundstation.cli import build_parser

    # Fixture: the session file's own bounds
    session = tmp_path / "s.yaml"
    session.write_text(GOOD.replace("  seed: 1\n", f"  seed: {2**32 - 1}\n"))
    assert load_session(session).backend.seed == 2**32 - 1
    session.write_text(GOOD.replace("  seed: 1\n", f"  seed: {2**32}\n"))
    with pytest.raises(ConfigError, match="seed"):
        load_session(session)
    # Test / Assert: the CLI takes the same bounds
    for seed in (0, 2**32 - 1):
        assert build_parser().parse_args([command, "--seed", str(seed)]).seed == seed


@pytest.mark.parametrize(("key", "uri", "message"), [
    ("mocap_uri", "natnet://192.0.2.10?local=notanip&body=fasthex",
     "natnet://192.0.2.10?local=notanip&body=fasthex: local_ip: must be an IPv4 address"),
    ("mocap_uri", "bogus://x", "bogus://x: unknown scheme 'bogus'; expected natnet://"),
    ("flight_ctrl_uri", "serial:///dev/ttyUSB0?baud=fast",
     "serial:///dev/ttyUSB0?baud=fast: option baud='fast' is not an integer; expected "
     "serial://<device>?baud=<int>&low_latency=<0|1>"),
    ("flight_ctrl_uri", "serial:///dev/ttyUSB0?speed=500000",
     "serial:///dev/ttyUSB0?speed=500000: unknown option 'speed'; expected the form serial://"),
    ("flight_ctrl_uri", "ser:///dev/ttyUSB0",
     "ser:///dev/ttyUSB0: unknown scheme 'ser'; expected one of loop://, pty://, serial://, "
     "spy://"),
    ("flight_ctrl_uri", "spy://serial:///dev/ttyUSB0?baud=x?log=fc.log",
     "serial:///dev/ttyUSB0?baud=x: option baud='x' is not an integer"),
    ("servo_uri", "serial:///dev/ttyUSB1?baud=1000000&id=300",
     "serial:///dev/ttyUSB1?baud=1000000&id=300: id 300 outside 0..253"),
    ("servo_uri", "serial:///dev/ttyUSB1?baud=123",
     "serial:///dev/ttyUSB1?baud=123: baud 123 cannot be opened by dynamixel-sdk"),
])
def test_that_a_malformed_device_uri_is_refused_at_its_line_by_its_drivers_parser(
        tmp_path: Path, key: str, uri: str, message: str) -> None:
    # Fixture: the hardware template (its vehicle and mission are shipped names)
    template = find_config("sessions", "hardware-template")
    text = "\n".join(f'  {key}: "{uri}"' if line.strip().startswith(f"{key}:") else line
                     for line in template.read_text().splitlines()) + "\n"
    path = tmp_path / "bench.yaml"
    path.write_text(text)
    # Test
    with pytest.raises(ConfigError) as info:
        load_session(path)
    # Assert: before any device is opened (load_session opens none), at the key's line
    assert str(info.value).startswith(
        f"{path}:{_line_of(text, key + ':')}: backend.{key}: {message}")


@pytest.mark.parametrize("written", ["off", "Off", "OFF", '"off"', "{rerun: off}"])
def test_that_a_bare_off_is_the_choice_off_not_a_boolean(tmp_path: Path, written: str) -> None:
    # YAML 1.1 reads a bare off as false: it was 'telemetry.rerun: expected one of 'off', ...
    # got False'
    text = GOOD.replace("telemetry:\n  rerun: auto", f"telemetry: {written}" if "{" in written
                        else f"telemetry:\n  rerun: {written}")
    path = tmp_path / "session.yaml"
    path.write_text(text)
    assert load_session(path).telemetry.rerun == "off"

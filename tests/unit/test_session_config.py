"""Session files: the shipped ones load; malformed ones are refused with a precise message
before anything is opened (including errors in the files a session refers to)."""

from __future__ import annotations

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
     "backend.flight_ctrl_uri: unknown key; expected one of: clock, corrupt_prob, disturbances, "
     "faults, imu_rate_hz, kind, seed"),
])
def test_that_a_malformed_session_gives_its_precise_message(
        tmp_path: Path, old: str, new: str, fragment: str, message: str) -> None:
    text = GOOD.replace(old, new, 1)
    path = tmp_path / "session.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as info:
        load_session(path)
    assert str(info.value).startswith(f"{path}:{_line_of(text, fragment)}: {message}")


def test_that_a_session_naming_a_missing_mission_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "session.yaml"
    text = GOOD.replace("mission: exp1-hover-tilt-steps", "mission: exp9")
    path.write_text(text)
    with pytest.raises(ConfigError) as info:
        load_session(path)
    # the session file and the line of its key, not the bare name
    assert str(info.value) == (
        f"{path}:{_line_of(text, 'mission:')}: mission: no such mission 'exp9' (shipped: "
        "exp1-hover-tilt-steps, exp2a-sine-translation, exp2a-sine-translation-auto, "
        "exp2b-roll-sine)")


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

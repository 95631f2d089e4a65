"""Hardware-in-the-loop tests: they run against whatever devices the environment names, and are
skipped (with the reason) when it names none.

- ``FASTHEX_HIL_FLIGHT_CTRL``: the Flight-Ctrl URI (``serial:///dev/ttyUSB0?baud=500000``);
- ``FASTHEX_HIL_SERVO``: the tilt servo URI (``serial:///dev/ttyUSB1?baud=1000000&id=1``);
- ``FASTHEX_HIL_MOCAP``: the MoCap URI (``natnet://192.168.1.10?local=192.168.1.2&body=fasthex``);
- ``FASTHEX_HIL_PROPS_OFF=1``: the operator's word that the propellers are off, needed by the
  tests that spin the motors;
- ``FASTHEX_HIL_VEHICLE``: the vehicle whose limits the servo tests check (default ``fasthex``).

``tests/hil/run_against_emulator.py`` runs them all against ``fasthex emulate``'s devices, with
``FASTHEX_HIL_REQUIRE=1``: then a variable left unset fails the test instead of skipping it.
"""

from __future__ import annotations

import os

import pytest

from controller.params import VehicleParams
from groundstation.configs import load_vehicle

_FORMS = {
    "FASTHEX_HIL_FLIGHT_CTRL": "a Flight-Ctrl URI, e.g. serial:///dev/ttyUSB0?baud=500000",
    "FASTHEX_HIL_SERVO": "a servo URI, e.g. serial:///dev/ttyUSB1?baud=1000000&id=1",
    "FASTHEX_HIL_MOCAP": "a MoCap URI, e.g. natnet://192.168.1.10?local=192.168.1.2&body=fasthex",
}


def _unavailable(reason: str) -> None:
    if os.environ.get("FASTHEX_HIL_REQUIRE") == "1":
        pytest.fail(f"FASTHEX_HIL_REQUIRE=1 but {reason}")
    pytest.skip(reason)


def _uri(name: str) -> str:
    value = os.environ.get(name, "").strip()
    if not value:
        _unavailable(f"{name} is not set ({_FORMS[name]})")
    return value


@pytest.fixture
def flight_ctrl_uri() -> str:
    return _uri("FASTHEX_HIL_FLIGHT_CTRL")


@pytest.fixture
def servo_uri() -> str:
    return _uri("FASTHEX_HIL_SERVO")


@pytest.fixture
def mocap_uri() -> str:
    return _uri("FASTHEX_HIL_MOCAP")


@pytest.fixture
def props_off() -> None:
    if os.environ.get("FASTHEX_HIL_PROPS_OFF") != "1":
        _unavailable("spins the motors: set FASTHEX_HIL_PROPS_OFF=1 once the propellers are off")


@pytest.fixture(scope="session")
def hil_vehicle() -> VehicleParams:
    return load_vehicle(os.environ.get("FASTHEX_HIL_VEHICLE", "fasthex"))

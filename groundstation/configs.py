"""Loading the typed configuration files (the composition root's entry to ``config/``)."""

from __future__ import annotations

from pathlib import Path

from config import find_config
from config.schema import load_config
from controller.params import VEHICLE_SCHEMA, VehicleParams

DEFAULT_VEHICLE = "fasthex"


def load_vehicle(name_or_path: str | Path = DEFAULT_VEHICLE) -> VehicleParams:
    """A shipped vehicle by name (``fasthex``, ``fasthex-mini``) or a vehicle YAML file."""
    return load_config(find_config("vehicles", name_or_path), VehicleParams,
                       schema=VEHICLE_SCHEMA, versions=(1,))


# Missions (appended; imports kept here so the vehicle part above stays untouched).
from controller.missions import MISSION_SCHEMA, MissionSpec  # noqa: E402


def load_mission(name_or_path: str | Path) -> MissionSpec:
    """A shipped mission by name (``exp1-hover-tilt-steps``) or a mission YAML file."""
    return load_config(find_config("missions", name_or_path), MissionSpec,
                       schema=MISSION_SCHEMA, versions=(1,))


# Simulator disturbance presets (appended).
from sim_backend.disturbances import DISTURBANCES_SCHEMA, DisturbancePreset  # noqa: E402

DEFAULT_DISTURBANCES = "paper-calibrated"


def load_disturbances(name_or_path: str | Path = DEFAULT_DISTURBANCES) -> DisturbancePreset:
    """A simulator disturbance preset by name (``ideal``, ``paper-calibrated``) or file."""
    return load_config(find_config("disturbances", name_or_path), DisturbancePreset,
                       schema=DISTURBANCES_SCHEMA, versions=(1,))

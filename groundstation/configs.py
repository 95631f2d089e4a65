"""Loading the typed configuration files (the composition root's entry to ``config/``)."""

from __future__ import annotations

import math
from pathlib import Path

from config import find_config
from config.schema import ConfigValueError, load_config
from controller.params import VEHICLE_SCHEMA, TiltParams, VehicleParams

DEFAULT_VEHICLE = "fasthex"


def load_vehicle(name_or_path: str | Path = DEFAULT_VEHICLE) -> VehicleParams:
    """A shipped vehicle by name (``fasthex``, ``fasthex-mini``) or a vehicle YAML file."""
    return load_config(find_config("vehicles", name_or_path), VehicleParams,
                       schema=VEHICLE_SCHEMA, versions=(1,))


# Missions (appended; imports kept here so the vehicle part above stays untouched).
from controller.missions import MISSION_SCHEMA, Mission, MissionSpec  # noqa: E402
from controller.trajectory_csv import mission_base_dir  # noqa: E402


def load_mission(name_or_path: str | Path, *, vehicle: VehicleParams | None = None,
                 lines: dict[str, int] | None = None) -> MissionSpec:
    """A shipped mission by name (``exp1-hover-tilt-steps``) or a mission YAML file.

    With ``vehicle``, the mission is checked against it too (:func:`check_mission_against_vehicle`);
    ``lines`` is filled with the line of each key path (see :func:`config.schema.load_config`).
    """
    path = find_config("missions", name_or_path)
    lines = {} if lines is None else lines
    with mission_base_dir(path.parent):  # trajectory CSV files are relative to the mission
        spec = load_config(path, MissionSpec, schema=MISSION_SCHEMA, versions=(1,), lines=lines)
    check_mission_lands(spec, str(path), lines)
    if vehicle is not None:
        check_mission_against_vehicle(spec, vehicle, str(path), lines)
    return spec


def check_mission_lands(mission: MissionSpec, file: str, lines: dict[str, int]) -> None:
    """A mission file to fly ends on the ground (:func:`controller.missions.check_ends_on_ground`),
    as an error at the mission's line."""
    from config.schema import ConfigError, line_of
    from controller.missions import check_ends_on_ground

    try:
        check_ends_on_ground(mission)
    except ConfigValueError as exc:
        raise ConfigError(file, line_of(lines, exc.key), exc.key, exc.message) from None


def check_mission_against_vehicle(mission: MissionSpec, vehicle: VehicleParams, file: str,
                                  lines: dict[str, int]) -> None:
    """Every alpha the mission writes down lies in the vehicle's tilt range: an error at the
    mission's line, never a silent clamp by the planner. (Segments without an alpha inherit
    one; on a fixed-tilt vehicle the planner holds its tilt.)"""
    from config.schema import ConfigError, line_of
    from controller.missions import explicit_alphas_deg, peak_vertical_accel_m_s2

    # vertical accelerations within the rotors' thrust: up, the lift at the smallest tilt less
    # 10 % kept for attitude control; down, no less than the idle thrust
    g = vehicle.gravity_m_s2
    up_max = 0.9 * 6.0 * vehicle.rotors.max_thrust_n * math.cos(vehicle.tilt.min_tilt_rad) \
        / vehicle.mass_kg - g
    down_max = g - 6.0 * vehicle.rotors.min_thrust_n / vehicle.mass_kg
    for i, accel in enumerate(peak_vertical_accel_m_s2(mission)):
        if accel > min(up_max, down_max):
            key = f"segments[{i}].duration_s"
            raise ConfigError(file, line_of(lines, key), key,
                              f"the reference accelerates vertically at {accel:.3g} m/s^2; "
                              f"vehicle {vehicle.name!r} manages {up_max:.3g} m/s^2 up and "
                              f"{down_max:.3g} m/s^2 down (a longer duration_s)")
    tilt = vehicle.tilt
    for seg in mission.segments:   # a trajectory's alpha column: the file's own line
        table = getattr(seg, "table", None)
        if seg.alpha is None and table is not None and table.alpha_deg and table.row_lines:
            for line, value_deg in zip(table.row_lines, table.alpha_deg, strict=True):
                if not tilt.min_tilt_deg <= value_deg <= tilt.max_tilt_deg:
                    raise ConfigError(table.path, line, table.alpha_column,
                                      f"{value_deg:g} deg is outside vehicle {vehicle.name!r}'s "
                                      f"tilt ({_tilt_range(tilt)})")
    for key, value_deg in explicit_alphas_deg(mission):
        if not tilt.min_tilt_deg <= value_deg <= tilt.max_tilt_deg:
            raise ConfigError(file, line_of(lines, key), key,
                              f"{value_deg:g} deg is outside vehicle {vehicle.name!r}'s tilt "
                              f"({_tilt_range(tilt)})")


def _tilt_range(tilt: TiltParams) -> str:
    return (f"a fixed tilt of {tilt.max_tilt_deg:g} deg" if tilt.is_fixed else
            f"a tilt range of {tilt.min_tilt_deg:g}..{tilt.max_tilt_deg:g} deg")


def preflight_warnings(mission: Mission, vehicle: VehicleParams, *,
                       tilt_override_rad: float | None = None) -> list[str]:
    """The pre-flight lateral-force check's warning lines (empty: nothing to say), printed by
    ``simulate`` and ``fly`` before flying."""
    from controller.preflight import lateral_force_shortfalls, shortfall_warnings

    spans = lateral_force_shortfalls(mission, vehicle, tilt_override_rad=tilt_override_rad)
    return shortfall_warnings(spans, mission.name)


# Simulator disturbance presets (appended).
from sim_backend.disturbances import DISTURBANCES_SCHEMA, DisturbancePreset  # noqa: E402

DEFAULT_DISTURBANCES = "paper-calibrated"


def load_disturbances(name_or_path: str | Path = DEFAULT_DISTURBANCES) -> DisturbancePreset:
    """A simulator disturbance preset by name (``ideal``, ``paper-calibrated``) or file."""
    return load_config(find_config("disturbances", name_or_path), DisturbancePreset,
                       schema=DISTURBANCES_SCHEMA, versions=(1,))


# Scenarios (appended): plant overrides, scheduled disturbances and faults.
from sim_backend.scenario import (  # noqa: E402
    SCENARIO_SCHEMA,
    Scenario,
    check_scenario_against_mission,
    check_scenario_against_vehicle,
)


def load_scenario(name_or_path: str | Path, *, vehicle: VehicleParams | None = None,
                  mission_duration_s: float | None = None,
                  lines: dict[str, int] | None = None) -> Scenario:
    """A shipped scenario by name or a scenario YAML file, checked against the vehicle (the
    plant still flies) and the mission's duration (every event inside it) when given."""
    path = find_config("scenarios", name_or_path)
    lines = {} if lines is None else lines
    scenario = load_config(path, Scenario, schema=SCENARIO_SCHEMA, versions=(1,), lines=lines)
    if vehicle is not None:
        check_scenario_against_vehicle(scenario, vehicle, str(path), lines)
    if mission_duration_s is not None:
        check_scenario_against_mission(scenario, mission_duration_s, str(path), lines)
    return scenario

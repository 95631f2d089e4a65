"""Shared fixtures: the shipped vehicles, loaded through the same path as the CLI."""

from __future__ import annotations

import pytest

from controller.model import VehicleModel
from controller.params import VehicleParams
from groundstation.configs import load_vehicle


@pytest.fixture(scope="session")
def fasthex_params() -> VehicleParams:
    return load_vehicle("fasthex")


@pytest.fixture(scope="session")
def fasthex_model(fasthex_params: VehicleParams) -> VehicleModel:
    return VehicleModel(fasthex_params)

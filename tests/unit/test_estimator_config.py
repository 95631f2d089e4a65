"""The estimator config through the project's validating YAML loader."""

from __future__ import annotations

import pytest

from config.schema import ConfigError, load_config_text
from estimator import EstimatorConfig


def test_that_a_partial_file_keeps_the_defaults_for_the_rest() -> None:
    cfg = load_config_text("schema: estimator\nversion: 1\nlatency_compensation: false\n"
                           "mocap_pos_sigma_m: 1e-3\n", EstimatorConfig, schema="estimator")
    assert cfg.latency_compensation is False
    assert cfg.mocap_pos_sigma_m == 1e-3
    assert cfg.gate_nis == EstimatorConfig().gate_nis


def test_that_an_out_of_range_value_names_the_key_and_line() -> None:
    text = "schema: estimator\nversion: 1\nsigma_alpha: 0.5\ngate_nis: -1\n"
    with pytest.raises(ConfigError) as err:
        load_config_text(text, EstimatorConfig, schema="estimator", file_label="est.yaml")
    assert "est.yaml:4: gate_nis" in str(err.value)


def test_that_inconsistent_limits_are_refused() -> None:
    text = "schema: estimator\nversion: 1\ndiverged_pos_sigma_m: 20.0\n"
    with pytest.raises(ConfigError) as err:
        load_config_text(text, EstimatorConfig, schema="estimator", file_label="est.yaml")
    assert "diverged_pos_sigma_m" in str(err.value)
    assert "max_pos_sigma_m" in str(err.value)


def test_that_the_integration_scheme_is_one_of_the_known_names() -> None:
    text = "schema: estimator\nversion: 1\nimu_integration: euler\n"
    with pytest.raises(ConfigError, match="imu_integration"):
        load_config_text(text, EstimatorConfig, schema="estimator")

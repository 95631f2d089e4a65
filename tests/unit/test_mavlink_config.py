"""The bridge's YAML block: rates and link from config, never the key itself."""

from __future__ import annotations

import pytest

from config.schema import ConfigError, load_config_text
from drivers.mavlink import MavlinkConfig


def _load(body: str) -> MavlinkConfig:
    return load_config_text("schema: mavlink\nversion: 1\n" + body, MavlinkConfig,
                            schema="mavlink", file_label="session.yaml")


def test_that_the_link_rates_and_key_source_come_from_yaml() -> None:
    cfg = _load("uri: udpin:0.0.0.0:14550\nattitude_hz: 25\nsigning: true\n"
                "key_file: lab.key\nallow_unsigned_ids: [109]\n")
    assert cfg.uri == "udpin:0.0.0.0:14550"
    assert cfg.rates_hz()["ATTITUDE"] == 25.0
    assert cfg.rates_hz()["HEARTBEAT"] == 1.0
    assert (cfg.signing, cfg.key_file, cfg.allow_unsigned_ids) == (True, "lab.key", (109,))


def test_that_a_signing_key_written_in_clear_in_the_yaml_is_refused() -> None:
    with pytest.raises(ConfigError, match="key"):
        _load("signing: true\nkey: 0123456789abcdef\n")


def test_that_a_bad_uri_or_rate_names_the_key_and_line() -> None:
    with pytest.raises(ConfigError, match=r"session.yaml:3.*uri.*udpout:HOST:PORT"):
        _load("uri: tcp:127.0.0.1:5760\n")
    with pytest.raises(ConfigError, match="attitude_hz"):
        _load("attitude_hz: -1\n")


def test_that_a_signing_bridge_reads_its_key_from_the_environment_or_refuses_to_start() -> None:
    from drivers.mavlink import SigningKeyError
    from groundstation.mavlink_bridge import MavlinkBridge
    from groundstation.operator import RuleBasedCommandSink

    cfg = _load("uri: udpout:127.0.0.1:9\nsigning: true\nkey_env: LAB_KEY\n")
    with pytest.raises(SigningKeyError, match=r"\$LAB_KEY"):
        MavlinkBridge.from_config(cfg, RuleBasedCommandSink(), environ={})
    with MavlinkBridge.from_config(cfg, RuleBasedCommandSink(),
                                   environ={"LAB_KEY": "labpass"}) as bridge:
        assert bridge.stats().signing is not None

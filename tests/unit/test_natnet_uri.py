"""MoCap URIs (natnet://, vrpn://, qtm://) -> device configs, and clear errors for bad ones."""

from __future__ import annotations

import pytest

from drivers.mocap.natnet_client import NatNetClient, NatNetConfig
from drivers.mocap.pose import PoseSource
from drivers.mocap.qtm_client import QtmClient, QtmConfig
from drivers.mocap.uri import MocapUriError, open_pose_source, parse_uri
from drivers.mocap.vrpn_client import VrpnClient, VrpnConfig


def test_that_a_full_natnet_uri_sets_every_option() -> None:
    cfg = parse_uri("natnet://192.168.1.10:1600?local=192.168.1.20&mode=multicast"
                    "&data_port=1611&group=239.255.42.98&body=fasthex&version=3.1&up=z"
                    "&units=mm&delay_ms=0.5&require_version=1")
    assert isinstance(cfg, NatNetConfig)
    assert (cfg.server_ip, cfg.command_port, cfg.local_ip, cfg.mode) == \
        ("192.168.1.10", 1600, "192.168.1.20", "multicast")
    assert (cfg.data_port, cfg.multicast_group, cfg.body, cfg.version) == \
        (1611, "239.255.42.98", "fasthex", "3.1")
    assert cfg.require_version
    assert (cfg.frames.up_axis, cfg.frames.units) == ("z", "mm")
    assert cfg.network_delay_s == pytest.approx(0.0005)


def test_that_a_bare_natnet_uri_takes_the_documented_defaults() -> None:
    cfg = parse_uri("natnet://127.0.0.1")
    assert cfg == NatNetConfig()


def test_that_a_vrpn_uri_names_tracker_host_and_port_and_defaults_to_z_up() -> None:
    cfg = parse_uri("vrpn://Tracker0@127.0.0.1:3884?sensor=2&latency_ms=8&stale_ms=30")
    assert isinstance(cfg, VrpnConfig)
    assert (cfg.tracker, cfg.host, cfg.port, cfg.sensor) == ("Tracker0", "127.0.0.1", 3884, 2)
    assert cfg.latency_s == pytest.approx(0.008) and cfg.stale_after_s == pytest.approx(0.03)
    assert cfg.frames.up_axis == "z"
    assert cfg.handshake == "auto"  # the classic UDP request, then direct TCP


def test_that_a_vrpn_uri_can_choose_the_handshake() -> None:
    cfg = parse_uri("vrpn://Tracker0@127.0.0.1?handshake=tcp")
    assert isinstance(cfg, VrpnConfig) and cfg.handshake == "tcp"


def test_that_a_qtm_uri_sets_every_option_and_defaults_to_z_up_millimetres() -> None:
    assert parse_uri("qtm://127.0.0.1") == QtmConfig()
    assert (QtmConfig().port, QtmConfig().frames.up_axis, QtmConfig().frames.units) == \
        (22223, "z", "mm")
    cfg = parse_uri("qtm://192.168.1.10:22300?body=fasthex&component=6deuler&frequency_hz=50"
                    "&udp=1&local=192.168.1.20&latency_ms=4&range_m=20")
    assert isinstance(cfg, QtmConfig)
    assert (cfg.host, cfg.port, cfg.body, cfg.component, cfg.frequency_hz) == \
        ("192.168.1.10", 22300, "fasthex", "6deuler", 50.0)
    assert (cfg.udp, cfg.local_ip, cfg.limits.max_range_m) == (True, "192.168.1.20", 20.0)
    assert cfg.latency_s == pytest.approx(0.004)
    assert cfg.stream_command(6734) == "StreamFrames Frequency:50 UDP:6734 6deuler"
    assert isinstance(open_pose_source("qtm://127.0.0.1", body="pad"), QtmClient)


@pytest.mark.parametrize("uri,fragment", [
    ("natnet://127.0.0.1?moda=unicast", "unknown option"),
    ("natnet://127.0.0.1?mode=broadcast", "mode"),
    ("natnet://127.0.0.1?version=2.9", "unsupported NatNet version"),
    ("natnet://127.0.0.1?up=x", "up_axis"),
    ("natnet://not-an-ip", "IPv4"),
    ("vrpn://127.0.0.1", "TRACKER@HOST"),
    ("vrpn://T@127.0.0.1?sensor=one", "one"),
    ("vrpn://T@127.0.0.1?handshake=udp", "handshake"),
    ("natnet://127.0.0.1?version=3.1&require_version=yes", "require_version"),
    ("vicon://127.0.0.1", "unknown scheme"),
    ("qtm://?body=hex", "no QTM host"),
    ("qtm://127.0.0.1?component=3d", "component"),
    ("qtm://127.0.0.1?udp=yes", "udp must be 0 or 1"),
    ("qtm://127.0.0.1?frequency=100", "unknown option"),
])
def test_that_a_bad_uri_is_a_typed_error_naming_it(uri: str, fragment: str) -> None:
    with pytest.raises(MocapUriError, match=fragment) as info:
        parse_uri(uri)
    assert uri in str(info.value)


def test_that_open_pose_source_builds_unstarted_pose_sources_with_overrides() -> None:
    nat = open_pose_source("natnet://127.0.0.1", body="pad")
    vr = open_pose_source("vrpn://Tracker0@127.0.0.1")
    assert isinstance(nat, NatNetClient) and nat.config.body == "pad"
    assert isinstance(vr, VrpnClient)
    assert isinstance(nat, PoseSource) and isinstance(vr, PoseSource)
    assert nat.latest() is None and vr.latest() is None
    with pytest.raises(MocapUriError):
        open_pose_source("natnet://127.0.0.1", no_such_field=1)

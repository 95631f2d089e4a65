"""``fasthex mocap list|watch`` against the emulated servers, through the real CLI entry point."""

from __future__ import annotations

import dataclasses
import re
from typing import Any

import pytest

from drivers.mocap.pose import MocapStats, PoseSample, TrackingStatus
from groundstation.cli import main
from groundstation.commands.mocap import format_status
from sim_backend.emulators.natnet import (
    NatNetEmulatorConfig,
    NatNetServer,
    StaticBody,
    free_udp_port,
)
from sim_backend.emulators.vrpn import VrpnEmulatorConfig, VrpnServer
from sim_backend.vehicle import BenchVehicle


def _emulator(**kw: Any) -> NatNetServer:
    cfg = dataclasses.replace(NatNetEmulatorConfig(
        command_port=0, rate_hz=250.0, static_bodies=(StaticBody("pad", 7, (0.5, 0.5, 0.0)),)),
        **kw)
    return NatNetServer(BenchVehicle(pos_w_m=(1.0, -2.0, 1.5)), cfg)


def test_that_list_shows_server_version_and_rigid_bodies(capsys: pytest.CaptureFixture[str]
                                                         ) -> None:
    with _emulator(version="4.0") as server:
        rc = main(["mocap", "list", f"natnet://127.0.0.1:{server.command_port}"])
    out = capsys.readouterr().out
    assert rc == 0
    assert "Motive" in out and "NatNet 4.0" in out and "unicast" in out
    assert re.search(r"\b1\s+fasthex\s+4 markers", out)
    assert re.search(r"\b7\s+pad\s+4 markers", out)


def test_that_watch_prints_the_world_pose_of_the_chosen_body_in_multicast(
        capsys: pytest.CaptureFixture[str]) -> None:
    port = free_udp_port()
    with _emulator(mode="multicast", data_port=port, latency_s=0.004) as server:
        rc = main(["mocap", "watch", f"natnet://127.0.0.1:{server.command_port}"
                   f"?mode=multicast&data_port={port}", "--body", "fasthex", "--frames", "30",
                   "--interval", "0.05"])
    lines = capsys.readouterr().out.strip().splitlines()
    assert rc == 0
    last = lines[-1]
    assert "fasthex: p [ +1.000  -2.000  +1.500] m" in last
    # the server's 4 ms plus this packet's delay above the earliest one (clock sync)
    lat = re.search(r"lat +([0-9.]+) ms", last)
    assert lat is not None and 4.0 <= float(lat.group(1)) < 9.0


def test_that_watch_reads_a_vrpn_tracker(capsys: pytest.CaptureFixture[str]) -> None:
    with VrpnServer(BenchVehicle(pos_w_m=(0.25, 0.5, 1.0)), VrpnEmulatorConfig(port=0)) as srv:
        rc = main(["mocap", "watch", f"vrpn://Tracker0@127.0.0.1:{srv.port}", "--frames", "10",
                   "--interval", "0.05"])
    assert rc == 0
    assert "Tracker0: p [ +0.250  +0.500  +1.000] m" in capsys.readouterr().out


def test_that_an_unknown_body_is_a_one_line_user_error(capsys: pytest.CaptureFixture[str]
                                                       ) -> None:
    with _emulator() as server:
        rc = main(["mocap", "watch", f"natnet://127.0.0.1:{server.command_port}",
                   "--body", "nope"])
    err = capsys.readouterr().err
    assert rc == 2
    assert "no rigid body named 'nope'" in err and "fasthex" in err and "Traceback" not in err


def test_that_watching_an_unknown_vrpn_tracker_ends_with_the_names_the_server_announces(
        capsys: pytest.CaptureFixture[str]) -> None:
    with VrpnServer(BenchVehicle(), VrpnEmulatorConfig(port=0, tracker_name="fasthex")) as srv:
        rc = main(["mocap", "watch", f"vrpn://Tracker0@127.0.0.1:{srv.port}", "--frames", "10"])
    err = capsys.readouterr().err
    assert rc == 2
    assert "no tracker named 'Tracker0'" in err and "it announces fasthex" in err
    assert "Traceback" not in err


def test_that_an_invalid_sample_is_shown_as_such_without_a_pose() -> None:
    stats = MocapStats(10, 0, 0, 1, 0, 0, 100.0, 0.02, 0.004)
    nan3 = (float("nan"),) * 3
    nan4 = (float("nan"),) * 4
    sample = PoseSample(0, 0, 42, 1, "fasthex", TrackingStatus.INVALID, nan3, nan4, 0.004, 0.0)
    line = format_status(sample, stats)
    assert line.startswith("#42 fasthex: TRACKING_INVALID") and "p [" not in line

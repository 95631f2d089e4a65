"""``fasthex mocap list|watch`` against the emulated servers, through the real CLI entry point."""

from __future__ import annotations

import dataclasses
import re
from typing import Any

import pytest

from drivers.mocap.pose import FrameWaits, MocapStats, PoseSample, TrackingStatus
from groundstation.cli import main
from groundstation.commands import mocap as mocap_command
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


class LockstepPacer(mocap_command.WatchPacer):
    """The watch's clock is the emulator's: each wait steps the vehicle by the wait and
    publishes the frames due, and returns once the client has received them."""

    def __init__(self, server: NatNetServer, vehicle: BenchVehicle) -> None:
        self.server, self.vehicle = server, vehicle
        self.waits = 0

    def now_s(self) -> float:
        return self.vehicle.now_s()

    def wait(self, dev: FrameWaits, until_frames: int, timeout_s: float) -> None:
        self.waits += 1
        before = dev.frames_seen
        self.vehicle.advance(timeout_s)
        published = self.server.publish_due(self.vehicle.now_s())
        assert dev.wait_for_total(before + published, 10.0)


@pytest.mark.parametrize("interval_s,lines", [(0.02, 16), (0.05, 7), (0.1, 4)])
def test_that_watch_prints_one_line_per_interval_of_the_stream(
        interval_s: float, lines: int, capsys: pytest.CaptureFixture[str],
        monkeypatch: pytest.MonkeyPatch) -> None:
    # Fixture: a 100 Hz server stepped by the watch's own waits (no wall-clock timing)
    vehicle = BenchVehicle(pos_w_m=(1.0, -2.0, 1.5))
    server = NatNetServer(vehicle, NatNetEmulatorConfig(command_port=0, rate_hz=100.0))
    server.start(realtime=False)
    server.publish_due(vehicle.now_s())  # the frame schedule starts at t = 0
    pacer = LockstepPacer(server, vehicle)
    monkeypatch.setattr(mocap_command, "PACER", pacer)
    try:
        # Test: 30 frames = 0.3 s of stream
        rc = main(["mocap", "watch", f"natnet://127.0.0.1:{server.command_port}",
                   "--frames", "30", "--interval", str(interval_s)])
    finally:
        server.close()
    # Assert: a line at t = 0, then one per interval until the 30th frame
    out = capsys.readouterr().out.strip().splitlines()
    assert rc == 0
    assert len(out) == lines, out
    assert out[0] == "waiting for frames..."  # no rate, latency or age before a frame
    assert all("fasthex: p [ +1.000  -2.000  +1.500] m" in line for line in out[1:])
    assert pacer.waits == lines - 1
    assert vehicle.now_s() == pytest.approx(0.3)


def test_that_a_non_positive_interval_is_a_user_error(capsys: pytest.CaptureFixture[str]
                                                      ) -> None:
    rc = main(["mocap", "watch", "natnet://127.0.0.1", "--interval", "0"])
    assert rc == 2 and "--interval must be > 0 s" in capsys.readouterr().err


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


def test_that_waiting_for_frames_shows_no_placeholder_as_a_measurement() -> None:
    # before the first frame: rate 0, latency NaN, age inf are unknowns, not measurements
    nothing = MocapStats(0, 0, 0, 0, 0, 0, 0.0, float("inf"), float("nan"))
    assert format_status(None, nothing) == "waiting for frames..."
    garbled = dataclasses.replace(nothing, malformed_packets=3)
    assert format_status(None, garbled) == "waiting for frames...  drop 0 inv 0 bad 3"
    # frames of the body arrive but none valid yet: no age, no latency known
    stats = dataclasses.replace(nothing, frames_received=4, invalid_samples=4, rate_hz=100.0)
    nan3, nan4 = (float("nan"),) * 3, (float("nan"),) * 4
    sample = PoseSample(0, 0, 4, 1, "fasthex", TrackingStatus.INVALID, nan3, nan4, 0.0, 0.0)
    line = format_status(sample, stats)
    assert "lat    -- ms  age     -- ms" in line and "nan" not in line and "99000" not in line

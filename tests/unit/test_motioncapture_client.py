"""The libmotioncapture adapter without the library: a scripted stand-in with the library's
Python interface (``connect``, ``waitForNextFrame``, ``rigidBodies``) drives the real adapter
thread; frame conversion, staleness, plausibility and hostile values."""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.mocap.frames import FrameConfig, quat_angle_rad
from drivers.mocap.motioncapture_client import (
    MotionCaptureClient,
    MotionCaptureConfig,
    library_options,
)
from drivers.mocap.pose import TrackingStatus, UnknownBodyError
from drivers.mocap.uri import MocapUriError, parse_uri


@dataclass
class Quaternion:
    w: float
    x: float
    y: float
    z: float


@dataclass
class RigidBody:
    position: tuple[float, float, float]
    rotation: Quaternion


class ScriptedLibrary:
    """Returns the scripted frames one per wait, then empty frames; records the connect."""

    def __init__(self, frames: list[dict[str, RigidBody]]) -> None:
        self.frames = frames
        self.connected: tuple[str, dict[str, str]] | None = None
        self.rigidBodies: dict[str, RigidBody] = {}
        self.drained = threading.Event()  # set once every scripted frame has been handled

    def connect(self, system: str, options: dict[str, str]) -> ScriptedLibrary:
        self.connected = (system, options)
        return self

    def waitForNextFrame(self) -> None:  # noqa: N802 (the library's name)
        if not self.frames:
            self.drained.set()  # the adapter handled the last frame before waiting again
            threading.Event().wait(0.005)
        self.rigidBodies = self.frames.pop(0) if self.frames else {}


class FakeClock:
    def __init__(self) -> None:
        self.t_ns = 1_000_000_000

    def __call__(self) -> int:
        return self.t_ns


def _optitrack(frames: list[dict[str, RigidBody]]
               ) -> tuple[MotionCaptureClient, ScriptedLibrary, FakeClock]:
    lib = ScriptedLibrary(frames)
    clock = FakeClock()
    cfg = parse_uri("motioncapture://optitrack?host=10.0.0.2&body=hex&latency_ms=4")
    assert isinstance(cfg, MotionCaptureConfig)
    return MotionCaptureClient(cfg, clock, connect=lib.connect), lib, clock


def test_that_an_optitrack_y_up_pose_becomes_the_z_up_world_pose() -> None:
    # Fixture: Motive Y-up, 1.5 m high, yawed 90 deg about Motive's up axis (y)
    s2 = math.sqrt(0.5)
    body = RigidBody((1.0, 1.5, 2.0), Quaternion(s2, 0.0, s2, 0.0))
    sut, lib, clock = _optitrack([{"other": body}, {"hex": body}])
    # Test
    with sut:
        s = sut.latest()
    # Assert
    assert lib.connected == ("optitrack", {"hostname": "10.0.0.2"})
    assert s is not None and s.valid and s.frame_number == 1
    assert s.pos_w_m == pytest.approx((1.0, -2.0, 1.5))  # N=x, up=y, y_world=-z
    assert quat_angle_rad(s.q_wb, (s2, 0.0, 0.0, s2)) < 1e-12  # yaw about world z
    assert s.t_ns == clock.t_ns - 4_000_000 and s.latency_s == pytest.approx(0.004)
    assert sut.bodies() == {"hex": 0, "other": 0}


def test_that_a_body_absent_for_the_staleness_limit_reads_missing() -> None:
    sut, _, clock = _optitrack([{"hex": RigidBody((0.0, 1.0, 0.0), Quaternion(1, 0, 0, 0))}])
    with sut:
        assert sut.latest() is not None and sut.latest().valid  # type: ignore[union-attr]
        clock.t_ns += 60_000_000
        s = sut.latest()
    assert s is not None and s.status is TrackingStatus.MISSING
    assert all(math.isnan(c) for c in s.pos_w_m + s.q_wb)


def test_that_implausible_poses_are_dropped_and_counted() -> None:
    good = RigidBody((0.0, 1.0, 0.0), Quaternion(1, 0, 0, 0))
    sut, lib, _ = _optitrack([
        {"hex": good},
        {"hex": RigidBody((0.0, 1.0, 0.0), Quaternion(0.5, 0, 0, 0))},  # |q| = 0.5
        {"hex": RigidBody((500.0, 1.0, 0.0), Quaternion(1, 0, 0, 0))},  # beyond 100 m
        {"hex": RigidBody((math.nan, 1.0, 0.0), Quaternion(1, 0, 0, 0))}])
    with sut:
        assert lib.drained.wait(10.0)
        s = sut.latest()
    assert sut.frames_seen == 1 and sut.stats().implausible_samples == 3
    assert s is not None and s.pos_w_m == pytest.approx((0.0, 0.0, 1.0))


def test_that_a_body_the_server_never_sends_is_an_error_listing_the_sent_ones() -> None:
    lib = ScriptedLibrary([{"pad": RigidBody((0.0, 0.0, 0.0), Quaternion(1, 0, 0, 0))}])
    cfg = MotionCaptureConfig(system="vicon", host="10.0.0.3", body="hex",
                              connect_timeout_s=0.3)
    with pytest.raises(UnknownBodyError, match=r"no rigid body named 'hex'.*sends pad"):
        MotionCaptureClient(cfg, connect=lib.connect).start()


@pytest.mark.parametrize("uri,up", [("motioncapture://vicon?host=h&body=b", "z"),
                                    ("motioncapture://qualisys?host=h&body=b", "z"),
                                    ("motioncapture://vrpn?host=h:3883&body=b", "z"),
                                    ("motioncapture://optitrack?host=h&body=b", "y"),
                                    ("motioncapture://optitrack?host=h&body=b&up=z", "z")])
def test_that_each_system_takes_its_world_up_axis_by_default(uri: str, up: str) -> None:
    cfg = parse_uri(uri)
    assert isinstance(cfg, MotionCaptureConfig) and cfg.frames.up_axis == up


@pytest.mark.parametrize("uri,fragment", [("motioncapture://kinect?host=h&body=b", "system"),
                                          ("motioncapture://vicon?host=h", "body"),
                                          ("motioncapture://vicon?body=b", "host"),
                                          ("motioncapture://vicon?host=h&body=b&x=1", "unknown")])
def test_that_a_bad_motioncapture_uri_is_a_typed_error(uri: str, fragment: str) -> None:
    with pytest.raises(MocapUriError, match=fragment):
        parse_uri(uri)


@pytest.mark.parametrize("system,host,options", [
    # QTM's RT port in the URI; the library wants the base port below it
    ("qualisys", "10.0.0.4:22223", {"hostname": "10.0.0.4", "port": "22222"}),
    ("qualisys", "10.0.0.4", {"hostname": "10.0.0.4"}),  # the library's default: 22222 + 1
    ("vrpn", "10.0.0.4:3883", {"hostname": "10.0.0.4:3883"}),  # VRPN parses HOST:PORT itself
    ("vicon", "10.0.0.4:801", {"hostname": "10.0.0.4:801"})])
def test_that_the_host_becomes_the_library_options_of_each_system(
        system: str, host: str, options: dict[str, str]) -> None:
    assert library_options(system, host) == options
    lib = ScriptedLibrary([{"hex": RigidBody((0.0, 0.0, 1.0), Quaternion(1, 0, 0, 0))}])
    cfg = parse_uri(f"motioncapture://{system}?host={host}&body=hex")
    assert isinstance(cfg, MotionCaptureConfig)
    with MotionCaptureClient(cfg, connect=lib.connect):
        assert lib.connected == (system, options)


@pytest.mark.parametrize("host", ["h:", "h:1", "h:65536", "h:port"])
def test_that_a_qualisys_host_port_out_of_range_is_a_typed_error(host: str) -> None:
    with pytest.raises(MocapUriError, match=r"TCP port 2\.\.65535"):
        parse_uri(f"motioncapture://qualisys?host={host}&body=b")


_floats = st.floats(allow_nan=True, allow_infinity=True, width=32)


@settings(max_examples=300, deadline=None)
@given(position=st.one_of(st.tuples(_floats, _floats, _floats), st.none(), st.text(),
                          st.lists(_floats, max_size=2)),
       q=st.tuples(_floats, _floats, _floats, _floats))
def test_that_any_values_from_the_library_never_raise_and_only_sane_poses_pass(
        position: Any, q: tuple[float, float, float, float]) -> None:
    cfg = MotionCaptureConfig(system="vicon", host="h", body="hex",
                              frames=FrameConfig(up_axis="z"))
    sut = MotionCaptureClient(cfg, clock=FakeClock())
    sut.on_body(position, Quaternion(*q), 1_000_000_000)
    s = sut.latest()
    if s is not None:
        assert s.valid and all(math.isfinite(c) for c in s.pos_w_m + s.q_wb)
        assert math.dist(s.pos_w_m, (0.0, 0.0, 0.0)) <= cfg.limits.max_range_m

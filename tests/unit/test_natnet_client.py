"""NatNetClient datagram handling without sockets: validity, timestamps, counters, hostility."""

from __future__ import annotations

import math
import socket
import threading

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.mocap import natnet
from drivers.mocap.natnet import FrameOfData, ModelDefinitions, RigidBodyData, ServerInfo
from drivers.mocap.natnet_client import NatNetClient, NatNetConfig
from drivers.mocap.pose import MocapConnectError, PoseSource, TrackingStatus

SERVER = ("10.1.1.5", 1510)
FREQ = 1_000_000


class FakeClock:
    def __init__(self) -> None:
        self.t_ns = 5_000_000_000

    def __call__(self) -> int:
        return self.t_ns


def _client(version: natnet.NatNetVersion = (4, 1)) -> tuple[NatNetClient, FakeClock]:
    clock = FakeClock()
    sut = NatNetClient(NatNetConfig(server_ip=SERVER[0], body="hex", network_delay_s=0.001),
                       clock=clock)
    sut._on_datagram(natnet.encode_server_info(ServerInfo(
        "Motive", (3, 1, 0, 0), (*version, 0, 0), FREQ, 1511, False, "239.255.42.99")), SERVER)
    sut._on_datagram(natnet.encode_modeldef(ModelDefinitions(
        (natnet.RigidBodyDescription("other", 2), natnet.RigidBodyDescription("hex", 4))),
        version), SERVER)
    sut._resolve_body()
    return sut, clock


def _frame(n: int, valid: bool = True, body_id: int = 4, latency_ticks: int = 4000
           ) -> FrameOfData:
    return FrameOfData(n, (RigidBodyData(2, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0), 0.0, True),
                           RigidBodyData(body_id, (1.0, 1.5, 2.0), (0.0, 0.0, 0.0, 1.0),
                                         0.0003, valid)),
                       camera_mid_exposure_ticks=10_000, transmit_ticks=10_000 + latency_ticks)


def test_that_the_client_is_a_pose_source() -> None:
    assert isinstance(_client()[0], PoseSource)


def test_that_a_tracked_body_is_converted_and_stamped_with_the_reported_latency() -> None:
    sut, clock = _client()
    sut._on_datagram(natnet.encode_frame(_frame(10), (4, 1)), SERVER)
    s = sut.latest()
    assert s is not None and s.valid and s.body_name == "hex" and s.frame_number == 10
    assert s.pos_w_m == pytest.approx((1.0, -2.0, 1.5))  # Y-up -> z-up
    # 4000 ticks at 1 MHz = 4 ms of system latency + 1 ms configured network delay
    assert s.latency_s == pytest.approx(0.005)
    assert s.rx_t_ns == clock.t_ns and s.t_ns == clock.t_ns - 5_000_000


def test_that_a_tracking_invalid_body_is_reported_invalid_and_never_as_the_stale_pose() -> None:
    sut, _ = _client()
    sut._on_datagram(natnet.encode_frame(_frame(1), (4, 1)), SERVER)
    sut._on_datagram(natnet.encode_frame(_frame(2, valid=False), (4, 1)), SERVER)
    s = sut.latest()
    assert s is not None and s.status is TrackingStatus.INVALID and s.frame_number == 2
    assert all(math.isnan(c) for c in s.pos_w_m + s.q_wb)
    assert sut.stats().invalid_samples == 1


def test_that_a_body_absent_from_the_frame_is_reported_missing() -> None:
    sut, _ = _client()
    sut._on_datagram(natnet.encode_frame(_frame(1, body_id=9), (4, 1)), SERVER)
    s = sut.latest()
    assert s is not None and s.status is TrackingStatus.MISSING and not s.valid


def test_that_frame_gaps_count_as_dropped_and_big_jumps_as_discontinuities() -> None:
    sut, _ = _client()
    for n in (1, 2, 5, 6, 50_000, 50_001, 3):
        sut._on_datagram(natnet.encode_frame(_frame(n), (4, 1)), SERVER)
    st_ = sut.stats()
    assert (st_.frames_received, st_.frames_dropped, st_.frame_jumps) == (7, 2, 2)


def test_that_datagrams_from_another_address_are_counted_and_ignored() -> None:
    sut, _ = _client()
    sut._on_datagram(natnet.encode_frame(_frame(1), (4, 1)), ("10.1.1.6", 1510))
    assert sut.latest() is None and sut.stats().foreign_packets == 1


def test_that_age_grows_on_the_injected_clock() -> None:
    sut, clock = _client()
    sut._on_datagram(natnet.encode_frame(_frame(1, latency_ticks=0), (4, 1)), SERVER)
    clock.t_ns += 30_000_000
    assert sut.stats().age_s == pytest.approx(0.031)


@settings(max_examples=300)
@given(data=st.binary(max_size=400))
def test_that_random_datagrams_never_raise_and_are_either_decoded_or_counted(data: bytes
                                                                            ) -> None:
    sut, _ = _client()
    sut._on_datagram(data, SERVER)
    before = sut.stats()
    sut._on_datagram(b"\x07\x00" + len(data).to_bytes(2, "little") + data, SERVER)
    after = sut.stats()
    assert (after.malformed_packets - before.malformed_packets) \
        + (after.frames_received - before.frames_received) == 1
    s = sut.latest()
    if s is not None and s.valid:
        assert all(math.isfinite(c) for c in s.pos_w_m + s.q_wb)


@pytest.mark.parametrize("version", natnet.SUPPORTED_VERSIONS)
def test_that_truncated_and_oversize_frames_never_produce_a_pose(
        version: natnet.NatNetVersion) -> None:
    sut, _ = _client(version)
    wire = natnet.encode_frame(_frame(1), version)
    for cut in range(len(wire)):
        sut._on_datagram(wire[:cut], SERVER)
    sut._on_datagram(wire + b"\0" * 8, SERVER)
    sut._on_datagram(wire + bytes(70_000), SERVER)
    assert sut.latest() is None
    assert sut.stats().malformed_packets == len(wire) + 2


def test_that_a_server_of_an_unsupported_version_is_refused_by_name() -> None:
    # Fixture: a one-shot server that answers CONNECT with a NatNet 2.10 SERVERINFO
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as srv:
        srv.bind(("127.0.0.1", 0))
        srv.settimeout(10.0)

        def answer() -> None:
            _, addr = srv.recvfrom(1024)
            srv.sendto(natnet.encode_server_info(ServerInfo(
                "Motive", (2, 2, 0, 0), (2, 10, 0, 0), 0, 1511, False, "239.255.42.99")), addr)

        t = threading.Thread(target=answer, daemon=True)
        t.start()
        cfg = NatNetConfig(command_port=srv.getsockname()[1], connect_timeout_s=10.0)
        # Test / Assert
        with pytest.raises(MocapConnectError, match=r"NatNet \(2, 10\)"):
            NatNetClient(cfg).start()
        t.join(10.0)


def test_that_waiting_sockets_tells_input_waiting_on_any_socket_and_follows_reopened_ones(
        ) -> None:
    from drivers.mocap.pose import WaitingSockets

    # Fixture: two bound UDP sockets, as a client's command and data sockets
    socks = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(3)]
    sender = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        for s in socks:
            s.bind(("127.0.0.1", 0))
            s.setblocking(False)
        waiting = WaitingSockets()
        pair = (socks[0], socks[1])
        # Test / Assert: nothing sent; a datagram on the second; read, nothing again
        assert not waiting.any(pair) and not waiting.any((None, None))
        sender.sendto(b"x", socks[1].getsockname())
        assert waiting.any(pair)
        assert socks[1].recv(16) == b"x" and not waiting.any(pair)
        # a re-opened data socket is watched, the old one no longer
        sender.sendto(b"y", socks[1].getsockname())
        sender.sendto(b"z", socks[2].getsockname())
        assert waiting.any((socks[0], None)) is False
        assert waiting.any((socks[0], socks[2]))
    finally:
        for s in (*socks, sender):
            s.close()

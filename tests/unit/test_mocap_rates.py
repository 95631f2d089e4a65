"""The measured MoCap stream rate: a sliding window on the injected clock, never a figure from
one or two arrivals (a burst of two reports in one TCP read read as 22 kHz)."""

from __future__ import annotations

from drivers.mocap import natnet, vrpn
from drivers.mocap.natnet import FrameOfData, ModelDefinitions, RigidBodyData, ServerInfo
from drivers.mocap.natnet_client import NatNetClient, NatNetConfig
from drivers.mocap.pose import MIN_RATE_SPAN_S, RATE_WINDOW_S, StreamMonitor
from drivers.mocap.vrpn import SystemType, TrackerPose, VrpnStreamParser
from drivers.mocap.vrpn_client import VrpnClient, VrpnConfig

T0_NS = 7_000_000_000
PERIOD_NS = 10_000_000  # a 100 Hz server
BURST_NS = 44_000  # the second report of a pair arrives 44 us after the first


class FakeClock:
    def __init__(self) -> None:
        self.t_ns = T0_NS

    def __call__(self) -> int:
        return self.t_ns


def _paired_arrivals(seconds: float) -> list[int]:
    """A 100 Hz stream that arrives in pairs every 20 ms (Nagle, a loaded network)."""
    out = []
    for k in range(round(seconds * 50)):
        t = T0_NS + k * 2 * PERIOD_NS
        out += [t, t + BURST_NS]
    return out


def test_that_two_frames_in_one_burst_give_no_rate_rather_than_a_spike() -> None:
    # Fixture
    clock = FakeClock()
    sut = StreamMonitor(clock)
    # Test
    sut.on_frame(1, T0_NS, 0.0)
    sut.on_frame(2, T0_NS + BURST_NS, 0.0)
    clock.t_ns = T0_NS + BURST_NS
    # Assert: the old figure was 1 / 44 us = 22727 Hz
    assert sut.snapshot().rate_hz == 0.0


def test_that_a_bursty_100_hz_stream_reads_100_hz_from_the_first_figure_on() -> None:
    # Fixture
    clock = FakeClock()
    sut = StreamMonitor(clock)
    rates = []
    # Test: 3 s of paired arrivals, the rate read after each one
    for n, t in enumerate(_paired_arrivals(3.0)):
        clock.t_ns = t
        sut.on_frame(n, t, 0.0)
        rates.append((t - T0_NS, sut.snapshot().rate_hz))
    # Assert
    early = [r for dt, r in rates if dt < MIN_RATE_SPAN_S * 1e9]
    measured = [r for dt, r in rates if dt >= MIN_RATE_SPAN_S * 1e9]
    assert early and all(r == 0.0 for r in early)
    assert measured and all(92.0 <= r <= 108.0 for r in measured), (min(measured),
                                                                     max(measured))
    steady = [r for dt, r in rates if dt >= RATE_WINDOW_S * 1e9]
    assert all(99.0 <= r <= 101.0 for r in steady)


def test_that_a_stream_that_stops_reads_a_falling_rate_down_to_zero() -> None:
    clock = FakeClock()
    sut = StreamMonitor(clock)
    arrivals = _paired_arrivals(2.0)
    for n, t in enumerate(arrivals):
        clock.t_ns = t
        sut.on_frame(n, t, 0.0)
    last = arrivals[-1]
    clock.t_ns = last + round(RATE_WINDOW_S * 1e9 / 2)
    assert 45.0 <= sut.snapshot().rate_hz <= 55.0
    clock.t_ns = last + round(RATE_WINDOW_S * 1e9)
    assert sut.snapshot().rate_hz == 0.0


def _vrpn_client(clock: FakeClock) -> tuple[VrpnClient, VrpnStreamParser]:
    sut = VrpnClient(VrpnConfig(tracker="Hex"), clock=clock)
    parser = VrpnStreamParser(expect_cookie=False)
    sut._handle(parser.feed(vrpn.encode_description(SystemType.SENDER_DESCRIPTION, 4, "Hex")
                            + vrpn.encode_description(SystemType.TYPE_DESCRIPTION, 2,
                                                      vrpn.POS_QUAT_TYPE)))
    return sut, parser


def test_that_the_vrpn_client_reports_the_windowed_rate_of_bursty_reports() -> None:
    # Fixture
    clock = FakeClock()
    sut, parser = _vrpn_client(clock)
    report = vrpn.encode_pos_quat(TrackerPose(0, (1.0, 2.0, 3.0), (0.0, 0.0, 0.0, 1.0)))
    rates = []
    # Test: every report stamped on the server at its arrival (zero latency)
    for t in _paired_arrivals(1.5):
        clock.t_ns = t
        sut._handle(parser.feed(vrpn.encode_message(4, 2, report, t * 1e-9)))
        rates.append((t - T0_NS, sut.stats().rate_hz))
    # Assert
    assert sut.stats().frames_received == 150
    assert all(r == 0.0 for dt, r in rates[:4])
    assert all(92.0 <= r <= 108.0 for dt, r in rates if dt >= MIN_RATE_SPAN_S * 1e9)


def test_that_the_natnet_client_reports_the_windowed_rate_of_bursty_frames() -> None:
    # Fixture
    clock = FakeClock()
    server = ("10.1.1.5", 1510)
    sut = NatNetClient(NatNetConfig(server_ip=server[0], body="hex"), clock=clock)
    sut.feed_datagram(natnet.encode_server_info(ServerInfo(
        "Motive", (3, 1, 0, 0), (4, 1, 0, 0), 0, 1511, False, "239.255.42.99")), server)
    sut.feed_datagram(natnet.encode_modeldef(ModelDefinitions(
        (natnet.RigidBodyDescription("hex", 4),)), (4, 1)), server)
    sut._resolve_body()
    rates = []
    # Test
    for n, t in enumerate(_paired_arrivals(1.5)):
        clock.t_ns = t
        frame = FrameOfData(n + 1, (RigidBodyData(4, (1.0, 1.5, 2.0), (0.0, 0.0, 0.0, 1.0),
                                                  0.0003, True),))
        sut.feed_datagram(natnet.encode_frame(frame, (4, 1)), server)
        rates.append((t - T0_NS, sut.stats().rate_hz))
    # Assert
    assert sut.stats().frames_received == 150 and sut.stats().frames_dropped == 0
    assert all(r == 0.0 for dt, r in rates[:4])
    assert all(92.0 <= r <= 108.0 for dt, r in rates if dt >= MIN_RATE_SPAN_S * 1e9)

"""Parse cost of one NatNet frame with 4 rigid bodies (target: < 50 us per frame).

Measured per call (``perf_counter_ns`` around each call, after a warm-up), for a frame as
Motive sends it: 4 rigid bodies, a marker set of 4 markers per body and 16 labeled markers.

- ``decode``: :func:`drivers.mocap.natnet.decode_message` alone, and without building the
  markers (``markers=False``, what the client asks for: it hands out rigid-body poses);
- ``client``: the whole receive path of :class:`NatNetClient` for one datagram (decode,
  frame-number bookkeeping, axis/units conversion of every body, mailbox update);
- baseline, same bytes, same process: the independent PyPI ``natnet`` parser
  (``DataFrame.read_from_buffer``) if installed, else one ``struct.unpack_from`` per body.

Run: ``python benchmarks/bench_mocap.py [--n 20000]``. Prints median, p99 and the ratio of our
median to the baseline's.
"""

from __future__ import annotations

import argparse
import struct
import time
from collections.abc import Callable
from functools import partial

from drivers.mocap import natnet
from drivers.mocap.frames import FrameTransform, quat_from_axis_angle
from drivers.mocap.natnet_client import NatNetClient, NatNetConfig


def make_frame(n_bodies: int = 4) -> natnet.FrameOfData:
    t = FrameTransform()
    rbs, sets, labeled = [], [], []
    for i in range(n_bodies):
        pos, q = t.to_mocap((0.5 * i, -1.0, 1.2), quat_from_axis_angle((0.1, 0.2, 1.0), 0.3 * i))
        rbs.append(natnet.RigidBodyData(i + 1, pos, q, 0.0003, True))
        markers = tuple((pos[0] + 0.1 * k, pos[1], pos[2] - 0.05 * k) for k in range(4))
        sets.append(natnet.MarkerSetData(f"body{i + 1}", markers))
        labeled += [natnet.LabeledMarker(((i + 1) << 16) | (k + 1), m, 0.014, 0x04, 0.0002)
                    for k, m in enumerate(markers)]
    return natnet.FrameOfData(1000, tuple(rbs), tuple(sets), (), (), tuple(labeled),
                              timestamp_s=10.0, camera_mid_exposure_ticks=100_000_000,
                              data_received_ticks=100_020_000, transmit_ticks=100_040_000,
                              precision_timestamp=(10, 0))


def measure(fn: Callable[[], object], n: int) -> list[int]:
    for _ in range(min(2000, n)):
        fn()
    out = []
    clock = time.perf_counter_ns
    for _ in range(n):
        t0 = clock()
        fn()
        out.append(clock() - t0)
    out.sort()
    return out


def stats(ns: list[int]) -> tuple[float, float]:
    return ns[len(ns) // 2] / 1e3, ns[min(len(ns) - 1, int(len(ns) * 0.99))] / 1e3


def baseline_fn(wire: bytes, version: natnet.NatNetVersion) -> tuple[str, Callable[[], object]]:
    try:
        from natnet.data_frame import DataFrame  # type: ignore[import-untyped]
        from natnet.packet_buffer import PacketBuffer  # type: ignore[import-untyped]
        from natnet.version import Version  # type: ignore[import-untyped]
    except ImportError:
        rb = struct.Struct("<i3f4ffh")

        def raw() -> object:
            return [rb.unpack_from(wire, 40 + 38 * i) for i in range(4)]

        return "struct.unpack_from x4", raw
    v = Version(*version)
    return "PyPI natnet parser", lambda: DataFrame.read_from_buffer(PacketBuffer(wire[4:]), v)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=20000, help="calls per measurement")
    args = ap.parse_args()
    frame = make_frame()
    print(f"NatNet frame with 4 rigid bodies, 16 markers; {args.n} calls each; microseconds")
    print(f"{'version':8s} {'what':28s} {'median':>8s} {'p99':>8s} {'x baseline':>11s}")
    for version in ((3, 1), (4, 1)):
        wire = natnet.encode_frame(frame, version)
        client = NatNetClient(NatNetConfig(server_ip="127.0.0.1", body="body1"))
        server = ("127.0.0.1", 1510)
        client._on_datagram(natnet.encode_server_info(natnet.ServerInfo(
            "bench", (3, 1, 0, 0), (*version, 0, 0), 10_000_000, 1511, False,
            "239.255.42.99")), server)
        client._on_datagram(natnet.encode_modeldef(natnet.ModelDefinitions(tuple(
            natnet.RigidBodyDescription(f"body{i + 1}", i + 1) for i in range(4))), version),
            server)
        client._resolve_body()
        name, base = baseline_fn(wire, version)
        b_med, b_p99 = stats(measure(base, args.n))
        vtxt = f"{version[0]}.{version[1]} ({len(wire)} B)"
        rows: list[tuple[str, Callable[[], object]]] = [
            ("decode_message", partial(natnet.decode_message, wire, version)),
            ("decode, markers not built", partial(natnet.decode_message, wire, version,
                                                  markers=False)),
            ("client receive path", partial(client._on_datagram, wire, server))]
        for what, fn in rows:
            med, p99 = stats(measure(fn, args.n))
            print(f"{vtxt:8s} {what:28s} {med:8.1f} {p99:8.1f} {med / b_med:10.2f}x")
        print(f"{vtxt:8s} {'baseline: ' + name:28s} {b_med:8.1f} {b_p99:8.1f} {1.0:10.2f}x")
    print("target: decode and client path median < 50 us per frame")


if __name__ == "__main__":
    main()

"""Cost of the MAVLink bridge: per telemetry cycle, per snapshot handed over, per command.

Run: ``python benchmarks/bench_mavlink.py [--n 3000]``. Prints the median and p99 of each
measurement (microseconds) and its ratio to a baseline measured in the same process: pymavlink
encoding one unsigned ATTITUDE (the spec's reference figure, about 12 us). A "cycle" is one
``bridge.step`` in which all eight periodic messages are due (HEARTBEAT, SYS_STATUS,
EXTENDED_SYS_STATE, ATTITUDE, ATTITUDE_QUATERNION, LOCAL_POSITION_NED, ODOMETRY,
ACTUATOR_OUTPUT_STATUS), built from a snapshot, encoded, signed or not, and sent over UDP
loopback. The last line estimates the share of one core the bridge takes at the default rates
(154 messages/s). The ``feed`` lines are the cost of one hostile frame through the bridge's input
path (rejected by the signature check, or decoded and refused without a key, with its
COMMAND_ACK sent).
"""

from __future__ import annotations

import argparse
import hashlib
import itertools
import math
import socket
import statistics
import time
from collections.abc import Callable, Iterator

from pymavlink.dialects.v20 import common as mavlink2

from drivers.mavlink import MavlinkConfig
from drivers.mavlink.frames import q_from_euler
from drivers.mavlink.link import MavlinkCodec
from groundstation.mavlink_bridge import MavlinkBridge
from groundstation.operator import (
    FlightPhase,
    RuleBasedCommandSink,
    SensorHealth,
    VehicleTelemetry,
)

KEY = hashlib.sha256(b"labpass").digest()


def snapshot(t_s: float) -> VehicleTelemetry:
    return VehicleTelemetry(
        t_s=t_s, phase=FlightPhase.MISSION, armed=True, pos_w_m=(0.1, 0.2, 1.0),
        vel_w_m_s=(0.01, 0.0, 0.0), q_wb=q_from_euler(0.05, -0.02, 0.5),
        omega_b_rad_s=(0.01, 0.02, 0.03), rotor_speeds_hz=(60.0,) * 6, tilt_rad=0.3,
        battery_v=15.5, health=SensorHealth(preflight_ok=True))


def measure(fn: Callable[[int], object], n: int) -> list[float]:
    """Per-call durations in microseconds (after a short warm-up)."""
    for i in range(min(200, n)):
        fn(i)
    out = []
    for i in range(n):
        t0 = time.perf_counter_ns()
        fn(i)
        out.append((time.perf_counter_ns() - t0) / 1000.0)
    return out


def p99(xs: list[float]) -> float:
    s = sorted(xs)
    return s[min(len(s) - 1, math.ceil(0.99 * len(s)) - 1)]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=3000, help="samples per measurement")
    args = ap.parse_args()
    n = args.n

    sink_sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)  # never read: the kernel drops
    sink_sock.bind(("127.0.0.1", 0))
    port = sink_sock.getsockname()[1]

    codec = MavlinkCodec(1, 1)
    att = mavlink2.MAVLink_attitude_message(1000, 0.1, 0.2, 0.3, 0.01, 0.02, 0.03)
    baseline = measure(lambda i: codec.encode(att), n)

    def bridge(signing: bool) -> MavlinkBridge:
        cfg = MavlinkConfig(uri=f"udpout:127.0.0.1:{port}", signing=signing)
        return MavlinkBridge(cfg, RuleBasedCommandSink(FlightPhase.MISSION),
                             key=KEY if signing else None)

    results: dict[str, list[float]] = {"baseline: encode 1 ATTITUDE": baseline}
    for signing in (False, True):
        b = bridge(signing)
        tel = snapshot(0.0)
        b.publish(tel)
        # each step 1 s later than the last: all eight periodic messages are due
        clock = itertools.count()
        label = "signed" if signing else "unsigned"

        def cycle(_i: int, b: MavlinkBridge = b, clock: Iterator[int] = clock) -> None:
            b.step(float(next(clock)))

        def hand_over(_i: int, b: MavlinkBridge = b, tel: VehicleTelemetry = tel) -> None:
            b.publish(tel)

        results[f"telemetry cycle, 8 msgs, {label}"] = measure(cycle, n)
        sent = b.stats().messages_out
        assert sent["ATTITUDE"] == sent["ACTUATOR_OUTPUT_STATUS"] == min(200, n) + n, sent
        results[f"publish(snapshot), {label}"] = measure(hand_over, n)
        b.close()

    # incoming: decode + verify one signed COMMAND_LONG (a fresh signature each time)
    peer = MavlinkCodec(255, 190, KEY)
    frames = [peer.encode(mavlink2.MAVLink_command_long_message(
        1, 1, mavlink2.MAV_CMD_REQUEST_MESSAGE, 0, 0, 0, 0, 0, 0, 0, 0)) for _ in range(n + 200)]
    rx = MavlinkCodec(1, 1, KEY)
    fresh = iter(frames)
    results["decode + verify 1 signed COMMAND_LONG"] = measure(
        lambda i: rx.decode(next(fresh)), n)
    assert rx.verifier is not None and rx.verifier.stats().good == min(200, n) + n

    # hostile input, through the bridge's own input path: what an attacker's frame costs us
    land = mavlink2.MAVLink_command_long_message(1, 1, mavlink2.MAV_CMD_NAV_LAND, 0,
                                                 0, 0, 0, 0, 0, 0, 0)
    unsigned_land = MavlinkCodec(66, 190).encode(land)
    wrong_land = MavlinkCodec(66, 190, hashlib.sha256(b"guess").digest()).encode(land)
    for label, signing, frame in (("unsigned NAV_LAND, signing bridge", True, unsigned_land),
                                  ("wrong-key NAV_LAND, signing bridge", True, wrong_land),
                                  ("unsigned NAV_LAND, keyless: DENIED", False,
                                   unsigned_land)):
        b = bridge(signing)

        def feed(_i: int, b: MavlinkBridge = b, f: bytes = frame) -> None:
            b.feed(f, 0.0)

        results[f"feed: {label}"] = measure(feed, n)
        st = b.stats()
        assert st.handler_errors == 0 and st.command_results.get("ACCEPTED", 0) == 0, st
        b.close()
    sink_sock.close()

    base_med = statistics.median(baseline)
    print(f"{'measurement':45s} {'median us':>10s} {'p99 us':>10s} {'/ baseline':>10s}")
    for name, xs in results.items():
        med = statistics.median(xs)
        print(f"{name:45s} {med:10.1f} {p99(xs):10.1f} {med / base_med:10.2f}")
    signed_cycle = statistics.median(results["telemetry cycle, 8 msgs, signed"])
    per_msg = signed_cycle / 8.0
    print(f"default rates (154 msg/s), signed: {154 * per_msg / 1e4:.2f} % of one core "
          f"({per_msg:.1f} us per message)")


if __name__ == "__main__":
    main()

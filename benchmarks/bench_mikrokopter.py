"""Flight-Ctrl link costs: codec work per 500 Hz tick, and the IMU -> `w` round trip on a pty.

Run: ``python benchmarks/bench_mikrokopter.py [--ticks N]``. Prints medians and p99 in µs and
the ratio against a baseline measured in the same process:

1. codec per tick = encode one ``w`` (six spin rates in Hz -> framed bytes) + deframe and decode
   one ``I`` (bytes -> SI sample in the body frame). Baseline: bare ``struct`` pack + unpack of
   the same payloads (no framing, no conversions). Target: < 30 µs per tick.
2. IMU in -> ``w`` out: from the reader thread's timestamp of an ``I`` frame to the ``w`` frame
   written by the loop thread (``FlightCtrl.wait_next`` + ``send_rotor_speeds_hz``), against the
   lockstep emulator. Target (architecture.md): median < 0.5 ms.
3. Full round trip ``w`` out -> next ``I`` in (through the emulator, which steps the bench
   vehicle). Baseline: a bare echo of 15 bytes through a pty by a thread doing only
   ``select`` + ``read`` + ``write``.
"""

from __future__ import annotations

import argparse
import os
import statistics
import struct
import sys
import threading
import time

from drivers.mikrokopter import FlightCtrl, FlightCtrlConfig, ImuAxes
from drivers.mikrokopter import framing_tk3 as tk3
from drivers.mikrokopter import messages as mkm
from drivers.transport import open_transport
from sim_backend.emulators.flightctrl import EmulatedFlightCtrl, FlightCtrlEmulatorConfig
from sim_backend.ptylink import PtyEndpoint
from sim_backend.vehicle import BenchVehicle


def _summary(name: str, samples_ns: list[int], baseline_ns: list[int] | None = None) -> None:
    us = sorted(s / 1000 for s in samples_ns)
    med = statistics.median(us)
    p99 = us[min(len(us) - 1, int(0.99 * len(us)))]
    line = f"{name:<44} median {med:8.2f} us   p99 {p99:8.2f} us   n={len(us)}"
    if baseline_ns:
        base = statistics.median(baseline_ns) / 1000
        line += f"   baseline median {base:7.2f} us   ratio {med / base:5.1f}x"
    print(line)


def bench_codec(ticks: int) -> None:
    speeds = [60.0, 70.0, 80.0, 90.0, 100.0, 50.0]
    axes = ImuAxes()
    imu_wire = tk3.encode_frame(
        mkm.ImuMessage(7, (0.12, -0.05, 9.81), (0.01, -0.02, 0.03)).encode())
    parser = tk3.Tk3Parser()
    w_struct = struct.Struct(">6h")
    i_struct = struct.Struct(">B3h3h")
    i_payload = imu_wire[2:-1]
    ours: list[int] = []
    base: list[int] = []
    clock = time.perf_counter_ns
    for _ in range(ticks):
        t0 = clock()
        frame = tk3.encode_frame(mkm.SpinRates.from_hz(speeds).encode())
        (raw,) = parser.feed(imu_wire)
        msg = mkm.decode_board_message(raw)
        assert isinstance(msg, mkm.ImuMessage)
        body = axes.imu_to_body(msg)
        t1 = clock()
        ours.append(t1 - t0)
        t0 = clock()
        frame = w_struct.pack(5000, 4901, 6250, 5555, 5000, 10000)
        values = i_struct.unpack(i_payload)
        t1 = clock()
        base.append(t1 - t0)
    del frame, body, values
    _summary("codec per tick (w encode + I decode)", ours, base)


def _pty_echo_baseline(n: int) -> list[int]:
    pty = PtyEndpoint()
    client = open_transport(f"pty://{pty.path}")
    stop = threading.Event()

    def echo() -> None:
        while not stop.is_set():
            if pty.wait_readable(0.05):
                data = pty.read()
                if data:
                    pty.write(data)

    thread = threading.Thread(target=echo, daemon=True)
    thread.start()
    payload = b"^w" + bytes(12) + b"$"
    out: list[int] = []
    for _ in range(n):
        t0 = time.perf_counter_ns()
        client.write(payload)
        got = b""
        while len(got) < len(payload):
            got += client.read(64)
        out.append(time.perf_counter_ns() - t0)
    stop.set()
    thread.join()
    client.close()
    pty.close()
    return out


def bench_round_trip(ticks: int) -> None:
    emu = EmulatedFlightCtrl(BenchVehicle(seed=1),
                             config=FlightCtrlEmulatorConfig(clock="lockstep")).start()
    fc = FlightCtrl.open(f"pty://{emu.path}", FlightCtrlConfig(imu_rate_hz=500.0))
    fc.connect()
    in_to_out: list[int] = []
    round_trip: list[int] = []
    last_w_ns: int | None = None
    speeds = [50.0] * 6
    clock = time.monotonic_ns
    t_start = time.monotonic()
    sim_start = emu.sim_time_s()
    for _ in range(ticks + 50):
        sample = fc.wait_next(1.0)
        if sample is None:
            raise RuntimeError("IMU stream stopped")
        if last_w_ns is not None:
            round_trip.append(sample.arrival_t_ns - last_w_ns)
        fc.send_rotor_speeds_hz(speeds)
        last_w_ns = clock()
        in_to_out.append(last_w_ns - sample.arrival_t_ns)
    wall = time.monotonic() - t_start
    sim = emu.sim_time_s() - sim_start
    stats = fc.link_stats()
    fc.close()
    emu.stop()
    baseline = _pty_echo_baseline(ticks)
    _summary("IMU in -> w out (reader -> loop -> write)", in_to_out[50:])
    _summary("w out -> next I in (through the emulator)", round_trip[50:], baseline)
    print(f"lockstep speed: {sim / wall:.1f}x real time ({ticks + 50} ticks, "
          f"{stats.dropped} dropped frames)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--ticks", type=int, default=5000)
    args = parser.parse_args()
    print(f"python {sys.version.split()[0]}, {os.cpu_count()} CPUs")
    bench_codec(args.ticks * 4)
    bench_round_trip(args.ticks)


if __name__ == "__main__":
    main()

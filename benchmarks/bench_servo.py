"""What the tilt servo costs: one bus cycle over the pty, and the 500 Hz loop with it running.

1. One goal-write + present-read cycle (the driver's per-cycle traffic: WRITE Goal Position,
   READ 36..46) through dynamixel-sdk 4.1.0 against the emulated MX-28T in its own process;
   baseline in the same run: a single 2-byte Present Position read.
2. A 500 Hz dummy control loop (fixed numpy work per tick, ``set_tilt`` + ``latest`` each tick):
   per-tick compute time and period jitter, p50/p99, with no servo (baseline), with the
   TiltServo in its own process (the design), and with the SDK in a thread of the loop's
   process (what the process avoids: the SDK busy-polls holding the GIL).
3. Fault detection latency: the emulated servo stops answering -> ``latest().health`` leaves OK.
4. A lockstep servo cycle (``serve: on_request``): ``begin_cycle``, the tick's work (a fixed
   ~60 us of numerics, what a lockstep tick computes between the two), ``finish_cycle``; what
   the cycle adds to the tick, served by the servo process (baseline) and inline (the SDK in
   the loop's thread, split around the work: what lockstep flights use), interleaved rounds.

Run: ``python benchmarks/bench_servo.py [--seconds 6 --rounds 3]``. Numbers vary with machine load.
"""

from __future__ import annotations

import argparse
import math
import multiprocessing as mp
import tempfile
import threading
import time
from dataclasses import replace
from pathlib import Path
from typing import Any, Literal

import numpy as np

from drivers.dynamixel import ServoHealth, TiltServo, TiltServoConfig
from drivers.dynamixel.control_table import Reg
from drivers.realtime import hold_cpu_latency, release_cpu_latency
from sim_backend.emulators.dynamixel_p1 import EmulatedMX28, Fault, serve_bench_servo
from sim_backend.vehicle import BenchVehicle

TICK_S = 0.002
WORK_ITERATIONS = 150
"""Numerics per dummy tick: about 0.25 ms, the median the real tick aims at."""


def pct(values: np.ndarray, q: float) -> float:
    return float(np.percentile(values, q))


def start_emulator_process(link: Path) -> tuple[Any, Any, Any]:
    ctx = mp.get_context("spawn")
    stop, ready, silent = ctx.Event(), ctx.Event(), ctx.Event()
    proc = ctx.Process(target=serve_bench_servo, args=(str(link), stop, ready, silent),
                       daemon=True)
    proc.start()
    if not ready.wait(30.0):
        raise RuntimeError("emulator process did not start")
    return proc, stop, silent


def bus_cycle(link: Path, n: int) -> None:
    import dynamixel_sdk as sdk

    port = sdk.PortHandler(str(link))
    port.openPort()
    ph = sdk.PacketHandler(1.0)
    ph.write4ByteTxRx(port, 1, Reg.CW_ANGLE_LIMIT, 0x0FFF0FFF)

    def read_only() -> int:
        return int(ph.read2ByteTxRx(port, 1, Reg.PRESENT_POSITION)[1])

    def cycle() -> int:
        ph.write2ByteTxRx(port, 1, Reg.GOAL_POSITION, 100)
        return int(ph.readTxRx(port, 1, 36, 11)[1])

    cases = (("present read (baseline)", read_only, 0.0),
             ("goal write + 36..46 read", cycle, 0.0),
             ("same, blocking 1 ms reads", cycle, 0.001))
    medians: dict[str, float] = {}
    for name, fn, block_s in cases:
        port.ser.timeout = block_s  # 0: the SDK's own busy-poll; > 0: what TiltServo sets
        wall = np.empty(n)
        cpu = np.empty(n)
        failures = 0
        for i in range(n):
            t0, c0 = time.perf_counter(), time.process_time()
            failures += fn() != sdk.COMM_SUCCESS
            wall[i] = (time.perf_counter() - t0) * 1e3
            cpu[i] = (time.process_time() - c0) * 1e3
        medians[name] = float(np.median(wall))
        print(f"  {name:28} median {np.median(wall):6.3f} ms  p99 {pct(wall, 99):6.3f} ms  "
              f"max {wall.max():6.2f} ms  cpu/cycle {cpu.mean():6.3f} ms  "
              f"ratio {medians[name] / medians['present read (baseline)']:4.2f}  "
              f"failures {failures}/{n}")
    port.closePort()


def dummy_loop(seconds: float,
               servo: TiltServo | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ticks at 500 Hz; returns per-tick numerics time (ms), period error (ms) and the time of
    the servo calls (set_tilt + latest, us)."""
    rng = np.random.default_rng(0)
    a = rng.standard_normal((12, 12))
    n = int(seconds / TICK_S)
    compute = np.empty(n)
    jitter = np.empty(n)
    mailbox = np.zeros(n)
    next_t = time.perf_counter() + TICK_S
    last_start = next_t - TICK_S
    for i in range(n):
        while True:  # sleep most of the way, then spin: how a 500 Hz loop keeps its period
            remaining = next_t - time.perf_counter()
            if remaining <= 0:
                break
            if remaining > 3e-4:
                time.sleep(remaining - 2e-4)
        start = time.perf_counter()
        jitter[i] = (start - last_start - TICK_S) * 1e3
        last_start = start
        # The tick: a fixed amount of numerics (a stand-in for UKF + controller) ...
        m = a
        for _ in range(WORK_ITERATIONS):
            m = np.tanh(m @ a * 0.1)
        done = time.perf_counter()
        compute[i] = (done - start) * 1e3
        # ... and the servo's part: one mailbox write, one mailbox read.
        if servo is not None:
            servo.set_tilt(math.radians(17.5 + 17.5 * math.sin(i * TICK_S)))
            servo.latest()
            mailbox[i] = (time.perf_counter() - done) * 1e6
        next_t += TICK_S
        if next_t < time.perf_counter():
            next_t = time.perf_counter() + TICK_S
    return compute[50:], jitter[50:], mailbox[50:]


PHASES: tuple[tuple[str, str | None, bool, float], ...] = (
    # name, isolation, servo silent (every transaction waits the full timeout), read block ms
    ("no servo (baseline)", None, False, 1.0),
    ("servo process", "process", False, 1.0),
    ("servo process, silent servo", "process", True, 1.0),
    ("SDK thread, same process", "thread", False, 1.0),
    ("SDK thread, silent servo", "thread", True, 1.0),
    ("SDK thread, busy-poll, silent", "thread", True, 0.0),
)


def loop_phases(link: Path, seconds: float, rounds: int, silent: Any) -> None:
    """Each phase runs ``rounds`` times, interleaved with the others, so that a change in the
    machine's load hits every phase alike."""
    cfg = TiltServoConfig(uri=f"serial://{link}?baud=1000000&id=1", rate_hz=100.0)
    acc: dict[str, list[np.ndarray]] = {}

    def run(name: str, isolation: str | None, quiet: bool, block_ms: float) -> None:
        servo = None
        if isolation is not None:
            servo = TiltServo(replace(cfg, sdk_read_block_ms=block_ms),
                              isolation="process" if isolation == "process" else "thread")
            servo.start()
            servo.wait_for(lambda s: s.ok, 30.0)
        if quiet:
            silent.set()
        compute, jitter, mailbox = dummy_loop(seconds / rounds, servo)
        silent.clear()
        if servo is not None:
            servo.wait_for(lambda s: s.ok, 30.0)
            servo.stop()
        for key, arr in (("c", compute), ("j", np.abs(jitter)), ("m", mailbox)):
            acc.setdefault(name + key, []).append(arr)

    for _ in range(rounds):
        for name, isolation, quiet, block_ms in PHASES:
            run(name, isolation, quiet, block_ms)
    base_c = np.concatenate(acc[PHASES[0][0] + "c"])
    base_j = np.concatenate(acc[PHASES[0][0] + "j"])
    print(f"  {'phase':30} {'numerics p50':>12} {'p99':>7} {'|jitter| p99':>12} "
          f"{'>0.5ms':>7} {'numerics p99/base':>17} {'jitter p99/base':>15} "
          f"{'servo calls p50':>15}")
    for name, *_ in PHASES:
        compute = np.concatenate(acc[name + "c"])
        jitter = np.concatenate(acc[name + "j"])
        mailbox = np.concatenate(acc[name + "m"])
        late = float(np.mean(jitter > 0.5) * 100)
        print(f"  {name:30} {np.median(compute):10.3f}ms {pct(compute, 99):6.3f}ms "
              f"{pct(jitter, 99):10.3f}ms {late:6.2f}% "
              f"{pct(compute, 99) / pct(base_c, 99):17.2f} "
              f"{pct(jitter, 99) / pct(base_j, 99):15.2f} "
              f"{np.median(mailbox):13.1f}us")


def fault_detection(trials: int) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        vehicle = BenchVehicle(max_tilt_rate_rad_s=math.radians(100.0))
        emu = EmulatedMX28(vehicle, lock=threading.Lock(), link_path=Path(tmp) / "servo",
                           drive_clock=True)
        with emu, TiltServo(TiltServoConfig(uri=emu.path, rate_hz=50.0)) as servo:
            latencies = []
            for _ in range(trials):
                servo.wait_for(lambda s: s.ok, 30.0)
                time.sleep(0.05)
                t0 = time.monotonic()
                emu.set_fault(Fault.SILENT)
                while servo.latest().health is ServoHealth.OK:
                    time.sleep(0.0005)
                latencies.append((time.monotonic() - t0) * 1e3)
                emu.set_fault(Fault.NONE)
        lat = np.array(latencies)
        print(f"  servo silent -> health not OK: median {np.median(lat):.1f} ms  "
              f"p99 {pct(lat, 99):.1f} ms  max {lat.max():.1f} ms  (n={trials}, target 100 ms)")


def _work_us(target_us: float) -> Any:
    """A fixed piece of numerics taking about ``target_us`` (calibrated here, once)."""
    a = np.random.default_rng(1).random((6, 6))

    def work(k: int) -> None:
        for _ in range(k):
            a @ a

    k = 1
    while True:
        t0 = time.perf_counter_ns()
        work(k)
        if time.perf_counter_ns() - t0 >= target_us * 1e3:
            return lambda: work(k)
        k *= 2 if k < 4 else 1
        k += 1


def lockstep_cycles(link: Path, cycles: int, rounds: int) -> None:
    work = _work_us(60.0)
    base = np.array([_timed_ns(work) for _ in range(500)]) / 1e3
    samples: dict[str, list[float]] = {"process": [], "inline": []}
    isolations: tuple[Literal["process", "inline"], ...] = ("process", "inline")
    for _ in range(rounds):
        for isolation in isolations:
            cfg = TiltServoConfig(uri=f"pty://{link}?id=1", serve="on_request",
                                  rate_limit_goal=False, late_reply_retries=2)
            servo = TiltServo(cfg, isolation).start()
            try:
                deadline = time.monotonic() + 20.0
                while True:  # "not connected" until configured
                    try:
                        servo.sync_cycle(5.0)
                        break
                    except Exception:
                        if time.monotonic() > deadline:
                            raise
                        time.sleep(0.05)
                for _ in range(cycles // rounds):
                    t0 = time.perf_counter_ns()
                    servo.begin_cycle()
                    work()
                    servo.finish_cycle(5.0)
                    samples[isolation].append((time.perf_counter_ns() - t0) / 1e3)
                    time.sleep(0.002)  # the other ticks of the servo period
            finally:
                servo.stop()
    work_us = float(np.median(base))
    print(f"  the work alone: median {work_us:6.1f} us")
    proc = np.array(samples["process"])
    for name in ("process", "inline"):
        v = np.array(samples[name])
        added = np.median(v) - work_us
        print(f"  {name:8} begin + work + finish: median {np.median(v):6.1f} us  p99 "
              f"{pct(v, 99):7.1f} us  added to the tick {added:6.1f} us  "
              f"ratio to process {np.median(v) / np.median(proc):4.2f}")


def _timed_ns(fn: Any) -> int:
    t0 = time.perf_counter_ns()
    fn()
    return time.perf_counter_ns() - t0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=6.0, help="per loop phase, in total")
    parser.add_argument("--rounds", type=int, default=3, help="interleaved rounds of phases")
    parser.add_argument("--cycles", type=int, default=2000, help="bus cycles per case")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        link = Path(tmp) / "tilt-servo"
        proc, stop, silent = start_emulator_process(link)
        try:
            print("1. one bus cycle over the pty (SDK here, emulator in its own process)")
            bus_cycle(link, args.cycles)
            print("2. 500 Hz dummy loop, same run")
            loop_phases(link, args.seconds, args.rounds, silent)
            # as a lockstep flight runs it: the CPUs held out of deep idle (drivers.realtime)
            held = hold_cpu_latency()
            print(f"4. a lockstep servo cycle around the tick's work, same run ({held})")
            try:
                lockstep_cycles(link, args.cycles, args.rounds)
            finally:
                release_cpu_latency()
        finally:
            stop.set()
            proc.join(5.0)
    print("3. fault detection")
    fault_detection(20)


if __name__ == "__main__":
    main()

"""The speed table: every figure the campaigns and the 1 kHz loop depend on, each with the
baseline it is judged against, measured in the same run.

- UKF predict + update (sum of the medians; 15 error states, MoCap 10 ms late, the default
  fusion horizon) against stock filterpy running the same logic: <= 40 us and >= 20x.
- Tick compute p50 of a lockstep flight through the byte path against the tick's numerics
  alone (UKF predict, a pose every 5th tick, the estimate as the loop reads it, the
  controller; no I/O): <= 1.5x.
- Lockstep flight through the byte path, sim s per wall s (against ``simulate``, truth, of
  the same mission: no bytes, no second process), the median of three flights (one swings by
  +-10 % with the host's load): >= 10x real time. Its floor on this
  machine: a bare pty round trip between two processes plus the numerics, per 2 ms tick
  (nothing else computed, no physics); the row says how far that floor allows.
- The same tick's compute against its numerics timed inside the flight (``LoopTimer``'s
  numerics: the same code as the yardstick, on the flight's CPU and caches): p50 and means,
  informative; the in-flight numerics run 2-3x slower than back to back.
- The numerics once more on one CPU while another spins: in a lockstep flight the emulated
  board computes on the other CPU alongside the tick, and where CPUs slow each other (a
  VM's vCPUs on one physical core: 1.5-1.7x at times on a 2-vCPU VM, none at others, as its
  host placed them) the same code then runs slower (informative row).
- The CPU wake-up latency: a flight holds it at 0 (``drivers.realtime``); the same lockstep
  flight with ``--no-realtime-settings`` (CPUs left to idle), and the numerics run after a
  pty round trip (the wait a lockstep tick follows) with and without the hold, show what a
  CPU that sleeps between ticks costs the same code.
- ``fasthex simulate --estimator ukf``: >= 30x; ``fasthex simulate`` (truth + noise): >= 60x.
- Realtime 1 kHz emulated session against the same at 500 Hz, two flights of each,
  alternated: misses < 0.1 % and compute p99 < 0.5 ms in the worst flight, mean position error
  no worse than at 500 Hz beyond the realtime flights' spread (+10 %: one flight's e_p varies
  by +-0.3 mm with the host's timing, 4.89-5.46 mm seen at either rate; the strict comparison
  is the lockstep one, same seed). The flights are the shipped sessions ``exp1-emulated``
  and ``exp1-emulated-1khz`` (their safety settings) on the clock the row names; the tracking
  at 1 kHz is also compared in lockstep (same seed: deterministic, no host noise).

The per-tick breakdown (medians, us): the simulator's physics step, the truth+noise state
source, the UKF (predict, and the update spread over the ticks), the controller, the record
row; it says where a simulated tick goes.

Run: ``python benchmarks/bench_speed.py [--realtime-s 60] [--skip-realtime]``; the two realtime
pairs fly Exp. 1's first ``--realtime-s`` seconds at 500 Hz and at 1 kHz, alternated.
Machines are noisy (2 shared cores here): compare the ratios, not the absolute figures.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import json
import multiprocessing
import select
import subprocess
import sys
import tempfile
import time
import tty
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Literal, TypeVar

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import bench_ukf  # the UKF flights and their timing

from config import find_config
from controller.missions import Mission
from controller.pipeline import FlightComputer
from controller.reference import VehicleState
from drivers.realtime import hold_cpu_latency, release_cpu_latency
from estimator import EstimatorConfig, Ukf
from groundstation.configs import load_disturbances, load_mission, load_vehicle
from groundstation.metrics import flight_metrics
from groundstation.record import read_record
from groundstation.session import FlightSession, SessionOutcome
from groundstation.session_config import EmulatedBackend, load_session
from sim_backend.closed_loop import TruthPlusNoise, UkfStateSource
from sim_backend.simulator import FastHexSimulator

ROOT = Path(__file__).resolve().parents[1]
T = TypeVar("T")
EXP1 = "exp1-hover-tilt-steps"
LOCKSTEP_FLIGHTS = 3
#: realtime flights per rate (alternated): a realtime flight's tracking varies with the host
REALTIME_PAIRS = 2


def row(figure: str, value: str, baseline: str, ratio: str, target: str, met: bool) -> None:
    print(f"| {figure} | {value} | {baseline} | {ratio} | {target} | "
          f"{'yes' if met else 'NOT met'} |", flush=True)


def ukf_figures(seconds: float) -> tuple[float, float, float]:
    """(fast predict+update, stock predict+update, largest estimate difference)."""
    sc = bench_ukf.scenario(seconds, 0.010, False)
    rows, worst = bench_ukf.compare(sc, seconds, min(seconds, 4.0), "UKF, 10 ms late")
    fast, stock = sum(rows["fast"]), sum(rows["filterpy"])
    return fast, stock, worst


def tick_breakdown(n: int = 4000) -> dict[str, float]:
    """Medians (us) of each part of one in-process simulated tick, on Exp. 1's hover."""
    params = load_vehicle("fasthex")
    mission = Mission(load_mission(EXP1, vehicle=params))
    preset = load_disturbances("paper-calibrated")
    sim = FastHexSimulator(params, preset, seed=1, start_pos_w_m=mission.start_pos_w_m,
                           start_q_wb=mission.start_q_wb)
    truth = TruthPlusNoise(sim.state, preset, np.random.default_rng(1))
    computer = FlightComputer(params, mission)
    ukf = UkfStateSource(params.mass_kg, params.gravity_m_s2)
    parts: dict[str, list[int]] = {k: [] for k in
                                   ("physics", "truth source", "ukf", "controller")}
    clock = time.perf_counter_ns
    dt = 0.002
    for k in range(n):
        t = 5.0 + k * dt                # past the take-off: hovering
        t0 = clock()
        imu = sim.read_imu()
        poses = sim.poll_mocap()
        est = truth.update(t, imu, poses)
        t1 = clock()
        ukf.update(t, imu, poses)      # the estimate is not flown: truth keeps the hover
        t2 = clock()
        tick = computer.step(t, est, sim.tilt_rad())
        sim.command_rotor_speeds_hz(tick.cmd.spin_hz)
        t3 = clock()
        sim.advance(dt)
        t4 = clock()
        parts["truth source"].append(t1 - t0)
        parts["ukf"].append(t2 - t1)
        parts["controller"].append(t3 - t2)
        parts["physics"].append(t4 - t3)
    return {k: float(np.median(v[200:])) / 1e3 for k, v in parts.items()}


def simulate_speed(estimator: str, duration_s: float | None, runs: int = 3) -> float:
    """``fasthex simulate`` as a user runs it: sim s per wall s of the flight (start-up
    excluded, as the command reports it); the median of ``runs`` runs (one run swings by
    +-20 % with the host's other load)."""
    cmd = [sys.executable, "-m", "groundstation", "simulate", EXP1, "--estimator", estimator,
           "--json"]
    if duration_s is not None:
        cmd += ["--duration", str(duration_s)]
    speeds = []
    for _ in range(runs):
        out = subprocess.run(cmd, capture_output=True, text=True, check=True, cwd=ROOT)
        speeds.append(float(json.loads(out.stdout)["sim_s_per_wall_s"]))
    print(f"simulate --estimator {estimator}: {', '.join(f'{x:.1f}' for x in speeds)}x "
          f"real time (median of {runs})", flush=True)
    return float(np.median(speeds))


#: the shipped sessions the flights of this table fly (their clock overridden)
SHIPPED = {500.0: "exp1-emulated", 1000.0: "exp1-emulated-1khz"}


def fly(tmp: Path, clock: Literal["realtime", "lockstep"], rate_hz: float,
        duration_s: float | None, realtime_settings: bool | None = None) -> SessionOutcome:
    """The shipped Exp. 1 session at ``rate_hz`` (its safety settings, e.g. the 0.15 s IMU
    timeout), on ``clock``, no dashboard; ``duration_s``: then an operator landing;
    ``realtime_settings`` as ``fly --[no-]realtime-settings`` (None: the default)."""
    name = f"{clock}-{rate_hz:.0f}-{realtime_settings}"
    cfg = load_session(find_config("sessions", SHIPPED[rate_hz]))
    assert isinstance(cfg.backend, EmulatedBackend)
    cfg = replace(cfg, backend=replace(cfg.backend, clock=clock))
    requests: tuple[tuple[float, str], ...] = ()
    if duration_s is not None:      # the first duration_s of Exp. 1, then a landing
        requests = ((duration_s, "land"),)
    return FlightSession(cfg, load_vehicle("fasthex"), Mission(load_mission(EXP1)),
                         record_path=tmp / f"{name}.fhr", echo_events=False,
                         scripted_requests=requests, dashboard="off",
                         realtime_settings=realtime_settings).run()


def numerics_baseline(n: int = 3000, between: Callable[[], object] | None = None) -> float:
    """Median (us) of a tick's numerics alone: UKF predict (+ a pose every 5th tick, as at
    100 Hz MoCap) and the controller, in-process, no I/O. ``between``: run (untimed) before
    each tick, e.g. the pty round trip a lockstep tick waits on."""
    params = load_vehicle("fasthex")
    computer = FlightComputer(params, Mission(load_mission(EXP1, vehicle=params)))
    ukf = Ukf(replace(EstimatorConfig(), mass_kg=params.mass_kg))
    ukf.initialize(0.0, (0.0, 0.0, 1.0), (1.0, 0.0, 0.0, 0.0))
    out = np.empty(n)
    for k in range(n):
        t = 0.002 * (k + 1)
        if between is not None:
            between()
        t0 = time.perf_counter_ns()
        ukf.predict(t, (0.0, 0.0, 0.0), (0.0, 0.0, 9.81))
        if k % 5 == 0:
            ukf.update_pose(t - 0.004, (0.0, 0.0, 1.0), (1.0, 0.0, 0.0, 0.0))
        # what the loop reads of the estimate each tick (not the full estimate())
        state = VehicleState(*ukf.output_state())
        force = ukf.force_ext_w_n()
        ukf.usable()
        computer.step(5.0 + t, state, 0.0, force_ext_w_n=force)
        out[k] = (time.perf_counter_ns() - t0) / 1e3
    return float(np.median(out[200:]))


def _echo(fd: int) -> None:
    """The far end of :func:`pty_round_trip_us`: send back what arrives, until ``q``."""
    while True:
        select.select([fd], [], [])
        data = os.read(fd, 4096)
        if data.endswith(b"q"):
            return
        os.write(fd, data)


class PtyEcho:
    """A pty whose far end, in another process, sends back what arrives (the board's side of
    a lockstep exchange with nothing computed)."""

    FRAME = b"^w" + bytes(13) + b"$"

    def __init__(self) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        self.proc = multiprocessing.get_context("fork").Process(
            target=_echo, args=(self.master,), daemon=True)
        self.proc.start()

    def round_trip(self) -> None:
        os.write(self.slave, self.FRAME)
        got = 0
        while got < len(self.FRAME):
            select.select([self.slave], [], [])
            got += len(os.read(self.slave, 4096))

    def close(self) -> None:
        os.write(self.slave, b"q")
        self.proc.join(5.0)
        os.close(self.master)
        os.close(self.slave)


def pty_round_trip_us(n: int = 3000) -> float:
    """Median (us) of a bare pty round trip between two processes: 16 bytes out, the same
    back (a ``w`` frame answered by the board), nothing computed on either side. A lockstep
    tick waits for one such round trip at least, plus the board's physics step."""
    echo, out = PtyEcho(), np.empty(n)
    for k in range(n):
        t0 = time.perf_counter_ns()
        echo.round_trip()
        out[k] = (time.perf_counter_ns() - t0) / 1e3
    echo.close()
    return float(np.median(out[200:]))


def numerics_after_wait_us() -> float:
    """The numerics of :func:`numerics_baseline` when each tick follows a pty round trip, as
    a lockstep tick does: the same code, on a CPU that has just waited."""
    echo = PtyEcho()
    try:
        return numerics_baseline(between=echo.round_trip)
    finally:
        echo.close()


def numerics_beside_busy_cpu_us() -> float | None:
    """The numerics of :func:`numerics_baseline` on one CPU while another spins (as in a
    lockstep flight, where the emulated board computes on the other CPU alongside the
    ground station's tick); None on a single CPU. Where CPUs slow each other (a VM's vCPUs
    on one physical core) the yardstick itself is slower in flight."""
    cpus = sorted(os.sched_getaffinity(0))
    if len(cpus) < 2:
        return None
    here, other = cpus[0], cpus[1]
    spin = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        os.sched_setaffinity(spin.pid, {other})
        os.sched_setaffinity(0, {here})
        time.sleep(0.3)  # the spinner running
        return numerics_baseline()
    finally:
        os.sched_setaffinity(0, set(cpus))
        spin.kill()
        spin.wait()


def with_cpu_latency_held(fn: Callable[[], T], held: bool) -> T:
    """``fn()`` with the CPU wake-up latency held at 0 (as a flight holds it) or left alone."""
    if held:
        hold_cpu_latency(0)
    try:
        return fn()
    finally:
        release_cpu_latency()


def pos_err_mm(record_path: Path) -> float:
    """Mean position error (mm) over the flight's measured phases, as ``report`` computes."""
    rows = read_record(record_path).rows
    params = load_vehicle("fasthex")
    m = flight_metrics(rows, min_spin_hz=params.rotors.min_spin_hz,
                       max_spin_hz=params.rotors.max_spin_hz)
    return float(m["all_pos_err_mean_mm"])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ukf-seconds", type=float, default=20.0)
    ap.add_argument("--realtime-s", type=float, default=60.0,
                    help="seconds of Exp. 1 flown in realtime at 500 Hz and at 1 kHz")
    ap.add_argument("--skip-realtime", action="store_true")
    args = ap.parse_args()

    fast, stock, worst = ukf_figures(args.ukf_seconds)
    parts = tick_breakdown()
    base_us = numerics_baseline()
    beside_us = numerics_beside_busy_cpu_us()
    pty_us = {held: with_cpu_latency_held(pty_round_trip_us, held) for held in (True, False)}
    waited_us = {held: with_cpu_latency_held(numerics_after_wait_us, held)
                 for held in (True, False)}
    sim_truth = simulate_speed("truth", None)
    sim_ukf = simulate_speed("ukf", None)
    with tempfile.TemporaryDirectory(prefix="fasthex-speed-") as d:
        tmp = Path(d)
        # the lockstep flight three times: one flight swings by +-10 % with the host's load
        locks = [fly(tmp, "lockstep", 500.0, None) for _ in range(LOCKSTEP_FLIGHTS)]
        speeds = [(o.result.ticks / 500.0) / o.result.loop_wall_s for o in locks]
        lock = locks[int(np.argsort(speeds)[len(speeds) // 2])]    # the median flight
        lock_idle = fly(tmp, "lockstep", 500.0, None, realtime_settings=False)
        lock_1k = fly(tmp, "lockstep", 1000.0, None)   # deterministic: tracking 1 kHz vs 500 Hz
        lock_errs = {500.0: pos_err_mm(lock.record_path), 1000.0: pos_err_mm(lock_1k.record_path)}
        # realtime pairs, alternated: one realtime flight's e_p varies by +-0.3 mm with the
        # host's timing (4.89-5.46 mm seen at either rate), so the rates are compared on means
        rt_runs: dict[float, list[tuple[SessionOutcome, float]]] = {500.0: [], 1000.0: []}
        for _ in range(0 if args.skip_realtime else REALTIME_PAIRS):
            for rate in (500.0, 1000.0):
                out = fly(tmp, "realtime", rate, args.realtime_s)
                rt_runs[rate].append((out, pos_err_mm(out.record_path)))  # before the next
        rt = {rate: runs[-1][0] for rate, runs in rt_runs.items() if runs}
        errs = {rate: float(np.mean([e for _, e in runs])) for rate, runs in rt_runs.items()
                if runs}

    print("\nper simulated tick (medians, us): " + ", ".join(
        f"{k} {v:.1f}" for k, v in parts.items()))
    print(f"UKF estimates, fast vs stock filterpy: largest difference {worst:.2e}")
    print("\n| figure | now | baseline (same run) | ratio | target | met |")
    print("|---|---|---|---|---|---|")
    row("UKF predict + update, medians", f"{fast:.1f} us", f"stock {stock:.1f} us",
        f"{stock / fast:.1f}x", "<= 40 us, >= 20x", fast <= 40.0 and stock / fast >= 20.0)
    t, t_idle = lock.result.timing, lock_idle.result.timing
    held = lock.realtime_settings.get("cpu idle", "not held")
    print(f"lockstep flights: cpu idle {held}; the other with --no-realtime-settings")
    print(f"numerics after a pty round trip (as a lockstep tick runs them): {waited_us[True]:.0f}"
          f" us with the wake-up latency held, {waited_us[False]:.0f} us without; back to "
          f"back {base_us:.0f} us")
    lock_x = (lock.result.ticks / 500.0) / lock.result.loop_wall_s
    print(f"lockstep flights: {', '.join(f'{x:.1f}x' for x in speeds)} (the median's timing "
          "below)")
    idle_x = (lock_idle.result.ticks / 500.0) / lock_idle.result.loop_wall_s
    row("tick compute p50 (lockstep, byte path)", f"{t.compute_p50_ms * 1e3:.0f} us",
        f"numerics {base_us:.0f} us", f"{t.compute_p50_ms * 1e3 / base_us:.2f}x", "<= 1.5x",
        t.compute_p50_ms * 1e3 <= 1.5 * base_us)
    # the same numerics timed inside the flight's ticks: the same code on the CPU the tick
    # runs on, caches as they are then (the rest of the compute is I/O, parsing, the monitor,
    # the state machine and the record)
    row("tick compute against its own numerics (timed in the same flight), p50",
        f"{t.compute_p50_ms * 1e3:.0f} us", f"numerics in flight {t.numerics_p50_ms * 1e3:.0f} us"
        f" (back to back {base_us:.0f} us)", f"{t.compute_p50_ms / t.numerics_p50_ms:.2f}x",
        "(informative)", True)
    row("... and the means", f"{t.compute_mean_ms * 1e3:.0f} us",
        f"numerics in flight {t.numerics_mean_ms * 1e3:.0f} us",
        f"{t.compute_mean_ms / t.numerics_mean_ms:.2f}x", "(informative)", True)
    if beside_us is not None:
        row("tick compute p50 against the numerics beside a busy CPU",
            f"{t.compute_p50_ms * 1e3:.0f} us", f"numerics, the other CPU spinning "
            f"{beside_us:.0f} us ({beside_us / base_us:.2f}x back to back)",
            f"{t.compute_p50_ms * 1e3 / beside_us:.2f}x", "(informative)", True)
    row("tick compute p50, CPUs left to idle", f"{t_idle.compute_p50_ms * 1e3:.0f} us",
        f"numerics after a wait {waited_us[False]:.0f} us",
        f"{t_idle.compute_p50_ms * 1e3 / waited_us[False]:.2f}x", "(the same wait)", True)
    row("tick compute p50 against the numerics after the same wait",
        f"{t.compute_p50_ms * 1e3:.0f} us", f"numerics after a wait {waited_us[True]:.0f} us",
        f"{t.compute_p50_ms * 1e3 / waited_us[True]:.2f}x", "(the same wait)", True)
    row(f"lockstep flight, byte path (median of {LOCKSTEP_FLIGHTS})", f"{lock_x:.1f}x real time",
        f"simulate truth {sim_truth:.1f}x", f"{lock_x / sim_truth:.2f}", ">= 10x",
        lock_x >= 10.0)
    row("lockstep flight, CPUs left to idle (--no-realtime-settings)", f"{idle_x:.1f}x",
        f"held: {lock_x:.1f}x", f"{lock_x / idle_x:.2f}x faster held", "", True)
    floor_us = pty_us[True] + waited_us[True]
    floor_x = 2000.0 / floor_us   # 500 Hz: 2000 us of simulated time per tick
    row("lockstep floor: a bare pty round trip + the numerics after it",
        f"{floor_us:.0f} us/tick", f"pty {pty_us[True]:.0f} us (CPUs idle: {pty_us[False]:.0f})"
        f" + numerics {waited_us[True]:.0f} us", f"at most {floor_x:.1f}x real time",
        ">= 10x possible?", floor_x >= 10.0)
    row("simulate --estimator ukf", f"{sim_ukf:.1f}x real time",
        f"truth {sim_truth:.1f}x", f"{sim_ukf / sim_truth:.2f}", ">= 30x", sim_ukf >= 30.0)
    row("simulate (truth + noise)", f"{sim_truth:.1f}x real time",
        "physics {:.0f} + controller {:.0f} us/tick".format(parts["physics"],
                                                            parts["controller"]),
        "", ">= 60x", sim_truth >= 60.0)
    for name, out in (("lockstep 500 Hz", lock), *((f"realtime {r:.0f} Hz", o)
                                                   for r, o in rt.items())):
        first = out.result.first_ticks_ms
        timing = out.result.timing
        print(f"{name}: first tick after arming {first.get('first_after_arming', 0.0):.3f} ms, "
              f"controller's first step {first.get('first_control', 0.0):.3f} ms, against "
              f"compute p99 {timing.compute_p99_ms:.3f} ms; IMU sample to command (the "
              f"motors' latency) p50 {timing.latency_p50_ms:.3f} ms, p99 "
              f"{timing.latency_p99_ms:.3f} ms")
    row("tracking at 1 kHz (lockstep, same seed: deterministic)",
        f"e_p {lock_errs[1000.0]:.2f} mm", f"500 Hz: e_p {lock_errs[500.0]:.2f} mm",
        f"{lock_errs[1000.0] / lock_errs[500.0]:.2f}x", "<= 500 Hz",
        lock_errs[1000.0] <= lock_errs[500.0])
    if rt:
        for rate, runs in rt_runs.items():
            print(f"realtime {rate:.0f} Hz flights: " + "; ".join(
                f"misses {100 * o.result.timing.miss_fraction:.3f} %, compute p99 "
                f"{o.result.timing.compute_p99_ms:.3f} ms, e_p {e:.2f} mm" for o, e in runs))
        # the worst of the flights for misses and p99, the mean for the tracking
        miss = {r: max(o.result.timing.miss_fraction for o, _ in runs)
                for r, runs in rt_runs.items()}
        p99 = {r: max(o.result.timing.compute_p99_ms for o, _ in runs)
               for r, runs in rt_runs.items()}
        ea, eb = errs[500.0], errs[1000.0]
        row(f"realtime 1 kHz session ({REALTIME_PAIRS} flights each)",
            f"misses {100 * miss[1000.0]:.3f} %, compute p99 {p99[1000.0]:.3f} ms (worst), "
            f"e_p {eb:.2f} mm (mean)",
            f"500 Hz: misses {100 * miss[500.0]:.3f} %, p99 {p99[500.0]:.3f} ms, "
            f"e_p {ea:.2f} mm", f"p99 {p99[1000.0] / p99[500.0]:.2f}x",
            "< 0.1 %, < 0.5 ms, e_p <= 500 Hz + 10 %",
            miss[1000.0] < 0.001 and p99[1000.0] < 0.5 and eb <= ea * 1.1)
    return 0


if __name__ == "__main__":
    sys.exit(main())

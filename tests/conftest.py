"""Shared fixtures (the shipped vehicles, loaded through the same path as the CLI) and the
scheduling of the suite under pytest-xdist.

The README's test command runs the suite on three workers (``pytest -n 3``). Lockstep flights are
repeatable whatever the load (each tick is a round trip through the emulated board's pty), so
two of them may run side by side. Tests that measure wall time, real-time streams or scheduling
(a realtime emulator, MoCap rates and latencies, a pty driven as a terminal, a process killed
in flight) must run alone: they are marked ``exclusive`` (a module in :data:`EXCLUSIVE_MODULES`
or the marker on the test) and hold a run-wide exclusive lock while every other test holds it
shared. The lock is two ``flock`` files in a directory the controller makes for the run: a
turnstile that a waiting exclusive test holds, so that shared holders cannot starve it. Without
xdist nothing is locked.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import shutil
import signal
import tempfile
import threading
import warnings
from collections.abc import Iterator
from pathlib import Path

import pytest

from controller.model import VehicleModel
from controller.params import VehicleParams
from groundstation.configs import load_vehicle

#: test modules (paths below tests/) whose every test runs alone: they assert on real time
#: (rates, latencies, clock estimates, the 100 ms a kill may lose, IMU gaps on the host clock,
#: servo reply timeouts); everything else shares the machine. The stop-signal tests
#: (test_fly_signals) share it: their lockstep flights wait for the record to show the
#: vehicle airborne before each signal, so a loaded machine only slows them, as a
#: user's busy laptop would. Single tests of shared modules that fly or run against a realtime
#: device carry the ``exclusive`` marker themselves (test_bench_leave_devices' bench tests, the
#: realtime flights of test_fly_signals and test_fly_emulated: two realtime flights side by
#: side on two cores were seen to lose the IMU stream for 101 ms and cut)
EXCLUSIVE_MODULES = frozenset({
    "hil/test_hil_flight_ctrl.py",
    "hil/test_hil_mocap.py",
    "hil/test_hil_servo.py",
    "integration/test_clock_sync.py",
    "integration/test_flightctrl_emulator.py",
    "integration/test_flightctrl_link.py",
    "integration/test_fly_kill.py",
    "integration/test_mocap_cli.py",
    "integration/test_mocap_natnet.py",
    "integration/test_mocap_natnet_peer.py",
    "integration/test_mocap_vrpn.py",
    "integration/test_tilt_servo_faults.py",
    "unit/test_telemetry_ring.py",
})

_TESTS = Path(__file__).resolve().parent
_LOCK_DIR_KEY = pytest.StashKey[str]()


#: the longest shared modules (lockstep flights), started first so that no worker is left
#: with one of them at the end of the run; in this order
LONG_SHARED_MODULES = (
    "integration/test_fly_paper_exp1.py",
    "integration/test_fly_paper_exp2a.py",
    "integration/test_fly_paper_exp2b.py",
    "integration/test_fly_emulated.py",
    "integration/test_failsafes.py",
    "integration/test_ukf_simulated.py",
    "integration/test_simulate_paper.py",
    "integration/test_fly_mavlink.py",
    "integration/test_dashboard.py",
    "integration/test_takeoff_on_estimate.py",
    "integration/test_fly_1khz.py",
    "integration/test_scenario_fly_vs_simulate.py",
    "integration/test_fly_console.py",
    "integration/test_fly_signals.py",
    "integration/test_bench_leave_devices.py",
    "integration/test_mocap_qtm.py",
    "integration/test_simulate_mission_kinds.py",
)


def _module(item: pytest.Item) -> str:
    try:
        return Path(str(item.path)).resolve().relative_to(_TESTS).as_posix()
    except ValueError:
        return str(item.path)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    # Every xdist worker collects, and orders, the same way: the exclusive modules first (the run
    # is serial while they last), then the long shared flights, then the rest, the unit tests
    # last (short ones fill the end of the run evenly). A module's tests stay together, in
    # their order.
    order = {m: i for i, m in enumerate(LONG_SHARED_MODULES)}

    def rank(pair: tuple[int, pytest.Item]) -> tuple[int, int, int]:
        index, item = pair
        mod = _module(item)
        if mod in EXCLUSIVE_MODULES:
            return (0, 0, index)
        if mod in order:
            return (1, order[mod], index)
        return (2 if mod.startswith("integration/") else 3, 0, index)

    for item in items:
        if _module(item) in EXCLUSIVE_MODULES:
            item.add_marker(pytest.mark.exclusive)
    if hasattr(config, "workerinput"):  # one process: the order given (e.g. pytest -x A B)
        items[:] = [item for _, item in sorted(enumerate(items), key=rank)]


_LOCK_DIR_ENV = "FASTHEX_TEST_LOCK_DIR"


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line("markers", "exclusive: runs alone under pytest-xdist (timing, real "
                            "time, signals); see tests/conftest.py")
    if not hasattr(config, "workerinput") and getattr(config.option, "numprocesses", None):
        # the controller: a fresh lock directory for this run, inherited by its workers (a
        # pytest started by a test is a controller of its own: it never waits on ours)
        lock_dir = tempfile.mkdtemp(prefix="pytest-run-lock-")
        os.environ[_LOCK_DIR_ENV] = lock_dir
        config.stash[_LOCK_DIR_KEY] = lock_dir
        _compile_kernels()


def _compile_kernels() -> None:
    """Fill numba's on-disk cache once, in the controller, before the workers start: else each
    worker (and the CLI processes of the first tests) compiles the physics, the control law
    and the UKF itself, ~25 s each on a fresh install. Two processes, one per core: a 0.1 s
    flight on the true state (physics, control law, wrench map) and the UKF's kernels."""
    import subprocess
    import sys

    flight = ("from controller.missions import Mission;"
              "from groundstation.configs import load_disturbances, load_mission, load_vehicle;"
              "from sim_backend.closed_loop import fly_mission;"
              "fly_mission(load_vehicle('fasthex'), Mission(load_mission('exp1-hover-tilt-steps'"
              ")), load_disturbances('ideal'), duration_s=0.1)")
    ukf = "from estimator.ukf import Ukf; Ukf()"
    procs = [subprocess.Popen([sys.executable, "-c", code]) for code in (flight, ukf)]
    for proc in procs:
        proc.wait()


def pytest_unconfigure(config: pytest.Config) -> None:
    lock_dir = config.stash.get(_LOCK_DIR_KEY, None)
    if lock_dir is not None:
        shutil.rmtree(lock_dir, ignore_errors=True)


@contextlib.contextmanager
def _run_lock(config: pytest.Config, exclusive: bool) -> Iterator[None]:
    lock_dir = os.environ.get(_LOCK_DIR_ENV)
    if not hasattr(config, "workerinput") or not lock_dir:  # not an xdist worker
        yield
        return
    base = Path(lock_dir)
    with open(base / "turnstile", "a+b") as turnstile, open(base / "lock", "a+b") as lock:
        fcntl.flock(turnstile, fcntl.LOCK_EX)
        try:
            fcntl.flock(lock, fcntl.LOCK_EX if exclusive else fcntl.LOCK_SH)
        finally:
            fcntl.flock(turnstile, fcntl.LOCK_UN)
        try:
            yield
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item: pytest.Item, nextitem: pytest.Item | None) -> Iterator[None]:
    # setup, call and teardown of the test, its function and module fixtures included
    with _run_lock(item.config, item.get_closest_marker("exclusive") is not None):
        yield


_STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


def _stop_signal_state() -> tuple[frozenset[int], tuple[object, ...]]:
    blocked = frozenset(int(s) for s in signal.pthread_sigmask(signal.SIG_BLOCK, []))
    return blocked & {int(s) for s in _STOP_SIGNALS}, tuple(
        signal.getsignal(s) for s in _STOP_SIGNALS)


@pytest.fixture(autouse=True)
def _stop_signals_left_as_found(request: pytest.FixtureRequest) -> Iterator[None]:
    """A test that leaves the stop signals blocked or ignored in this process would pass that
    on to every program a later test starts (a mask and SIG_IGN survive exec): their Ctrl-C
    would do nothing. Put back as found, with a warning naming the test."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    before = _stop_signal_state()
    yield
    after = _stop_signal_state()
    if after != before:
        signal.pthread_sigmask(signal.SIG_SETMASK, sorted(
            (set(signal.pthread_sigmask(signal.SIG_BLOCK, [])) - set(_STOP_SIGNALS))
            | {signal.Signals(s) for s in before[0]}))
        for sig, handler in zip(_STOP_SIGNALS, before[1], strict=True):
            if handler is not None:
                signal.signal(sig, handler)  # type: ignore[arg-type]
        warnings.warn(f"{request.node.nodeid} left the stop signals changed (blocked "
                      f"{sorted(after[0])}, handlers {after[1]}); put back", stacklevel=1)


@pytest.fixture(scope="session")
def fasthex_params() -> VehicleParams:
    return load_vehicle("fasthex")


@pytest.fixture(scope="session")
def fasthex_model(fasthex_params: VehicleParams) -> VehicleModel:
    return VehicleModel(fasthex_params)

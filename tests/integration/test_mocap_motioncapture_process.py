"""The libmotioncapture adapter's child process: a silent or wrong host costs
``connect_timeout_s`` and a typed error while this process keeps running, and the child never
outlives ``close()`` or the ground station (also when killed with SIGKILL).

Hosts that never answer, on loopback: ``qualisys`` against a listening TCP port that never
speaks (the library waits 5 s for QTM's welcome, holding its process's GIL), ``vicon`` against
a refused port (the DataStream SDK retries for ever) and ``vrpn`` against a bound UDP port
(the library connects, then returns empty frames)."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

from drivers.mocap.motioncapture_child import STAGE_CONNECT, ChildError, Frame, read_message
from drivers.mocap.motioncapture_client import MotionCaptureClient, MotionCaptureConfig
from drivers.mocap.pose import MocapConnectError
from drivers.mocap.uri import open_pose_source, parse_uri
from sim_backend.emulators.vrpn import VrpnEmulatorConfig, VrpnServer
from sim_backend.vehicle import BenchVehicle

WAIT_S = 10.0
ROOT = Path(__file__).resolve().parents[2]
ENV = {**os.environ, "PYTHONPATH": os.pathsep.join(
    [str(ROOT), *filter(None, [os.environ.get("PYTHONPATH")])])}


def _exists(pid: int) -> bool:
    """The process exists, a zombie included (so False means ended and reaped)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


def _running(pid: int) -> bool:
    """The process exists and is not a zombie (an orphan's zombie waits for init to reap)."""
    try:
        import psutil
    except ImportError:
        try:
            with open(f"/proc/{pid}/stat") as f:
                return f.read().rpartition(")")[2].split()[0] != "Z"
        except FileNotFoundError:
            return False
    try:
        return bool(psutil.Process(pid).status() != psutil.STATUS_ZOMBIE)
    except psutil.NoSuchProcess:
        return False


def _wait_ended(pid: int, timeout_s: float = WAIT_S) -> bool:
    deadline = time.monotonic() + timeout_s
    while _running(pid):
        if time.monotonic() > deadline:
            return False
        time.sleep(0.02)
    return True


@contextmanager
def _silent_host(system: str) -> Iterator[str]:
    """``HOST:PORT`` of a loopback port that never answers ``system``'s library."""
    if system == "vrpn":
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.bind(("127.0.0.1", 0))
    else:
        sock = socket.socket()
        sock.bind(("127.0.0.1", 0))
        if system == "qualisys":
            sock.listen(8)  # the kernel accepts the connection; nobody says a word
        # vicon: bound, not listening: refused, and nobody else gets the port meanwhile
    with sock:
        yield f"127.0.0.1:{sock.getsockname()[1]}"


class Ticker:
    """A Python thread counting 5 ms sleeps, and noting the adapter's child process."""

    def __init__(self, dev: MotionCaptureClient) -> None:
        self.dev = dev
        self.ticks = 0
        self.child_pids: set[int] = set()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def __enter__(self) -> Ticker:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()

    def _run(self) -> None:
        while not self._stop.wait(0.005):
            self.ticks += 1
            pid = self.dev.child_pid
            if pid is not None:
                self.child_pids.add(pid)


@pytest.mark.parametrize("system,fragment", [
    ("qualisys", "libmotioncapture's qualisys connect to 127.0.0.1:{port} did not answer "
                 "within 1.5 s"),
    ("vicon", "libmotioncapture's vicon connect to 127.0.0.1:{port} did not answer within "
              "1.5 s"),
    ("vrpn", "no rigid body within 1.5 s")])
def test_that_a_silent_host_is_a_connect_error_within_the_timeout_while_threads_run(
        system: str, fragment: str) -> None:
    with _silent_host(system) as host:
        dev = open_pose_source(f"motioncapture://{system}?host={host}&body=hex",
                               connect_timeout_s=1.5)
        assert isinstance(dev, MotionCaptureClient)
        # Test
        t0 = time.monotonic()
        with Ticker(dev) as ticker, pytest.raises(MocapConnectError) as err:
            dev.start()
        elapsed_s = time.monotonic() - t0
    # Assert: the error names the device, the thread ran (the GIL was free), the child is gone
    port = host.rpartition(":")[2]
    assert str(err.value).startswith(f"motioncapture://{system}?host={host}&body=hex: ")
    assert fragment.format(port=port) in str(err.value)
    assert elapsed_s < 1.5 + 3.0
    assert ticker.ticks >= 50  # ~300 at 5 ms; a held GIL would allow one or two
    assert len(ticker.child_pids) == 1 and dev.child_pid is None
    assert not _exists(ticker.child_pids.pop())  # ended and reaped


def test_that_close_during_a_blocked_connect_ends_the_child() -> None:
    with _silent_host("vicon") as host:
        dev = open_pose_source(f"motioncapture://vicon?host={host}&body=hex",
                               connect_timeout_s=60.0)
        assert isinstance(dev, MotionCaptureClient)
        errors: list[BaseException] = []

        def start() -> None:
            try:
                dev.start()
            except BaseException as exc:
                errors.append(exc)

        starter = threading.Thread(target=start)
        starter.start()
        deadline = time.monotonic() + WAIT_S
        while (pid := dev.child_pid) is None and time.monotonic() < deadline:
            time.sleep(0.01)
        assert pid is not None
        time.sleep(1.0)  # the child is in the library's connect by now
        # Test
        dev.close()
        starter.join(WAIT_S)
    # Assert
    assert not starter.is_alive()
    assert len(errors) == 1 and isinstance(errors[0], MocapConnectError)
    assert "closed while connecting" in str(errors[0])
    assert dev.child_pid is None and not _exists(pid)


def test_that_close_after_streaming_ends_the_child_and_sigint_does_not() -> None:
    cfg = VrpnEmulatorConfig(port=0, rate_hz=200.0, tracker_name="fasthex")
    with VrpnServer(BenchVehicle(pos_w_m=(0.25, 0.5, 1.0)), cfg) as server:
        dev = open_pose_source(f"motioncapture://vrpn?host=127.0.0.1:{server.port}"
                               f"&body=fasthex")
        assert isinstance(dev, MotionCaptureClient)
        dev.start()
        try:
            pid = dev.child_pid
            assert pid is not None
            # Test: Ctrl-C is the parent's; the child ignores it and streams on
            os.kill(pid, signal.SIGINT)
            assert dev.wait_frames(20, WAIT_S)
            assert dev.child_pid == pid and _running(pid)
            s = dev.latest()
        finally:
            dev.close()
    # Assert
    assert dev.child_pid is None and not _exists(pid)
    assert s is not None and s.pos_w_m == pytest.approx((0.25, 0.5, 1.0), abs=1e-6)


def _signal_set(pid: int, field: str) -> set[int]:
    with open(f"/proc/{pid}/status") as f:
        mask = int(next(line for line in f if line.startswith(field + ":")).split()[1], 16)
    return {n for n in range(1, 65) if mask >> (n - 1) & 1}


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_that_a_child_started_with_stop_signals_blocked_takes_sigterm_and_ignores_ctrl_c(
        ) -> None:
    # Fixture: a session starts devices with its stop signals deferred; threads and processes
    # started meanwhile inherit the mask
    stop_signals = {signal.SIGINT, signal.SIGTERM, signal.SIGHUP}
    cfg = VrpnEmulatorConfig(port=0, rate_hz=200.0, tracker_name="fasthex")
    with VrpnServer(BenchVehicle(), cfg) as server:
        dev = open_pose_source(f"motioncapture://vrpn?host=127.0.0.1:{server.port}"
                               f"&body=fasthex")
        assert isinstance(dev, MotionCaptureClient)
        signal.pthread_sigmask(signal.SIG_BLOCK, stop_signals)
        try:
            dev.start()
        finally:
            signal.pthread_sigmask(signal.SIG_UNBLOCK, stop_signals)
        try:
            pid = dev.child_pid
            assert pid is not None
            blocked, ignored = _signal_set(pid, "SigBlk"), _signal_set(pid, "SigIgn")
        finally:
            dev.close()
    # Assert
    assert not blocked & stop_signals
    assert {signal.SIGINT, signal.SIGHUP} <= ignored and signal.SIGTERM not in ignored


def test_that_starting_again_replaces_the_child() -> None:
    cfg = VrpnEmulatorConfig(port=0, rate_hz=200.0, tracker_name="fasthex")
    with VrpnServer(BenchVehicle(), cfg) as server:
        dev = open_pose_source(f"motioncapture://vrpn?host=127.0.0.1:{server.port}"
                               f"&body=fasthex")
        assert isinstance(dev, MotionCaptureClient)
        dev.start()
        first = dev.child_pid
        with dev:  # starts again
            second = dev.child_pid
            assert dev.wait_frames(5, WAIT_S)
    assert first is not None and second is not None and first != second
    assert not _exists(first) and not _exists(second)


PARENT = """
import sys, threading, time
from drivers.mocap.uri import open_pose_source
dev = open_pose_source(sys.argv[1], connect_timeout_s=60.0)
threading.Thread(target=dev.start, daemon=True).start()
while dev.child_pid is None:
    time.sleep(0.01)
print(dev.child_pid, flush=True)
if sys.argv[2] == "streaming":
    assert dev.wait_for_total(10, 10.0)
else:
    time.sleep(1.0)  # the child is in the library's connect by now
print("ready", flush=True)
time.sleep(600)
"""


@pytest.mark.parametrize("stage", ["connecting", "streaming"])
def test_that_the_child_ends_when_the_ground_station_is_killed(stage: str) -> None:
    # Fixture: a ground station in its own process, its child blocked in connect (vicon
    # against a refused port) or streaming from the emulated VRPN server in this process
    cfg = VrpnEmulatorConfig(port=0, rate_hz=200.0, tracker_name="fasthex")
    with VrpnServer(BenchVehicle(), cfg) as server, _silent_host("vicon") as silent:
        uri = (f"motioncapture://vrpn?host=127.0.0.1:{server.port}&body=fasthex"
               if stage == "streaming" else f"motioncapture://vicon?host={silent}&body=hex")
        with subprocess.Popen([sys.executable, "-c", PARENT, uri, stage], env=ENV, text=True,
                              stdout=subprocess.PIPE) as parent:
            try:
                assert parent.stdout is not None
                child = int(parent.stdout.readline())
                assert parent.stdout.readline().strip() == "ready"
                assert _running(child)
                # Test
                parent.send_signal(signal.SIGKILL)
                parent.wait(WAIT_S)
                ended = _wait_ended(child)
            finally:
                parent.kill()
    # Assert
    assert parent.returncode == -signal.SIGKILL
    assert ended


def test_that_an_unknown_system_in_the_child_is_a_typed_error_with_the_library_message(
        ) -> None:
    # Fixture: a config that skipped validation (none built from a URI or YAML can)
    cfg = parse_uri("motioncapture://vicon?host=127.0.0.1&body=hex&stale_ms=50")
    assert isinstance(cfg, MotionCaptureConfig)
    object.__setattr__(cfg, "system", "kinect")
    dev = MotionCaptureClient(cfg)
    # Test
    t0 = time.monotonic()
    with pytest.raises(MocapConnectError) as err:
        dev.start()
    # Assert: the library's own words, at once rather than at the timeout
    assert "libmotioncapture: Unknown motion capture type!" in str(err.value)
    assert time.monotonic() - t0 < cfg.connect_timeout_s
    assert dev.child_pid is None


def test_that_a_refused_qualisys_connection_is_the_library_error_in_the_parent() -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    dev = open_pose_source(f"motioncapture://qualisys?host=127.0.0.1:{port}&body=hex",
                           connect_timeout_s=WAIT_S)
    # the library names the base port it was given, one below QTM's RT port
    with pytest.raises(MocapConnectError,
                       match=f"libmotioncapture: Error connecting QTM on address: "
                             f"127.0.0.1:{port - 1}$"):
        dev.start()


def _child(system: str, options: dict[str, str]) -> subprocess.Popen[bytes]:
    return subprocess.Popen([sys.executable, "-P", "-m", "drivers.mocap.motioncapture_child",
                             system, json.dumps(options), str(os.getpid())], env=ENV,
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE)


def test_that_the_child_reports_frames_and_exits_when_its_stdin_ends() -> None:
    cfg = VrpnEmulatorConfig(port=0, rate_hz=200.0, tracker_name="fasthex")
    with VrpnServer(BenchVehicle(pos_w_m=(0.25, 0.5, 1.0)), cfg) as server, \
            _child("vrpn", {"hostname": f"127.0.0.1:{server.port}"}) as child:
        assert child.stdout is not None and child.stdin is not None
        messages = [read_message(child.stdout) for _ in range(30)]
        # Test: the parent's end of the stdin pipe closes, as when it dies
        child.stdin.close()
        code = child.wait(WAIT_S)
    # Assert
    assert messages[0] == b"C"
    frames = [m for m in messages[1:] if isinstance(m, Frame) and m.bodies]
    assert frames and all(isinstance(m, Frame) for m in messages[1:])
    body = frames[-1].bodies[0]
    assert body.name == "fasthex" and body.ok
    # the emulator's Z-up world is VRPN's frame: the true pose as it is
    assert body.position_m == pytest.approx((0.25, 0.5, 1.0), abs=1e-6)
    assert body.q_wxyz == pytest.approx((1.0, 0.0, 0.0, 0.0), abs=1e-6)
    assert frames[-1].rx_monotonic_ns <= time.monotonic_ns()
    assert code == 0


def test_that_the_child_reports_the_library_error_and_exits() -> None:
    with _child("kinect", {"hostname": "127.0.0.1"}) as child:
        assert child.stdout is not None
        message = read_message(child.stdout)
        end = read_message(child.stdout)
        code = child.wait(WAIT_S)
    assert message == ChildError(STAGE_CONNECT, "Unknown motion capture type!")
    assert end is None and code == 1

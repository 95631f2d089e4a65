"""Helpers for the MAVLink tests: a headless MAVProxy driven on stdin, free UDP ports, and
emulated-session files with a MAVLink telemetry block.

MAVProxy (GPLv3) runs as a separate process, fed commands on stdin as an operator would type
them; every wait is on a line it prints, with a generous deadline. It is taken from the running
interpreter's environment (``mavproxy.py`` next to ``sys.executable``, installed by the test
extra); a missing one fails the test instead of skipping it.
"""

from __future__ import annotations

import os
import queue
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

MAVPROXY = Path(sys.executable).parent / "mavproxy.py"
TIMEOUT_S = 90.0


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class MavProxy:
    """A MAVProxy process listening on ``port``; its output lines are collected by a thread."""

    def __init__(self, port: int, state_dir: Path, *extra: str) -> None:
        # a missing MAVProxy fails the test: the test extra installs it
        assert MAVPROXY.exists(), (
            f"MAVProxy is not installed next to {sys.executable} (pip install -e '.[test]')")
        env = {**os.environ, "HOME": str(state_dir)}
        env.pop("MAVLINK20", None)
        self.proc = subprocess.Popen(
            [sys.executable, str(MAVPROXY), f"--master=udpin:127.0.0.1:{port}",
             f"--state-basedir={state_dir}", "--cmd=set flushlogs True", *extra],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
            bufsize=1, env=env, cwd=state_dir)
        self.lines: list[str] = []
        self._q: queue.Queue[str] = queue.Queue()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self._q.put(line.rstrip("\n"))

    def type(self, command: str) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.write(command + "\n")
        self.proc.stdin.flush()

    def expect(self, pattern: str) -> re.Match[str]:
        """The first new output line matching ``pattern`` (a regex)."""
        rx = re.compile(pattern)
        deadline = time.monotonic() + TIMEOUT_S
        while time.monotonic() < deadline:
            try:
                line = self._q.get(timeout=0.5)
            except queue.Empty:
                if self.proc.poll() is not None:
                    break
                continue
            self.lines.append(line)
            m = rx.search(line)
            if m is not None:
                return m
        tail = "\n".join(self.lines[-40:])
        raise AssertionError(f"MAVProxy never printed /{pattern}/; last lines:\n{tail}")

    def close(self) -> None:
        if self.proc.poll() is None:
            try:
                # MAVProxy only honours "exit" with requireexit set; stopping cleanly
                # flushes its telemetry log
                self.type("set requireexit True")
                self.type("exit")
                assert self.proc.stdin is not None
                self.proc.stdin.close()  # its input loop checks for the stop only between lines
                self.proc.wait(timeout=30)
            except (OSError, subprocess.TimeoutExpired):
                self.proc.send_signal(signal.SIGINT)
                self.proc.terminate()
                try:
                    self.proc.wait(timeout=10)
                except subprocess.TimeoutExpired:
                    self.proc.kill()
                    self.proc.wait(timeout=10)
        for stream in (self.proc.stdin, self.proc.stdout):
            if stream is not None and not stream.closed:
                stream.close()


def write_session(tmp_path: Path, *, hover_s: float, key_file: str | None = None,
                  allow_unsigned: bool = False, name: str = "gcs-flight") -> Path:
    """An emulated lockstep session (the shared short mission, its hover ``hover_s`` long)
    whose telemetry block names a MAVLink key file and/or allows unsigned commands."""
    from flight_support import SESSION, SHORT_MISSION

    (tmp_path / "short-hover.yaml").write_text(
        SHORT_MISSION.replace("duration_s: 4.0", f"duration_s: {hover_s}"))
    text = SESSION.format(seed=3, faults="", corrupt=0.0, zmax=2.5, servo_action="hold")
    if key_file is not None:
        text += f"  mavlink_key_file: {key_file}\n"
    if allow_unsigned:
        text += "  mavlink_allow_unsigned: true\n"
    path = tmp_path / f"{name}.yaml"
    path.write_text(text)
    return path


def start_fly(session: Path, record: Path, port: int, *extra: str,
              env: dict[str, str] | None = None) -> subprocess.Popen[str]:
    """``fasthex fly SESSION --json`` sending its MAVLink telemetry to 127.0.0.1:``port``."""
    environ = dict(os.environ if env is None else env)
    return subprocess.Popen(
        [sys.executable, "-m", "groundstation", "fly", str(session), "--json", "--rerun", "off",
         "--record", str(record), "--mavlink", f"udpout:127.0.0.1:{port}", *extra],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=environ,
        cwd=session.parent)

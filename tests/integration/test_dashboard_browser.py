"""The web dashboard renders in a real browser: ``fasthex replay --rerun serve`` serves a
recorded flight, headless Chromium loads the printed URL (driven over the DevTools protocol on
a pipe), and the screenshot must show the dashboard's plots, not a blank or loading page.

The rerun web viewer is a wasm app drawing into a canvas through WebGL (SwiftShader here), so
the check is on pixels: the dashboard draws the tilt, lateral-force, actuation and trail series
in :data:`groundstation.dashboard.MARKER_RGB`, a colour neither the viewer's chrome nor its
loading screen uses. Skipped only when no Chromium is installed (CI installs the Debian
package ``chromium``).
"""

from __future__ import annotations

import base64
import contextlib
import json
import os
import selectors
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from groundstation.dashboard import MARKER_RGB

CHROMIUM_NAMES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")
DEADLINE_S = 150.0  # wasm start-up in a software renderer on a loaded 2-core machine
MIN_MARKER_PIXELS = 150


def _chromium() -> str | None:
    return next((p for p in map(shutil.which, CHROMIUM_NAMES) if p), None)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class DevToolsPipe:
    """Headless Chromium driven over ``--remote-debugging-pipe``: NUL-terminated JSON messages,
    commands on the child's fd 3, replies and events on its fd 4."""

    def __init__(self, exe: str, width: int = 1280, height: int = 800) -> None:
        to_child_r, self._to_child = os.pipe()
        self._from_child, from_child_w = os.pipe()

        def fds() -> None:  # in the child, before exec: the two pipe ends onto fds 3 and 4
            a, b = os.dup(to_child_r), os.dup(from_child_w)
            os.dup2(a, 3)
            os.dup2(b, 4)

        self.profile = tempfile.TemporaryDirectory(prefix="fasthex-chromium-")
        self.proc = subprocess.Popen(
            [exe, "--headless", "--no-sandbox", "--disable-gpu", "--enable-unsafe-swiftshader",
             "--disable-quic", "--no-first-run", "--disable-background-networking",
             "--disable-component-update", "--disable-sync", f"--window-size={width},{height}",
             f"--user-data-dir={self.profile.name}", "--remote-debugging-pipe", "about:blank"],
            pass_fds=(3, 4), preexec_fn=fds, stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
        os.close(to_child_r)
        os.close(from_child_w)
        self._buf = b""
        self._id = 0

    def call(self, method: str, session: str | None = None, timeout_s: float = 60.0,
             **params: Any) -> dict[str, Any]:
        self._id += 1
        msg: dict[str, Any] = {"id": self._id, "method": method, "params": params}
        if session:
            msg["sessionId"] = session
        os.write(self._to_child, json.dumps(msg).encode() + b"\0")
        deadline = time.monotonic() + timeout_s
        with selectors.DefaultSelector() as sel:
            sel.register(self._from_child, selectors.EVENT_READ)
            while True:
                while b"\0" in self._buf:
                    raw, self._buf = self._buf.split(b"\0", 1)
                    reply = json.loads(raw)
                    if reply.get("id") == self._id:
                        if "error" in reply:
                            raise RuntimeError(f"{method}: {reply['error']}")
                        return dict(reply.get("result", {}))
                left = deadline - time.monotonic()
                if left <= 0 or not sel.select(left):
                    raise TimeoutError(f"chromium did not answer {method} in {timeout_s} s")
                chunk = os.read(self._from_child, 1 << 20)
                if not chunk:
                    raise RuntimeError("chromium closed its DevTools pipe")
                self._buf += chunk

    def close(self) -> None:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(self.proc.pid, signal.SIGTERM)
        try:
            self.proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait(timeout=20)
        os.close(self._to_child)
        os.close(self._from_child)
        self.profile.cleanup()


def _read_until(proc: subprocess.Popen[str], prefix: str, deadline: float) -> str:
    assert proc.stdout is not None
    with selectors.DefaultSelector() as sel:
        sel.register(proc.stdout, selectors.EVENT_READ)
        while time.monotonic() < deadline:
            if sel.select(max(0.0, deadline - time.monotonic())):
                line = proc.stdout.readline()
                if not line:
                    break
                if line.startswith(prefix):
                    return line.strip()
    raise AssertionError(f"replay never printed {prefix!r} (exit {proc.poll()})")


def _marker_pixels(png: bytes) -> tuple[int, int]:
    """Pixels within 40 of MARKER_RGB, and the number of distinct colours."""
    import io

    import matplotlib.image as mpimg

    img = (mpimg.imread(io.BytesIO(png), format="png")[..., :3] * 255).astype(int)
    near = np.abs(img - np.array(MARKER_RGB)).max(axis=2) < 40
    return int(near.sum()), len(np.unique(img.reshape(-1, 3), axis=0))


@pytest.mark.slow
def test_that_the_web_dashboard_renders_a_recorded_flight_in_headless_chromium(
        tmp_path: Path) -> None:
    exe = _chromium()
    # a peer this machine can have (.ci/run installs it): missing is a failure, not a skip
    assert exe is not None, "no Chromium installed (Debian: apt-get install -y chromium)"
    record = tmp_path / "flight.fhr"
    # 25 s of Exp. 1: the takeoff and the step to 30 deg, so every panel moves
    sim = subprocess.run([sys.executable, "-m", "groundstation", "simulate",
                          "exp1-hover-tilt-steps", "--duration", "25", "--log", str(record)],
                         capture_output=True, text=True, timeout=300, check=False)
    assert sim.returncode == 0, sim.stderr
    deadline = time.monotonic() + DEADLINE_S
    replay = subprocess.Popen(
        [sys.executable, "-m", "groundstation", "replay", str(record), "--speed", "max",
         "--rerun", "serve", "--grpc-port", str(_free_port()), "--web-port", str(_free_port())],
        stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, start_new_session=True)
    browser: DevToolsPipe | None = None
    try:
        url = _read_until(replay, "web viewer: ", deadline).split(": ", 1)[1]
        assert url.startswith("http://127.0.0.1:")
        _read_until(replay, "replayed ", deadline)  # every row is on the server
        browser = DevToolsPipe(exe)
        # a new tab opened on the URL: no cross-site navigation that would detach a session
        target = browser.call("Target.createTarget", url=url)["targetId"]
        session = browser.call("Target.attachToTarget", targetId=target,
                               flatten=True)["sessionId"]
        shot = b""
        markers = colours = 0
        while time.monotonic() < deadline:
            try:
                shot = base64.b64decode(browser.call("Page.captureScreenshot", session,
                                                     format="png")["data"])
            except RuntimeError as exc:  # the page is still being created
                if "Not attached" not in str(exc):
                    raise
                session = browser.call("Target.attachToTarget", targetId=target,
                                       flatten=True)["sessionId"]
                continue
            markers, colours = _marker_pixels(shot)
            if markers >= MIN_MARKER_PIXELS:
                break
            time.sleep(1.0)  # the next frame, not a wait for the result: the loop is bounded
        (tmp_path / "dashboard.png").write_bytes(shot)
        canvases = browser.call("Runtime.evaluate", session,
                                expression="document.querySelectorAll('canvas').length",
                                returnByValue=True)["result"]["value"]
        assert canvases >= 1
        assert markers >= MIN_MARKER_PIXELS, (
            f"dashboard series not on screen after {DEADLINE_S} s: {markers} marker pixels, "
            f"{colours} colours; screenshot {tmp_path / 'dashboard.png'}")
        assert colours > 500  # a rendered dashboard, not a flat page
    finally:
        if browser is not None:
            browser.close()
        with contextlib.suppress(ProcessLookupError):
            os.killpg(replay.pid, signal.SIGTERM)
        replay.wait(timeout=30)
        if replay.stdout:
            replay.stdout.close()

"""The operator's live console of ``fasthex fly``: events scroll, one status line stays below.

One thread owns the terminal. The flight loop and the session only hand text over
(:meth:`Console.event` appends to a deque: atomic, no lock, no I/O in the 500 Hz tick); the
console thread prints every event as it comes, each on its own line, and redraws the status line
below them five times a second. On a terminal the status line is rewritten in place (carriage
return + ANSI "erase line"), so an event never lands on the same line as a status. When the
stream is not a terminal (a pipe, a log file) events are plain lines and there is no status.

``stop()`` prints what is left and erases the status line: the summary that follows starts on a
clean line and no stale status is printed after the flight.
"""

from __future__ import annotations

import collections
import contextlib
import math
import os
import threading
from collections.abc import Callable
from typing import TextIO

#: ANSI: carriage return, then erase the whole line
CLEAR_LINE = "\r\x1b[2K"
PLACEHOLDER = "--"


def number(value: float | None, fmt: str, unit: str = "") -> str:
    """``value`` formatted, or ``--`` when it is not known yet (None, NaN, +-inf)."""
    if value is None or not math.isfinite(value):
        return PLACEHOLDER + (f" {unit}" if unit else "")
    return f"{value:{fmt}}" + (f" {unit}" if unit else "")


class Console:
    """Events above, a live status line below (see the module doc)."""

    def __init__(self, stream: TextIO, *, live: bool | None = None,
                 status: Callable[[], str] | None = None, refresh_s: float = 0.2) -> None:
        self.stream = stream
        #: rewrite a status line in place (a terminal) or print plain event lines only
        self.live = _isatty(stream) if live is None else live
        self._status = status
        self._refresh_s = refresh_s
        self._events: collections.deque[str] = collections.deque()
        self._wake = threading.Event()
        self._stopping = False
        self._thread: threading.Thread | None = None
        self._shown = ""  # the status line on screen now ("" when none)
        self.broken = False  # the terminal went away (SIGHUP): stay silent

    def event(self, text: str) -> None:
        """Queue one event line; printed by the console thread within ``refresh_s``."""
        self._events.append(text)

    def start(self) -> Console:
        self._thread = threading.Thread(target=self._run, name="fasthex-console", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Print the remaining events and erase the status line (idempotent)."""
        self._stopping = True
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        self._flush(show_status=False)

    def _run(self) -> None:
        while not self._stopping:
            self._flush(show_status=True)
            self._wake.wait(self._refresh_s)

    def _flush(self, *, show_status: bool) -> None:
        out: list[str] = []
        while self._events:
            out.append(self._events.popleft() + "\n")
        status = ""
        if show_status and self.live and self._status is not None:
            try:
                status = self._status()
            except Exception:  # a half-built loop: show nothing rather than fail the flight
                status = ""
            # a status wider than the terminal would wrap, and the erase would miss a line:
            # cut it at the last field (two spaces apart) that fits
            width = _columns(self.stream) - 1
            if len(status) > width:
                status = status[:width].rsplit("  ", 1)[0]
        if not out and status == self._shown:
            return
        text = "".join(out)
        if self.live:
            # erase the old status, print the events on their own lines, draw the new status
            text = (CLEAR_LINE if self._shown else "") + text + status
            self._shown = status
        if self.broken or not text:
            return
        try:
            self.stream.write(text)
            self.stream.flush()
        except (OSError, ValueError):  # the terminal is gone: the events file has everything
            self.broken = True


def _columns(stream: TextIO) -> int:
    """The terminal's width; 80 when unknown (a pty nobody sized reports 0 columns)."""
    try:
        columns = os.get_terminal_size(stream.fileno()).columns
    except (AttributeError, ValueError, OSError):
        columns = 0
    return columns if columns > 0 else 80


def _isatty(stream: TextIO) -> bool:
    with contextlib.suppress(AttributeError, ValueError, OSError):
        return bool(stream.isatty())
    return False

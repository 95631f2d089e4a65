"""Pseudo-terminals for the device emulators.

An emulator owns the master side of a pty; the driver under test opens the slave path like any
serial port (pyserial, the Dynamixel SDK's ``PortHandler``). The slave is put in raw mode and
kept open by the emulator too, so the master never reads EIO while no client is connected. An
optional stable symlink (e.g. ``/tmp/fasthex/flight-ctrl``) points at the slave so that a session
file can name the device before the emulator starts.
"""

from __future__ import annotations

import contextlib
import os
import select
import termios
import tty
from pathlib import Path


class PtyEndpoint:
    """The emulator's side of one pty: raw bytes in and out of the master fd."""

    def __init__(self, link_path: str | Path | None = None) -> None:
        self.master_fd, self._slave_fd = os.openpty()
        tty.setraw(self._slave_fd, termios.TCSANOW)
        attrs = termios.tcgetattr(self._slave_fd)
        attrs[3] &= ~termios.ECHO
        termios.tcsetattr(self._slave_fd, termios.TCSANOW, attrs)
        os.set_blocking(self.master_fd, False)
        self.slave_path = os.ttyname(self._slave_fd)
        self.link_path: Path | None = None
        if link_path is not None:
            link = Path(link_path)
            link.parent.mkdir(parents=True, exist_ok=True)
            with contextlib.suppress(FileNotFoundError):
                link.unlink()
            link.symlink_to(self.slave_path)
            self.link_path = link
        self._closed = False

    @property
    def path(self) -> str:
        """The path a client opens: the stable symlink if any, else the slave device."""
        return str(self.link_path) if self.link_path is not None else self.slave_path

    def fileno(self) -> int:
        return self.master_fd

    def wait_readable(self, timeout_s: float) -> bool:
        """Block until bytes from the client are available, or the timeout (s) passes."""
        ready, _, _ = select.select([self.master_fd], [], [], max(0.0, timeout_s))
        return bool(ready)

    def read(self, max_bytes: int = 4096) -> bytes:
        """Bytes written by the client so far (possibly none); never blocks."""
        try:
            return os.read(self.master_fd, max_bytes)
        except (BlockingIOError, InterruptedError):
            return b""

    def write(self, data: bytes) -> int:
        """Send bytes to the client. Returns how many were queued (the pty buffer may be full:
        a real UART would drop them too; the caller counts them)."""
        view = memoryview(data)
        sent = 0
        while sent < len(view):
            try:
                n = os.write(self.master_fd, view[sent:])
            except BlockingIOError:
                ready = select.select([], [self.master_fd], [], 0.05)[1]
                if not ready:
                    break
                continue
            sent += n
        return sent

    def close(self) -> None:
        """Close both sides and remove the symlink: the client sees the device disappear."""
        if self._closed:
            return
        self._closed = True
        for fd in (self.master_fd, self._slave_fd):
            with contextlib.suppress(OSError):
                os.close(fd)
        if self.link_path is not None:
            with contextlib.suppress(FileNotFoundError):
                self.link_path.unlink()

    def __enter__(self) -> PtyEndpoint:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

"""Typed errors shared by the drivers.

Every error names the device it concerns (a path or URI), so that a message shown to the
operator says which cable to look at. Drivers raise these instead of returning result codes;
the ground station turns them into health states or user-facing messages.
"""

from __future__ import annotations

import errno as _errno
import os

__all__ = [
    "DeviceLostError",
    "DeviceOpenError",
    "DriverError",
    "TransportError",
    "TransportUriError",
]


class DriverError(Exception):
    """Base of every driver error. ``device`` names the port, path or URI concerned."""

    def __init__(self, device: str, message: str) -> None:
        self.device = device
        self.message = message
        super().__init__(f"{device}: {message}")


class TransportError(DriverError):
    """The byte pipe to a device failed."""


class TransportUriError(TransportError, ValueError):
    """A transport URI is malformed or names an unknown scheme or option."""


class DeviceOpenError(TransportError):
    """The device could not be opened (missing, busy, no permission, unsupported baud...).

    ``errno`` is the OS error number when there is one (``errno.ENOENT`` for a missing port).
    ``device`` is the path; ``uri``, when given, is what the operator wrote (the URI with its
    options) and leads the one-line message: ``URI: what is wrong``.
    """

    def __init__(self, device: str, errno: int | None, message: str | None = None,
                 uri: str | None = None) -> None:
        self.errno = errno
        self.uri = uri if uri is not None else device
        if message is None:
            reason = os.strerror(errno) if errno is not None else "cannot open"
            name = _errno.errorcode.get(errno, "") if errno is not None else ""
            message = f"cannot open: {reason}" + (f" ({name})" if name else "")
        super().__init__(device, " ".join(message.split()))  # one line, whatever the OS said
        self.args = (f"{self.uri}: {self.message}",)

    def __str__(self) -> str:
        return f"{self.uri}: {self.message}"

    def __reduce__(self) -> tuple[type[DeviceOpenError], tuple[str, int | None, str, str]]:
        return (type(self), (self.device, self.errno, self.message, self.uri))


class DeviceLostError(TransportError):
    """An open device disappeared (USB unplugged, emulator gone, pty closed)."""

    def __init__(self, device: str, message: str = "device disappeared",
                 errno: int | None = None) -> None:
        self.errno = errno
        super().__init__(device, message)

"""Byte transports chosen by URI: the thin pipe under every serial driver.

A transport only moves bytes; framing lives in the codecs. Contract (:class:`Transport`):

- ``read(max_bytes, timeout_s=None)`` waits at most ``timeout_s`` (``None``: the transport's
  ``read_timeout_s``, default 50 ms) for input and returns what is there (1..max_bytes bytes),
  or ``b""`` when nothing came. It never returns a partial
  frame on purpose: the codecs are incremental parsers fed arbitrary chunks.
- ``write(data)`` sends all of ``data`` or raises.
- ``close()`` is idempotent.
- Failures are typed (:mod:`drivers.errors`) and name the device: :class:`DeviceOpenError`
  (with ``errno``) when it cannot be opened, :class:`DeviceLostError` when an open device
  disappears (USB adapter unplugged, emulator gone).
- Serial realities, each one line ``URI: what is wrong`` (:func:`describe_open_error`): port
  absent, permission denied (naming the group that owns the device, e.g. ``dialout``), port
  already open by another process (every tty is opened with an exclusive ``flock``, real ports
  also with ``TIOCEXCL``; the holder's pid is named when ``/proc`` shows it), a baud rate the
  adapter cannot do.

URI forms understood by :func:`open_transport` with the default registry :data:`TRANSPORTS`:

``serial:///dev/ttyUSB0?baud=500000``
    A real serial port through pyserial: raw 8N1, no flow control, exclusive access. ``baud``
    defaults to 500000 (the LAAS tk3 link); ``baud=0`` leaves the line speed alone (what a pty
    or an already configured port wants). On Linux the driver asks for low latency
    (``ASYNC_LOW_LATENCY``) and, for USB-serial adapters (``ttyUSB*``), reads the
    ``latency_timer`` (``/sys/bus/usb-serial/devices/<tty>/latency_timer``), lowers it to 1 ms
    when it is allowed to, and warns with the command to fix it when it stays above 1 ms (the
    default 16 ms would batch a 500 Hz stream); ``low_latency=0`` skips both.
``pty:///tmp/fasthex/flight-ctrl``
    The slave side of a pseudo-terminal (an emulator), opened raw; no line speed.
``/dev/ttyUSB0`` (a bare path)
    ``pty://`` when the path resolves to ``/dev/pts/*``, otherwise ``serial://`` at 500000 baud.
``loop://``
    An in-memory loopback: what is written is read back (tests of codecs and devices).
``spy://<inner-uri>?log=<file>``
    Wraps any other URI and appends every chunk read or written to ``file`` as
    ``<monotonic ns> RX|TX <hex>`` lines, for recording real traffic.

The registry is an immutable mapping from scheme to factory; tests pass their own mapping to
add fake schemes instead of mutating module state.
"""

from __future__ import annotations

import contextlib
import errno as _errno
import logging
import os
import select
import threading
import time
import tty
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType
from typing import Protocol, runtime_checkable
from urllib.parse import parse_qsl

from drivers.errors import DeviceLostError, DeviceOpenError, TransportError, TransportUriError

__all__ = [
    "DEFAULT_BAUD",
    "LATENCY_TIMER_ROOT",
    "TRANSPORTS",
    "FdTransport",
    "LoopTransport",
    "SpyTransport",
    "Transport",
    "TransportFactory",
    "TransportUri",
    "check_latency_timer",
    "describe_open_error",
    "open_transport",
    "parse_uri",
]

log = logging.getLogger(__name__)

DEFAULT_BAUD = 500_000
DEFAULT_READ_TIMEOUT_S = 0.05
_WRITE_TIMEOUT_S = 1.0


@runtime_checkable
class Transport(Protocol):
    """A byte pipe to one device."""

    name: str

    def read(self, max_bytes: int = 4096, timeout_s: float | None = None) -> bytes:
        """Up to ``max_bytes`` received bytes; ``b""`` if none came within ``timeout_s`` (None:
        the transport's own read timeout)."""
        ...

    def write(self, data: bytes) -> None:
        """Send every byte of ``data``."""
        ...

    def close(self) -> None:
        """Release the device; further calls do nothing."""
        ...


@dataclass(frozen=True, slots=True)
class TransportUri:
    """A parsed transport URI: ``scheme://target?key=value&...``."""

    uri: str
    scheme: str
    target: str
    options: Mapping[str, str]

    def check_options(self, allowed: tuple[str, ...], form: str) -> None:
        unknown = sorted(set(self.options) - set(allowed))
        if unknown:
            raise TransportUriError(
                self.uri, f"unknown option {unknown[0]!r}; expected the form {form}")

    def int_option(self, key: str, default: int, form: str) -> int:
        raw = self.options.get(key)
        if raw is None:
            return default
        try:
            value = int(raw)
        except ValueError:
            raise TransportUriError(
                self.uri, f"option {key}={raw!r} is not an integer; expected {form}") from None
        if value < 0:
            raise TransportUriError(self.uri, f"option {key}={value} must be >= 0")
        return value


TransportFactory = Callable[[TransportUri, Mapping[str, "TransportFactory"]], Transport]


def parse_uri(uri: str) -> TransportUri:
    """Split ``uri`` into scheme, target and options. A bare path gets the scheme ``path``.

    ``spy://`` keeps everything before its own (last) ``?`` as the target, so that the inner URI
    may carry options of its own.
    """
    if not uri:
        raise TransportUriError("<empty>", "empty transport URI")
    scheme, sep, rest = uri.partition("://")
    if not sep:
        return TransportUri(uri, "path", uri, MappingProxyType({}))
    scheme = scheme.lower()
    target, _, query = rest.rpartition("?") if "?" in rest else (rest, "", "")
    if scheme != "spy" and "?" in target:
        raise TransportUriError(uri, "more than one '?' in the URI")
    try:
        pairs = parse_qsl(query, keep_blank_values=True, strict_parsing=bool(query))
    except ValueError:
        raise TransportUriError(uri, f"malformed options {query!r}; expected key=value&...")\
            from None
    options: dict[str, str] = {}
    for key, value in pairs:
        if key in options:
            raise TransportUriError(uri, f"option {key!r} given twice")
        options[key] = value
    return TransportUri(uri, scheme, target, MappingProxyType(options))


class FdTransport:
    """A transport over one POSIX file descriptor (a tty or pty), waiting with ``select``.

    ``on_close`` releases whatever owns the descriptor (pyserial's ``Serial`` for real ports).
    """

    def __init__(self, name: str, fd: int, on_close: Callable[[], None] | None = None,
                 read_timeout_s: float = DEFAULT_READ_TIMEOUT_S) -> None:
        self.name = name
        self.read_timeout_s = read_timeout_s
        self.latency_timer_ms: int | None = None
        self._fd = fd
        self._on_close = on_close
        self._closed = False
        os.set_blocking(fd, False)

    def fileno(self) -> int:
        return self._fd

    def read(self, max_bytes: int = 4096, timeout_s: float | None = None) -> bytes:
        if self._closed:
            raise DeviceLostError(self.name, "transport is closed")
        wait_s = self.read_timeout_s if timeout_s is None else max(timeout_s, 0.0)
        try:
            ready = select.select([self._fd], [], [], wait_s)[0]
            if not ready:
                return b""
            data = os.read(self._fd, max_bytes)
        except (BlockingIOError, InterruptedError):
            return b""
        except (OSError, ValueError) as exc:
            if self._closed:
                raise DeviceLostError(self.name, "transport is closed") from None
            raise DeviceLostError(self.name, f"read failed: {exc}",
                                  getattr(exc, "errno", None)) from exc
        if not data:
            # Readable but empty: the other side hung up (USB unplugged, pty master closed).
            raise DeviceLostError(self.name, "device reports readiness but returned no data")
        return data

    def write(self, data: bytes) -> None:
        if self._closed:
            raise DeviceLostError(self.name, "transport is closed")
        view = memoryview(data)
        deadline = time.monotonic() + _WRITE_TIMEOUT_S
        while view:
            try:
                n = os.write(self._fd, view)
            except BlockingIOError:
                if time.monotonic() > deadline:
                    raise TransportError(self.name, "write timed out (output buffer full)")\
                        from None
                select.select([], [self._fd], [], 0.01)
                continue
            except OSError as exc:
                raise DeviceLostError(self.name, f"write failed: {exc}", exc.errno) from exc
            view = view[n:]

    def discard_input(self) -> None:
        """Drop bytes already received but not read (the connect-time flush)."""
        import termios

        with contextlib.suppress(OSError, termios.error):
            termios.tcflush(self._fd, termios.TCIFLUSH)

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        if self._on_close is not None:
            with contextlib.suppress(Exception):
                self._on_close()
        else:
            with contextlib.suppress(OSError):
                os.close(self._fd)

    def __enter__(self) -> FdTransport:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# ------------------------------------------------------------------------ serial realities

def _holders(path: str) -> list[tuple[int, str]]:
    """(pid, command) of the processes with ``path`` open, as far as ``/proc`` shows them
    (other users' processes are invisible to a non-root caller: then the list is short)."""
    real = os.path.realpath(path)
    found: list[tuple[int, str]] = []
    with contextlib.suppress(OSError):
        for entry in os.scandir("/proc"):
            if not entry.name.isdigit():
                continue
            try:
                fds = os.scandir(f"/proc/{entry.name}/fd")
            except OSError:
                continue
            with fds:
                for fd in fds:
                    try:
                        if os.readlink(fd.path) == real:
                            comm = Path(f"/proc/{entry.name}/comm").read_text().strip()
                            found.append((int(entry.name), comm))
                            break
                    except OSError:
                        continue
    return found


def describe_open_error(path: str, err: int | None, detail: str = "", *,
                        baud: int | None = None, pty: bool = False) -> str:
    """What the operator needs to read when ``path`` does not open with OS error ``err``: one
    line, with the fix where there is one. ``detail`` is the OS's own text (kept when the errno
    alone says little); ``baud``: the line speed asked for; ``pty``: an emulator's pty."""
    if err == _errno.ENOENT:
        if pty:
            return "no such pty: is the emulator (`fasthex emulate`) running?"
        return ("no such device: is the adapter plugged in and powered? (`ls -l "
                "/dev/serial/by-id/` lists the USB-serial adapters)")
    if err in (_errno.EACCES, _errno.EPERM):
        import grp
        import stat

        try:
            st = os.stat(path)
            group = grp.getgrgid(st.st_gid).gr_name
        except (OSError, KeyError):
            return "permission denied (and its owner cannot be read)"
        mode = stat.filemode(st.st_mode)
        if not st.st_mode & stat.S_IRWXG:
            return f"permission denied: {mode} leaves no access to its group {group!r}"
        return (f"permission denied: the device ({mode}) belongs to group {group!r}; add "
                f"yourself with `sudo usermod -aG {group} $USER` and log in again")
    if err in (_errno.EBUSY, _errno.EAGAIN, _errno.EWOULDBLOCK):
        holders = _holders(path)
        others = [h for h in holders if h[0] != os.getpid()]
        if holders and not others:
            return "already open by this process (one owner per port)"
        who = ", ".join(f"pid {pid} ({comm})" for pid, comm in others[:3])
        return ("already open by another process" + (f": {who}" if who else "")
                + "; close it first (one owner per port)")
    if err in (_errno.ENXIO, _errno.ENODEV, _errno.EIO):
        return "the device node exists but nothing answers behind it (adapter unplugged?)"
    if err == _errno.EINVAL and baud is not None:
        return (f"the adapter cannot run at {baud} baud (the driver refused the line speed); "
                "tk3 boards run at 500000, stock ones at 57600")
    reason = os.strerror(err) if err is not None else "cannot open"
    return f"cannot open: {reason}" + (f" ({detail})" if detail else "")


def _lock(fd: int, path: str, uri: str) -> None:
    """Exclusive advisory lock (what pyserial's ``exclusive=True`` takes; root included)."""
    import fcntl

    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as exc:
        os.close(fd)
        raise DeviceOpenError(path, _errno.EBUSY, describe_open_error(path, _errno.EBUSY),
                              uri) from exc


def _open_raw_tty(path: str, uri: str | None = None, pty: bool = False) -> int:
    uri = uri if uri is not None else path
    try:
        fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    except OSError as exc:
        raise DeviceOpenError(path, exc.errno, describe_open_error(path, exc.errno, pty=pty),
                              uri) from exc
    try:
        tty.setraw(fd)
    except Exception as exc:
        os.close(fd)
        raise DeviceOpenError(path, getattr(exc, "errno", None), f"not a tty: {exc}",
                              uri) from exc
    _lock(fd, path, uri)
    return fd


def _open_pty(uri: TransportUri, registry: Mapping[str, TransportFactory]) -> Transport:
    uri.check_options((), "pty://<path>")
    if not uri.target:
        raise TransportUriError(uri.uri, "missing path; expected pty://<path>")
    return FdTransport(uri.target, _open_raw_tty(uri.target, uri.uri, pty=True))


LATENCY_TIMER_ROOT = Path("/sys/bus/usb-serial/devices")
"""Where Linux shows a USB-serial adapter's ``latency_timer`` (ms), one directory per tty."""


def check_latency_timer(path: str, root: Path = LATENCY_TIMER_ROOT, *, lower: bool = False
                        ) -> tuple[int | None, str | None]:
    """The USB-serial latency timer of the port ``path`` (ms; ``None``: not a ``ttyUSB`` or
    not readable) and a warning line when it is above 1 ms. ``lower`` first tries to write 1
    (allowed to root, or with a udev rule)."""
    name = os.path.basename(os.path.realpath(path))
    if not name.startswith("ttyUSB"):
        return None, None
    timer = root / name / "latency_timer"
    try:
        value = int(timer.read_text().strip())
        if value > 1 and lower:
            with contextlib.suppress(OSError):
                timer.write_text("1")
            value = int(timer.read_text().strip())
    except (OSError, ValueError):
        return None, None
    if value <= 1:
        return value, None
    return value, (f"USB-serial latency timer is {value} ms: a 500 Hz stream arrives in "
                   f"{value} ms batches (want 1 ms); fix: `echo 1 | sudo tee {timer}` (or a "
                   f"udev rule: ATTR{{latency_timer}}=\"1\")")


def _set_low_latency(name: str, uri: str, ser: object, transport: FdTransport) -> None:
    """Best effort: ASYNC_LOW_LATENCY, then the USB-serial latency timer down to 1 ms."""
    setter = getattr(ser, "set_low_latency_mode", None)
    if setter is not None:
        try:
            setter(True)
        except (OSError, ValueError) as exc:
            log.debug("%s: low-latency mode not available: %s", name, exc)
    value, warning = check_latency_timer(name, lower=True)
    transport.latency_timer_ms = value
    if warning is not None:
        log.warning("%s: %s", uri, warning)


_SERIAL_FORM = "serial://<device>?baud=<int>&low_latency=<0|1>"


def _open_serial(uri: TransportUri, registry: Mapping[str, TransportFactory]) -> Transport:
    uri.check_options(("baud", "low_latency"), _SERIAL_FORM)
    path = uri.target
    if not path:
        raise TransportUriError(uri.uri, f"missing device; expected {_SERIAL_FORM}")
    baud = uri.int_option("baud", DEFAULT_BAUD, _SERIAL_FORM)
    low_latency = uri.int_option("low_latency", 1, _SERIAL_FORM)
    if baud == 0:
        # Leave the line speed alone (rotorcraft's "baud 0"): a pty or a pre-configured port.
        return FdTransport(path, _open_raw_tty(path, uri.uri))
    import serial

    try:
        ser = serial.Serial(port=path, baudrate=baud, bytesize=8, parity="N", stopbits=1,
                            timeout=0, xonxoff=False, rtscts=False, dsrdtr=False,
                            exclusive=True)
    except (serial.SerialException, OSError, ValueError) as exc:
        raise _serial_open_error(path, uri.uri, baud, exc) from exc
    _set_exclusive(ser)
    transport = FdTransport(path, ser.fileno(), on_close=lambda: _close_serial(ser))
    if low_latency:
        _set_low_latency(path, uri.uri, ser, transport)
    return transport


def _serial_open_error(path: str, uri: str, baud: int, exc: Exception) -> DeviceOpenError:
    """pyserial's failures, sorted: absent or forbidden (asked of the node itself: pyserial
    folds those into one text), busy (its flock), the line speed, anything else."""
    text = str(exc)
    err = getattr(exc, "errno", None)
    try:
        os.close(os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK))
    except OSError as node:
        if node.errno in (_errno.ENOENT, _errno.EACCES, _errno.EPERM, _errno.ENXIO,
                          _errno.ENODEV):
            return DeviceOpenError(path, node.errno, describe_open_error(path, node.errno),
                                   uri)
    if "exclusively lock" in text or err in (_errno.EBUSY, _errno.EAGAIN):
        err = _errno.EBUSY
    elif isinstance(exc, ValueError) or "baud" in text.lower() or err == _errno.EINVAL:
        err = _errno.EINVAL
    return DeviceOpenError(path, err, describe_open_error(path, err, text, baud=baud), uri)


def _set_exclusive(ser: object) -> None:
    # TIOCEXCL: later open()s of the tty fail with EBUSY even for programs that take no
    # lock (screen, cat); root is exempt, hence the flock as well.
    import fcntl
    import termios

    with contextlib.suppress(OSError, ValueError, AttributeError):
        fcntl.ioctl(ser.fileno(), termios.TIOCEXCL)  # type: ignore[attr-defined]


def _close_serial(ser: object) -> None:
    import fcntl
    import termios

    with contextlib.suppress(OSError, ValueError, AttributeError):
        fcntl.ioctl(ser.fileno(), termios.TIOCNXCL)  # type: ignore[attr-defined]
    ser.close()  # type: ignore[attr-defined]


def _open_path(uri: TransportUri, registry: Mapping[str, TransportFactory]) -> Transport:
    real = os.path.realpath(uri.target)
    scheme = "pty" if real.startswith("/dev/pts/") else "serial"
    if scheme not in registry:
        raise TransportUriError(uri.uri, f"no transport registered for {scheme}://")
    inner = TransportUri(f"{scheme}://{uri.target}", scheme, uri.target, MappingProxyType({}))
    return registry[scheme](inner, registry)


class LoopTransport:
    """In-memory loopback: bytes written are read back in order. Thread-safe."""

    def __init__(self, name: str = "loop://", read_timeout_s: float = DEFAULT_READ_TIMEOUT_S
                 ) -> None:
        self.name = name
        self.read_timeout_s = read_timeout_s
        self._buf = bytearray()
        self._cond = threading.Condition()
        self._closed = False

    def read(self, max_bytes: int = 4096, timeout_s: float | None = None) -> bytes:
        with self._cond:
            if not self._buf and not self._closed:
                self._cond.wait(self.read_timeout_s if timeout_s is None else max(timeout_s, 0.0))
            if self._closed:
                raise DeviceLostError(self.name, "transport is closed")
            data = bytes(self._buf[:max_bytes])
            del self._buf[:max_bytes]
            return data

    def write(self, data: bytes) -> None:
        with self._cond:
            if self._closed:
                raise DeviceLostError(self.name, "transport is closed")
            self._buf += data
            self._cond.notify_all()

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify_all()


def _open_loop(uri: TransportUri, registry: Mapping[str, TransportFactory]) -> Transport:
    uri.check_options((), "loop://")
    return LoopTransport(uri.uri)


class SpyTransport:
    """Wraps a transport and logs every chunk read or written, with a monotonic timestamp."""

    def __init__(self, inner: Transport, log_path: str | None) -> None:
        self.name = inner.name
        self._inner = inner
        self._lock = threading.Lock()
        self._file = open(log_path, "a", encoding="ascii") if log_path else None  # noqa: SIM115

    def _log(self, direction: str, data: bytes) -> None:
        line = f"{time.monotonic_ns()} {direction} {data.hex(' ')}\n"
        with self._lock:
            if self._file is not None:
                self._file.write(line)
                self._file.flush()
            else:
                log.info("%s %s", self.name, line.rstrip())

    def read(self, max_bytes: int = 4096, timeout_s: float | None = None) -> bytes:
        data = self._inner.read(max_bytes, timeout_s)
        if data:
            self._log("RX", data)
        return data

    def write(self, data: bytes) -> None:
        self._log("TX", data)
        self._inner.write(data)

    def close(self) -> None:
        self._inner.close()
        with self._lock:
            if self._file is not None:
                self._file.close()
                self._file = None

    def __getattr__(self, attr: str) -> object:
        # Extras of the inner transport (discard_input, read_timeout_s...) stay reachable.
        return getattr(self._inner, attr)


def _open_spy(uri: TransportUri, registry: Mapping[str, TransportFactory]) -> Transport:
    uri.check_options(("log",), "spy://<inner-uri>?log=<file>")
    if not uri.target:
        raise TransportUriError(uri.uri, "missing inner URI; expected spy://<inner-uri>")
    inner = open_transport(uri.target, registry=registry)
    return SpyTransport(inner, uri.options.get("log") or None)


TRANSPORTS: Mapping[str, TransportFactory] = MappingProxyType({
    "serial": _open_serial,
    "pty": _open_pty,
    "path": _open_path,
    "loop": _open_loop,
    "spy": _open_spy,
})
"""The default scheme -> factory registry (read-only)."""


def check_transport_uri(uri: str) -> None:
    """What :func:`open_transport` checks of ``uri`` before it opens anything (scheme, options,
    their integer values), for a config file validated before any device opens. Raises
    :class:`TransportUriError`."""
    parsed = parse_uri(uri)
    if parsed.scheme not in TRANSPORTS:
        known = ", ".join(f"{s}://" for s in sorted(TRANSPORTS) if s != "path")
        raise TransportUriError(uri, f"unknown scheme {parsed.scheme!r}; expected one of {known}")
    if parsed.scheme == "serial":
        parsed.check_options(("baud", "low_latency"), _SERIAL_FORM)
        if not parsed.target:
            raise TransportUriError(uri, f"missing device; expected {_SERIAL_FORM}")
        parsed.int_option("baud", DEFAULT_BAUD, _SERIAL_FORM)
        parsed.int_option("low_latency", 1, _SERIAL_FORM)
    elif parsed.scheme in ("pty", "loop"):
        parsed.check_options((), f"{parsed.scheme}://" + ("<path>" if parsed.scheme == "pty"
                                                          else ""))
    elif parsed.scheme == "spy":
        parsed.check_options(("log",), "spy://<inner-uri>?log=<file>")
        if not parsed.target:
            raise TransportUriError(uri, "missing inner URI; expected spy://<inner-uri>")
        check_transport_uri(parsed.target)


def open_transport(uri: str, registry: Mapping[str, TransportFactory] = TRANSPORTS
                   ) -> Transport:
    """Open the transport named by ``uri`` (forms in the module docstring).

    Raises :class:`TransportUriError` for an unknown scheme or option, :class:`DeviceOpenError`
    when the device cannot be opened.
    """
    parsed = parse_uri(uri)
    factory = registry.get(parsed.scheme)
    if factory is None:
        known = ", ".join(f"{s}://" for s in sorted(registry) if s != "path")
        raise TransportUriError(uri, f"unknown scheme {parsed.scheme!r}; expected one of {known}")
    return factory(parsed, registry)

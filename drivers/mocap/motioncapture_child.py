"""The process libmotioncapture runs in, and the pipe format it reports through.

Why a process: ``motioncapture.connect`` holds the GIL for the whole connect and handshake, so
in the ground station's process a silent or wrong host froze every Python thread (5 s for
qualisys, for ever for vicon and optitrack). Here it freezes only this process, which the
adapter (:class:`drivers.mocap.motioncapture_client.MotionCaptureClient`) ends when its
``connect_timeout_s`` runs out or on ``close()``.

Run as ``python -P -m drivers.mocap.motioncapture_child SYSTEM OPTIONS_JSON PARENT_PID``; it
imports only the standard library and ``motioncapture``. It connects, then reports every frame
the library returns until the library fails, its stdin reaches end of file, or it is killed.
It never outlives the ground station: on Linux the kernel kills it when the parent thread that
started it ends (``PR_SET_PDEATHSIG``; this works even while the library holds the GIL), and
on any system it exits when its stdin (a pipe nobody writes to) ends or its report pipe
breaks. SIGINT and SIGHUP are ignored (Ctrl-C and a closed terminal are the parent's to
handle, which then ends this process); SIGTERM ends it at once.

Pipe format (the child's stdout; the library's own prints go to stderr), little-endian, one
message after another, each ``u32 payload_len, u8 kind, payload``:

``C`` (connected): empty; ``connect`` returned.

``F`` (frame): ``i64 rx_monotonic_ns`` (``time.monotonic_ns()`` when ``waitForNextFrame``
returned), ``f64 library_time_s`` (the library's frame time; NaN: the ``motioncapture`` 1.1
binding gives none), ``u16 body_count``, then per body ``u16 name_len``, ``name`` (UTF-8),
``u8 ok`` (0: the library's values were not numbers, the pose is NaN) and 7 ``f64``: the
position x, y, z in metres and the quaternion w, x, y, z, in the system's axes.

``E`` (error): ``u8 stage`` (``STAGE_IMPORT`` 0: no library, ``STAGE_CONNECT`` 1,
``STAGE_FRAMES`` 2), then the library's message (UTF-8). The child exits after it.
"""

from __future__ import annotations

import importlib
import json
import math
import os
import signal
import struct
import sys
import threading
import time
from collections.abc import Iterable
from dataclasses import dataclass
from typing import IO, Any

KIND_CONNECTED = b"C"
KIND_FRAME = b"F"
KIND_ERROR = b"E"
STAGE_IMPORT = 0
STAGE_CONNECT = 1
STAGE_FRAMES = 2

#: A payload longer than this is a broken pipe stream, never a frame (65535 bodies fit).
MAX_PAYLOAD_BYTES = 16 * 1024 * 1024

_HEADER = struct.Struct("<IB")
_FRAME_HEAD = struct.Struct("<qdH")
_NAME_LEN = struct.Struct("<H")
_POSE = struct.Struct("<B7d")
_STAGE = struct.Struct("<B")
_PR_SET_PDEATHSIG = 1  # <linux/prctl.h>

Pose7 = tuple[float, float, float, float, float, float, float]  # x, y, z, qw, qx, qy, qz
_NAN7: Pose7 = (math.nan,) * 7


@dataclass(frozen=True, slots=True)
class BodyPose:
    """One rigid body of one frame as the library gave it (system axes, metres)."""

    name: str
    ok: bool  # False: the library's values were not numbers
    position_m: tuple[float, float, float]
    q_wxyz: tuple[float, float, float, float]


@dataclass(frozen=True, slots=True)
class Frame:
    rx_monotonic_ns: int
    library_time_s: float
    bodies: tuple[BodyPose, ...]


@dataclass(frozen=True, slots=True)
class ChildError:
    stage: int
    message: str


class PipeFormatError(Exception):
    """The child's stream is not the format above (it cannot be read any further)."""


# ---------------------------------------------------------------------------------- encoding

def _message(kind: bytes, payload: bytes) -> bytes:
    return _HEADER.pack(len(payload), kind[0]) + payload


def encode_connected() -> bytes:
    return _message(KIND_CONNECTED, b"")


def encode_error(stage: int, message: str) -> bytes:
    return _message(KIND_ERROR, _STAGE.pack(stage) + message.encode("utf-8", "replace"))


def encode_frame(rx_monotonic_ns: int, library_time_s: float,
                 bodies: Iterable[tuple[str, bool, Pose7]]) -> bytes:
    parts = []
    count = 0
    for name, ok, pose in bodies:
        if count == 0xFFFF:  # the count's limit; no system tracks that many bodies
            break
        raw = name.encode("utf-8", "replace")[:0xFFFF]
        parts += [_NAME_LEN.pack(len(raw)), raw, _POSE.pack(1 if ok else 0, *pose)]
        count += 1
    return _message(KIND_FRAME, _FRAME_HEAD.pack(rx_monotonic_ns, library_time_s,
                                                  count) + b"".join(parts))


# ---------------------------------------------------------------------------------- decoding

def read_message(stream: IO[bytes]) -> bytes | Frame | ChildError | None:
    """The next message from ``stream`` (``KIND_CONNECTED`` as those bytes), or None at the end
    of the stream. Raises :class:`PipeFormatError` for bytes that are not the format."""
    header = stream.read(_HEADER.size)
    if not header:
        return None
    if len(header) < _HEADER.size:
        raise PipeFormatError("the stream ended inside a message header")
    length, kind = _HEADER.unpack(header)
    if length > MAX_PAYLOAD_BYTES:
        raise PipeFormatError(f"a {length}-byte message")
    payload = stream.read(length) if length else b""
    if len(payload) < length:
        raise PipeFormatError("the stream ended inside a message")
    try:
        if kind == KIND_CONNECTED[0] and not payload:
            return KIND_CONNECTED
        if kind == KIND_ERROR[0] and payload:
            return ChildError(payload[0], payload[1:].decode("utf-8", "replace"))
        if kind == KIND_FRAME[0]:
            return _decode_frame(payload)
    except (struct.error, IndexError) as exc:
        raise PipeFormatError(f"a malformed message of kind {kind}: {exc}") from exc
    raise PipeFormatError(f"a message of unknown kind {kind} ({length} bytes)")


def _decode_frame(payload: bytes) -> Frame:
    rx_ns, lib_t_s, count = _FRAME_HEAD.unpack_from(payload, 0)
    at = _FRAME_HEAD.size
    bodies = []
    for _ in range(count):
        (name_len,) = _NAME_LEN.unpack_from(payload, at)
        at += _NAME_LEN.size
        name = payload[at:at + name_len].decode("utf-8", "replace")
        at += name_len
        ok, x, y, z, qw, qx, qy, qz = _POSE.unpack_from(payload, at)
        at += _POSE.size
        bodies.append(BodyPose(name, bool(ok), (x, y, z), (qw, qx, qy, qz)))
    if at != len(payload):
        raise struct.error(f"{len(payload) - at} bytes after the last body")
    return Frame(rx_ns, lib_t_s, tuple(bodies))


# ---------------------------------------------------------------------------------- the child

def _body_pose(rb: Any) -> tuple[bool, Pose7]:
    try:
        p, q = rb.position, rb.rotation
        return True, (float(p[0]), float(p[1]), float(p[2]),
                      float(q.w), float(q.x), float(q.y), float(q.z))
    except (TypeError, ValueError, IndexError, AttributeError):
        return False, _NAN7


def _library_time_s(mc: Any) -> float:
    try:  # no binding up to motioncapture 1.1 has a frame time; a later one may
        return float(mc.timeStamp)
    except (AttributeError, TypeError, ValueError):
        return math.nan


def _die_with_parent(parent_pid: int) -> None:
    """Ask the kernel for SIGKILL when the parent thread ends; exit if it already has."""
    if sys.platform.startswith("linux"):
        try:
            import ctypes

            libc = ctypes.CDLL(None, use_errno=True)
            libc.prctl(_PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0)
        except (OSError, AttributeError):
            pass  # the stdin watch below still ends the child once the library lets it run
    if os.getppid() != parent_pid:  # the parent died before the request took effect
        os._exit(0)


def _exit_at_end_of_stdin() -> None:
    try:
        while os.read(0, 4096):
            pass
    except OSError:
        pass
    os._exit(0)  # the parent closed the pipe or died; nothing here needs cleaning up


def _send(fd: int, data: bytes) -> None:
    view = memoryview(data)
    while view:
        try:
            view = view[os.write(fd, view):]
        except BrokenPipeError:
            os._exit(0)  # the parent stopped reading: it is gone or closing


def main(argv: list[str]) -> int:
    # Ctrl-C and a closed terminal are the parent's to handle; SIGTERM (its default action,
    # which needs no GIL) is how the parent ends us. A parent that started us with these
    # signals blocked (a session deferring its stop signals) must not defer our SIGTERM.
    # Ctrl-\ would kill us and Ctrl-Z (and a background job's terminal stops) freeze the poses
    # in flight.
    for sig in (signal.SIGINT, signal.SIGHUP, signal.SIGQUIT, signal.SIGTSTP, signal.SIGTTIN,
                signal.SIGTTOU):
        signal.signal(sig, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT, signal.SIGHUP, signal.SIGTERM})
    system, options_json, parent_pid = argv[0], argv[1], int(argv[2])
    _die_with_parent(parent_pid)
    # The reports get a private copy of stdout; fd 1 (and print) goes to stderr, so whatever
    # the library writes to stdout cannot corrupt the pipe format.
    out_fd = os.dup(1)
    os.dup2(2, 1)
    threading.Thread(target=_exit_at_end_of_stdin, name="stdin-watch", daemon=True).start()
    options: dict[str, str] = json.loads(options_json)
    try:
        motioncapture = importlib.import_module("motioncapture")
    except ImportError as exc:
        _send(out_fd, encode_error(STAGE_IMPORT, str(exc)))
        return 1
    try:
        mc = motioncapture.connect(system, options)
    except Exception as exc:  # the library raises RuntimeError; any is reported as the error
        _send(out_fd, encode_error(STAGE_CONNECT, str(exc) or type(exc).__name__))
        return 1
    _send(out_fd, encode_connected())
    while True:
        try:
            mc.waitForNextFrame()
            rx_ns = time.monotonic_ns()
            bodies = mc.rigidBodies
            report = encode_frame(rx_ns, _library_time_s(mc),
                                  ((str(name), *_body_pose(rb)) for name, rb in bodies.items()))
        except Exception as exc:
            _send(out_fd, encode_error(STAGE_FRAMES, str(exc) or type(exc).__name__))
            return 1
        _send(out_fd, report)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))

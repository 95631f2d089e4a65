"""LAAS tk3-mikrokopter framing (the 500 Hz flight link). Pure: bytes in, bytes out.

Wire format (tk3-mikrokopter firmware, host side in rotorcraft-genom3 ``codels/tty.c``)::

    '^'  cmd  payload...  '$'

- ``^`` (0x5E) starts a message; a ``^`` inside a message restarts it (the partial one is lost).
- ``$`` (0x24) ends it; ``!`` (0x21) aborts it.
- Inside a message (command byte included) each of ``^ $ \\ !`` is sent as ``\\`` (0x5C)
  followed by its bitwise NOT: ``5E -> 5C A1``, ``24 -> 5C DB``, ``5C -> 5C A3``, ``21 -> 5C DE``.
- No checksum and no length field: the receiver checks the exact length of each message type
  (:mod:`drivers.mikrokopter.messages`). Integers are big-endian. A message (cmd + payload,
  unescaped) is at most 64 bytes; longer ones are discarded.
- Line: raw 8N1, 500000 baud on the FAST-Hex (57600 / 115200 / 2000000 also exist), no flow
  control. Worst-case frame size is ``3 + 2 n`` bytes for an n-byte payload.

A "message" here is the unescaped ``cmd + payload`` bytes; :func:`encode_frame` adds the framing,
:class:`Tk3Parser` removes it from arbitrary chunks of a byte stream.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import dataclass

__all__ = ["ABORT", "END", "ESC", "MAX_MESSAGE_BYTES", "START", "Tk3Parser", "Tk3ParserStats",
           "encode_frame"]

START = 0x5E  # '^'
END = 0x24  # '$'
ESC = 0x5C  # '\'
ABORT = 0x21  # '!'
MAX_MESSAGE_BYTES = 64

_SPECIAL = re.compile(rb"[\^\$\\!]")
_ESCAPED = {b: bytes((ESC, b ^ 0xFF)) for b in (START, END, ESC, ABORT)}


def _escape_match(m: re.Match[bytes]) -> bytes:
    return _ESCAPED[m.group()[0]]


def encode_frame(message: bytes) -> bytes:
    """Frame one message (``cmd + payload``): ``^``, escaped message, ``$``."""
    if _SPECIAL.search(message) is None:
        return b"^" + message + b"$"
    return b"^" + _SPECIAL.sub(_escape_match, message) + b"$"


@dataclass(slots=True)
class Tk3ParserStats:
    """What the parser has seen so far. Every byte not in a delivered message is accounted for
    by exactly one of the error kinds (garbage bytes, or the frame they belonged to)."""

    messages: int = 0
    garbage_bytes: int = 0
    """Bytes outside any frame (before a ``^``)."""
    aborted: int = 0
    """Frames ended by ``!``."""
    truncated: int = 0
    """Frames cut short by a new ``^`` before their ``$``."""
    oversize: int = 0
    """Frames longer than 64 bytes, or than their command's fixed length, discarded."""
    empty: int = 0
    """``^$`` with no command byte."""
    bad_escape: int = 0
    """``\\`` followed by a byte whose NOT is not a special byte: no valid sender does that."""

    @property
    def frame_errors(self) -> int:
        return self.aborted + self.truncated + self.oversize + self.empty + self.bad_escape


class Tk3Parser:
    """Incremental tk3 deframer: ``feed(chunk) -> [message, ...]``, never raises on any input."""

    def __init__(self, max_message_bytes: int = MAX_MESSAGE_BYTES,
                 message_bytes_by_cmd: Mapping[bytes, int] | None = None) -> None:
        """``message_bytes_by_cmd``: the fixed message length (cmd + payload) of command bytes
        that have one. A frame of such a command is dropped (as oversize) as soon as it grows
        past that length, not at its ``$``: a frame whose ``$`` was corrupted is then counted
        when its last byte arrives, not when the next frame starts (which on a link where the
        board answers each command may be a command away)."""
        self.max_message_bytes = max_message_bytes
        self._limit_by_cmd = [max_message_bytes] * 256
        for cmd, size in (message_bytes_by_cmd or {}).items():
            if len(cmd) != 1 or not 1 <= size <= max_message_bytes:
                raise ValueError(f"message length {size} for command {cmd!r}: expected one "
                                 f"command byte and 1..{max_message_bytes} bytes")
            self._limit_by_cmd[cmd[0]] = size
        self.stats = Tk3ParserStats()
        self._buf = bytearray()
        self._in_frame = False
        self._escape = False
        self._bad = False  # frame already known bad (bad escape), dropped at its end

    def reset(self) -> None:
        """Forget any partial frame (counters are kept)."""
        self._buf.clear()
        self._in_frame = self._escape = self._bad = False

    def feed(self, data: bytes) -> list[bytes]:
        if not isinstance(data, bytes):
            data = bytes(data)
        out: list[bytes] = []
        stats = self.stats
        pos = 0
        n = len(data)
        while pos < n:
            if not self._in_frame:
                start = data.find(b"^", pos)
                if start < 0:
                    stats.garbage_bytes += n - pos
                    return out
                stats.garbage_bytes += start - pos
                pos = start + 1
                self._in_frame = True
                self._buf.clear()
                self._escape = self._bad = False
                continue
            if self._escape:
                byte = data[pos]
                if byte in (START, END, ABORT):
                    # The framing byte wins; the dangling escape marks the frame as bad.
                    self._escape = False
                    self._bad = True
                    continue
                self._escape = False
                value = byte ^ 0xFF
                if value not in (START, END, ESC, ABORT):
                    self._bad = True
                self._buf.append(value)
                pos += 1
                self._check_size()
                continue
            m = _SPECIAL.search(data, pos)
            stop = m.start() if m is not None else n
            if stop > pos:
                self._buf += data[pos:stop]
                pos = stop
                if self._check_size():
                    continue
            if m is None:
                return out
            byte = data[pos]
            pos += 1
            if byte == ESC:
                self._escape = True
            elif byte == END:
                self._in_frame = False
                if self._bad:
                    stats.bad_escape += 1
                elif not self._buf:
                    stats.empty += 1
                else:
                    stats.messages += 1
                    out.append(bytes(self._buf))
            elif byte == ABORT:
                stats.aborted += 1
                self._in_frame = False
            else:  # START inside a frame: restart
                stats.truncated += 1
                self._buf.clear()
                self._escape = self._bad = False
        return out

    def _check_size(self) -> bool:
        """Drop the frame in progress if it overflowed; True if it was dropped."""
        buf = self._buf
        if len(buf) <= self._limit_by_cmd[buf[0]]:  # never empty here: a byte was just added
            return False
        self.stats.oversize += 1
        self._in_frame = False
        self._buf.clear()
        return True

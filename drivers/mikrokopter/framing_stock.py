"""Stock HiSystems MikroKopter serial framing (identification and bench tests only). Pure.

Wire format (FlightCtrl V2.12a ``uart.c``: ``SendOutData``, ``AddCRC``, ``Decode64``)::

    '#'  'a'+address  cmd  base64-ish payload (4 chars per 3 bytes)  CRC1 CRC2  '\\r'

- address: 0 ``a`` any, 1 ``b`` Flight-Ctrl, 2 ``c`` Navi-Ctrl, 3 ``d`` MK3MAG, 5 ``f`` BL-Ctrl.
- cmd: one ASCII letter, lowercase = request, uppercase = reply.
- payload: bytes ``a b c`` (zero-padded to a multiple of 3) become four chars
  ``'=' + (a >> 2)``, ``'=' + ((a & 3) << 4 | b >> 4)``, ``'=' + ((b & 15) << 2 | c >> 6)``,
  ``'=' + (c & 63)``; every payload char lies in ``'='..'|'`` (61..124), so ``#`` and ``\\r``
  never appear inside a frame. There is no length field: a decoded payload is padded to a
  multiple of 3 and the receiver truncates it to the struct size it expects.
- checksum: ``s = sum(bytes from '#' to the last payload char) % 4096``,
  ``CRC1 = '=' + s // 64``, ``CRC2 = '=' + s % 64``.
- Frames longer than 220 chars are dropped by the firmware (largest payload 159 bytes).
- Line: 57600 baud 8N1, no flow control; open the tty raw (ICRNL would turn ``\\r`` into ``\\n``).
  Integers inside payloads are little-endian (AVR structs).

The stock protocol cannot carry a 500 Hz IMU stream nor per-motor commands in flight; it is
spoken only to identify and bench-test boards that do not run the tk3 firmware.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

__all__ = ["MAX_FRAME_CHARS", "Address", "StockFrame", "StockParser", "StockParserStats",
           "decode64", "encode64", "encode_frame"]

START = 0x23  # '#'
END = 0x0D  # '\r'
BASE = 0x3D  # '='
TOP = 0x7C  # '|'
MAX_FRAME_CHARS = 220


class Address(IntEnum):
    """Board addresses (the frame carries ``'a' + address``)."""

    ANY = 0
    FLIGHT_CTRL = 1
    NAVI_CTRL = 2
    MK3MAG = 3
    BL_CTRL = 5


@dataclass(frozen=True, slots=True)
class StockFrame:
    """One deframed stock message. ``data`` is the decoded payload, padded to 3k bytes."""

    address: int
    cmd: bytes
    data: bytes


def encode64(payload: bytes) -> bytes:
    """The modified base64 of ``payload`` (zero-padded to a multiple of 3 bytes)."""
    padded = payload + bytes(-len(payload) % 3)
    out = bytearray()
    for i in range(0, len(padded), 3):
        a, b, c = padded[i], padded[i + 1], padded[i + 2]
        out += bytes((BASE + (a >> 2), BASE + (((a & 3) << 4) | (b >> 4)),
                      BASE + (((b & 15) << 2) | (c >> 6)), BASE + (c & 63)))
    return bytes(out)


def decode64(chars: bytes) -> bytes:
    """Inverse of :func:`encode64` on whole 4-char groups (3 bytes each, padding included).

    Raises ``ValueError`` for a length that is not a multiple of 4 or a char outside ``=..|``.
    """
    if len(chars) % 4:
        raise ValueError("payload length is not a multiple of 4 chars")
    out = bytearray()
    for i in range(0, len(chars), 4):
        g = chars[i:i + 4]
        if min(g) < BASE or max(g) > TOP:
            raise ValueError("payload char outside '='..'|'")
        a, b, c, d = (x - BASE for x in g)
        out += bytes(((a << 2) | (b >> 4), ((b & 15) << 4) | (c >> 2), ((c & 3) << 6) | d))
    return bytes(out)


def _crc(frame: bytes) -> bytes:
    s = sum(frame) % 4096
    return bytes((BASE + s // 64, BASE + s % 64))


def encode_frame(address: int, cmd: bytes, payload: bytes = b"") -> bytes:
    """A complete stock frame: ``#``, address, command letter, payload, checksum, ``\\r``."""
    if len(cmd) != 1:
        raise ValueError("the command is one byte")
    body = bytes((START, ord("a") + int(address))) + cmd + encode64(payload)
    if len(body) + 3 > MAX_FRAME_CHARS:
        raise ValueError(
            f"payload of {len(payload)} bytes exceeds the {MAX_FRAME_CHARS}-char frame")
    return body + _crc(body) + b"\r"


@dataclass(slots=True)
class StockParserStats:
    messages: int = 0
    garbage_bytes: int = 0
    truncated: int = 0
    """Frames cut short by a new ``#``."""
    oversize: int = 0
    bad_checksum: int = 0
    bad_format: int = 0
    """Too short, payload not whole 4-char groups, or a char outside the alphabet."""

    @property
    def frame_errors(self) -> int:
        return self.truncated + self.oversize + self.bad_checksum + self.bad_format


class StockParser:
    """Incremental stock deframer: ``feed(chunk) -> [StockFrame, ...]``; never raises."""

    def __init__(self) -> None:
        self.stats = StockParserStats()
        self._buf = bytearray()
        self._in_frame = False

    def reset(self) -> None:
        self._buf.clear()
        self._in_frame = False

    def feed(self, data: bytes) -> list[StockFrame]:
        if not isinstance(data, bytes):
            data = bytes(data)
        out: list[StockFrame] = []
        stats = self.stats
        pos, n = 0, len(data)
        while pos < n:
            if not self._in_frame:
                start = data.find(b"#", pos)
                if start < 0:
                    stats.garbage_bytes += n - pos
                    break
                stats.garbage_bytes += start - pos
                self._in_frame = True
                self._buf[:] = b"#"
                pos = start + 1
                continue
            stop_cr = data.find(b"\r", pos)
            stop_hash = data.find(b"#", pos)
            if stop_hash >= 0 and (stop_cr < 0 or stop_hash < stop_cr):
                stats.truncated += 1
                self._in_frame = False
                pos = stop_hash
                continue
            stop = stop_cr if stop_cr >= 0 else n
            self._buf += data[pos:stop]
            pos = stop
            if len(self._buf) + (1 if stop_cr >= 0 else 0) > MAX_FRAME_CHARS:
                stats.oversize += 1
                self._in_frame = False
                if stop_cr >= 0:
                    pos += 1
                continue
            if stop_cr < 0:
                break
            pos += 1
            self._in_frame = False
            frame = self._finish(bytes(self._buf))
            if frame is not None:
                out.append(frame)
        return out

    def _finish(self, raw: bytes) -> StockFrame | None:
        stats = self.stats
        if len(raw) < 5 or (len(raw) - 5) % 4 or raw[1] < ord("a"):
            stats.bad_format += 1
            return None
        if _crc(raw[:-2]) != raw[-2:]:
            stats.bad_checksum += 1
            return None
        try:
            data = decode64(raw[3:-2])
        except ValueError:
            stats.bad_format += 1
            return None
        stats.messages += 1
        return StockFrame(raw[1] - ord("a"), raw[2:3], data)

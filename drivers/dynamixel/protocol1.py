"""Dynamixel Protocol 1.0 packets: a pure codec (no I/O).

Wire format (ROBOTIS e-Manual, Protocol 1.0), both directions, half duplex:

    instruction  FF FF ID LEN INST P1..PN CHK     LEN = N + 2
    status       FF FF ID LEN ERR  P1..PN CHK     LEN = N + 2
    CHK = ~(ID + LEN + INST/ERR + sum(P)) & 0xFF  (the FF FF header is not summed)

ID 0..253, 254 = broadcast (no status reply except BULK_READ). The driver side talks through the
official ``dynamixel-sdk`` (its ``Protocol1PacketHandler`` is codec and transport in one); this
module is what the emulated MX-28T and the tests speak, and what a bus sniffer would use.

``Parser.feed(chunk)`` takes arbitrary chunks (half a packet, three packets, noise), resyncs on
``FF FF`` and returns every complete packet; a packet with a bad checksum is returned with
``checksum_ok=False`` (a servo answers it with the Checksum error bit) and counted.
"""

from __future__ import annotations

from dataclasses import dataclass

HEADER = b"\xff\xff"
MAX_LENGTH = 250
"""Largest LEN byte a receiver accepts (the SDK's own limit)."""


def checksum(body: bytes) -> int:
    """Checksum of ``ID LEN INST/ERR params`` (everything after the header)."""
    return (~sum(body)) & 0xFF


def _frame(dxl_id: int, code: int, params: bytes) -> bytes:
    if not 0 <= dxl_id <= 0xFE:
        raise ValueError(f"Dynamixel ID {dxl_id} outside 0..254")
    if len(params) + 2 > MAX_LENGTH:
        raise ValueError(f"{len(params)} parameter bytes: packet longer than LEN {MAX_LENGTH}")
    body = bytes((dxl_id, len(params) + 2, code & 0xFF)) + params
    return HEADER + body + bytes((checksum(body),))


def encode_instruction(dxl_id: int, instruction: int, params: bytes = b"") -> bytes:
    """An instruction packet, e.g. ``encode_instruction(1, 0x01)`` == ``FF FF 01 02 01 FB``."""
    return _frame(dxl_id, instruction, params)


def encode_status(dxl_id: int, error: int, params: bytes = b"") -> bytes:
    """A status packet; ``error`` is the 7-bit error byte (bit 7 must stay 0)."""
    if not 0 <= error <= 0x7F:
        raise ValueError(f"status error byte {error:#x} outside 0..0x7f")
    return _frame(dxl_id, error, params)


@dataclass(frozen=True, slots=True)
class Packet:
    """One decoded packet. ``code`` is the instruction (instruction packets) or the error byte
    (status packets): the framing is the same, the direction decides."""

    dxl_id: int
    code: int
    params: bytes
    checksum_ok: bool = True


class Parser:
    """Incremental Protocol 1.0 deframer. Counts dropped bytes and checksum errors."""

    def __init__(self) -> None:
        self._buf = bytearray()
        self.dropped_bytes = 0
        self.checksum_errors = 0
        self.packets = 0

    def feed(self, data: bytes) -> list[Packet]:
        self._buf += data
        out: list[Packet] = []
        buf = self._buf
        while True:
            start = buf.find(HEADER)
            if start < 0:
                # Keep a trailing FF: it may be the first half of the next header.
                keep = 1 if buf[-1:] == b"\xff" else 0
                self.dropped_bytes += len(buf) - keep
                del buf[: len(buf) - keep]
                break
            if start:
                self.dropped_bytes += start
                del buf[:start]
            if len(buf) < 4:
                break
            dxl_id, length = buf[2], buf[3]
            if dxl_id == 0xFF or length < 2 or length > MAX_LENGTH:
                # A third FF, or an impossible length: drop one byte and look again.
                self.dropped_bytes += 1
                del buf[:1]
                continue
            total = length + 4
            if len(buf) < total:
                break
            body = bytes(buf[2 : total - 1])
            ok = checksum(body) == buf[total - 1]
            if not ok:
                self.checksum_errors += 1
            out.append(Packet(dxl_id, body[2], body[3:], ok))
            self.packets += 1
            del buf[:total]
        return out

    def reset(self) -> None:
        self.dropped_bytes += len(self._buf)
        self._buf.clear()

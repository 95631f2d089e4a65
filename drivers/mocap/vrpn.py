"""VRPN codec (connection cookie, message framing, tracker Pos_Quat): bytes <-> dataclasses.

Wire protocol (VRPN 07.x; ``protocol-mocap-mavlink.md`` §3; all fields big-endian):

- Connection: TCP to the server (port 3883). Alternatively the client "lobs" a UDP datagram
  ``"<client ip> <tcp port>\\0"`` to server UDP 3883 and the server connects back over TCP.
- Cookie: each side first writes 24 bytes: ``"vrpn: ver. 07.38"``, two spaces, the remote
  log-mode digit (``0``), NUL padding. Only the major version (``07``) has to match.
- Message: a 24-byte header ``int32 length, int32 tv_sec, int32 tv_usec, int32 sender id,
  int32 type id, 4 bytes padding``; ``length`` = 24 + the *unpadded* payload length; the
  payload follows, padded with zeros to a multiple of 8 bytes.
- System messages (negative type id): -1 sender description and -2 type description (the
  header's sender field carries the id being described; payload ``uint32 len`` incl. NUL,
  then the NUL-terminated name), -3 UDP description, -4 log description, -5 disconnect.
  Sender and type ids are allocated by each side; names are what both sides agree on.
- ``vrpn_Tracker Pos_Quat`` payload: int32 sensor, int32 padding, 3 x f64 position,
  4 x f64 quaternion (x, y, z, w). Timestamps are the server clock (no latency field).

Incremental: :class:`VrpnStreamParser` takes whatever ``recv()`` returned.
"""

from __future__ import annotations

import enum
import socket
import struct
from dataclasses import dataclass

COOKIE_MAGIC = b"vrpn: ver. 07.38"
COOKIE_SIZE = 24
HEADER_SIZE = 24
DEFAULT_PORT = 3883
MAX_MESSAGE_BYTES = 1 << 20
POS_QUAT_TYPE = "vrpn_Tracker Pos_Quat"
PING_TYPE = "vrpn_Base ping_message"
PONG_TYPE = "vrpn_Base pong_message"


class SystemType(enum.IntEnum):
    SENDER_DESCRIPTION = -1
    TYPE_DESCRIPTION = -2
    UDP_DESCRIPTION = -3
    LOG_DESCRIPTION = -4
    DISCONNECT = -5


class VrpnDecodeError(ValueError):
    """Bytes that are not VRPN (bad cookie, impossible length, short payload)."""


@dataclass(frozen=True, slots=True)
class VrpnMessage:
    length: int
    tv_sec: int
    tv_usec: int
    sender_id: int
    type_id: int
    payload: bytes

    @property
    def t_s(self) -> float:
        return self.tv_sec + self.tv_usec * 1e-6


@dataclass(frozen=True, slots=True)
class TrackerPose:
    sensor: int
    pos: tuple[float, float, float]
    q_xyzw: tuple[float, float, float, float]


_HDR = struct.Struct(">5i4x")
_DESC_LEN = struct.Struct(">I")
_POS_QUAT = struct.Struct(">i4x3d4d")


def encode_cookie(log_mode: int = 0) -> bytes:
    return (COOKIE_MAGIC + b"  " + str(log_mode).encode()).ljust(COOKIE_SIZE, b"\0")


def check_cookie(data: bytes) -> str:
    """Validate a peer's cookie; returns its version text. Raises VrpnDecodeError."""
    if len(data) < COOKIE_SIZE or not data.startswith(COOKIE_MAGIC[:13]):
        raise VrpnDecodeError(f"not a VRPN 07.x cookie: {data[:COOKIE_SIZE]!r}")
    return data[:16].decode("ascii", errors="replace")


def encode_message(sender_id: int, type_id: int, payload: bytes, t_s: float) -> bytes:
    sec = int(t_s)
    usec = round((t_s - sec) * 1e6)
    if usec >= 1_000_000:
        sec, usec = sec + 1, usec - 1_000_000
    pad = (-len(payload)) % 8
    return _HDR.pack(HEADER_SIZE + len(payload), sec, usec, sender_id, type_id) + payload \
        + b"\0" * pad


def encode_description(kind: SystemType, described_id: int, name: str, t_s: float = 0.0
                       ) -> bytes:
    """Sender (-1) or type (-2) description of ``described_id`` as ``name``."""
    raw = name.encode("utf-8") + b"\0"
    return encode_message(described_id, kind, _DESC_LEN.pack(len(raw)) + raw, t_s)


def decode_description(payload: bytes) -> str:
    if len(payload) < 5:
        raise VrpnDecodeError("description payload too short")
    (n,) = _DESC_LEN.unpack_from(payload, 0)
    if n < 1 or 4 + n > len(payload):
        raise VrpnDecodeError(f"description length {n} does not fit its payload")
    return payload[4:4 + n].split(b"\0", 1)[0].decode("utf-8", errors="replace")


def encode_pos_quat(pose: TrackerPose) -> bytes:
    return _POS_QUAT.pack(pose.sensor, *pose.pos, *pose.q_xyzw)


def decode_pos_quat(payload: bytes) -> TrackerPose:
    if len(payload) < _POS_QUAT.size:
        raise VrpnDecodeError(f"Pos_Quat payload of {len(payload)} bytes (needs 64)")
    s, x, y, z, qx, qy, qz, qw = _POS_QUAT.unpack_from(payload, 0)
    return TrackerPose(s, (x, y, z), (qx, qy, qz, qw))


def encode_lob(client_ip: str, tcp_port: int) -> bytes:
    return f"{client_ip} {tcp_port}".encode("ascii") + b"\0"


def decode_lob(data: bytes) -> tuple[str, int]:
    """UDP connection request -> (client ip, tcp port). Raises VrpnDecodeError."""
    try:
        ip, port_text = data.split(b"\0", 1)[0].decode("ascii").split()
        port = int(port_text)
        socket.inet_aton(ip)
    except (UnicodeDecodeError, ValueError, OSError) as exc:
        raise VrpnDecodeError(f"bad connection request {data[:40]!r}") from exc
    if not 1 <= port <= 65535:
        raise VrpnDecodeError(f"connection request names port {port}")
    return ip, port


class VrpnStreamParser:
    """Incremental parser of one TCP direction: cookie first, then framed messages.

    ``feed(chunk)`` returns the complete messages. An impossible length or a bad cookie
    raises :class:`VrpnDecodeError`: a TCP stream cannot be resynchronised, the caller drops
    the connection.
    """

    def __init__(self, expect_cookie: bool = True) -> None:
        self._buf = bytearray()
        self._need_cookie = expect_cookie
        self.peer_version = ""

    def feed(self, chunk: bytes) -> list[VrpnMessage]:
        self._buf += chunk
        out: list[VrpnMessage] = []
        if self._need_cookie:
            if len(self._buf) < COOKIE_SIZE:
                return out
            self.peer_version = check_cookie(bytes(self._buf[:COOKIE_SIZE]))
            del self._buf[:COOKIE_SIZE]
            self._need_cookie = False
        buf = self._buf
        off = 0
        while len(buf) - off >= HEADER_SIZE:
            length, sec, usec, sender, kind = _HDR.unpack_from(buf, off)
            if length < HEADER_SIZE or length > MAX_MESSAGE_BYTES:
                raise VrpnDecodeError(f"impossible message length {length}")
            payload_len = length - HEADER_SIZE
            total = HEADER_SIZE + payload_len + ((-payload_len) % 8)
            if len(buf) - off < total:
                break
            start = off + HEADER_SIZE
            out.append(VrpnMessage(length, sec, usec, sender, kind,
                                   bytes(buf[start:start + payload_len])))
            off += total
        del buf[:off]
        return out

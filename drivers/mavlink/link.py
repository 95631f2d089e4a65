"""MAVLink link layer: a UDP endpoint chosen by URI and the codec around pymavlink.

URI forms (the same spelling as ``mavutil.mavlink_connection``):

``udpout:HOST:PORT``
    Send to HOST:PORT from an ephemeral local port; replies come back to that port. The usual
    vehicle-side form: the GCS listens (MAVProxy ``--master=udpin:HOST:PORT``, QGroundControl
    on 14550).
``udpin:HOST:PORT``
    Bind HOST:PORT and answer the address that sent the newest accepted frame (with signing
    on, an unsigned datagram cannot redirect the telemetry). Nothing is sent before a peer has
    spoken (counted as ``no_peer_drops``).

Each datagram carries whole MAVLink frames; the codec still parses incrementally and counts
anything that is not a valid frame (bad prefix, CRC, length) as corrupted and drops it.

The codec (:class:`MavlinkCodec`) uses pymavlink's generated MAVLink2 ``common`` dialect
(``pymavlink.dialects.v20.common``, no ``mavutil``: nothing depends on ``MAVLINK20`` or on
mavutil's global state). Outgoing frames are signed when a key is given; incoming frames are
decoded without pymavlink's own signature check and judged by
:class:`~drivers.mavlink.signing.SignatureVerifier` (see there for why).
"""

from __future__ import annotations

import errno as _errno
import select
import socket
from dataclasses import dataclass
from typing import Any

from pymavlink.dialects.v20 import common as mavlink2

from drivers.errors import DeviceOpenError, TransportError, TransportUriError
from drivers.mavlink.signing import SignatureVerifier, signing_timestamp_now

MAX_DATAGRAM = 65_535


@dataclass(frozen=True, slots=True)
class UdpUri:
    mode: str  # "udpout" or "udpin"
    host: str
    port: int

    def __str__(self) -> str:
        return f"{self.mode}:{self.host}:{self.port}"


def parse_mavlink_uri(uri: str) -> UdpUri:
    """``udpout:HOST:PORT`` or ``udpin:HOST:PORT``; :class:`TransportUriError` otherwise."""
    form = "expected udpout:HOST:PORT or udpin:HOST:PORT"
    mode, sep, rest = uri.partition(":")
    host, sep2, port_text = rest.rpartition(":")
    if mode not in ("udpout", "udpin") or not sep or not sep2 or not host:
        raise TransportUriError(uri, form)
    try:
        port = int(port_text)
    except ValueError:
        raise TransportUriError(uri, f"port {port_text!r} is not a number; {form}") from None
    if not 0 <= port <= 65535 or (mode == "udpout" and port == 0):
        raise TransportUriError(uri, f"port {port} out of range; {form}")
    return UdpUri(mode, host, port)


class UdpEndpoint:
    """One UDP socket for a MAVLink link. Not thread-safe: one owner thread."""

    def __init__(self, uri: str) -> None:
        self.uri = parse_mavlink_uri(uri)
        self.name = str(self.uri)
        self.no_peer_drops = 0
        self.send_errors = 0
        try:
            self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        except OSError as exc:
            raise DeviceOpenError(self.name, exc.errno) from None
        try:
            self._sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
            if self.uri.mode == "udpin":
                self._sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                self._sock.bind((self.uri.host, self.uri.port))
                self.peer: tuple[str, int] | None = None
            else:
                self._sock.bind(("0.0.0.0", 0))
                self.peer = (socket.gethostbyname(self.uri.host), self.uri.port)
        except OSError as exc:
            self._sock.close()
            raise DeviceOpenError(self.name, exc.errno, f"cannot bind: {exc.strerror}") from None
        self._sock.setblocking(False)
        self._closed = False

    @property
    def local_address(self) -> tuple[str, int]:
        host, port = self._sock.getsockname()[:2]
        return (str(host), int(port))

    def fileno(self) -> int:
        return self._sock.fileno()

    def wait_readable(self, timeout_s: float) -> bool:
        if self._closed:
            return False
        readable, _, _ = select.select([self._sock], [], [], max(0.0, timeout_s))
        return bool(readable)

    def recv_all(self) -> list[tuple[bytes, tuple[str, int]]]:
        """Every datagram waiting now with its sender (never blocks)."""
        out: list[tuple[bytes, tuple[str, int]]] = []
        while True:
            try:
                data, addr = self._sock.recvfrom(MAX_DATAGRAM)
            except (BlockingIOError, InterruptedError):
                return out
            except ConnectionRefusedError:
                continue  # ICMP port unreachable from an earlier send: no listener yet
            except OSError as exc:
                if self._closed:
                    return out
                raise TransportError(self.name, f"receive failed: {exc.strerror}") from None
            out.append((data, (str(addr[0]), int(addr[1]))))

    def adopt_peer(self, addr: tuple[str, int]) -> None:
        """In ``udpin`` mode, answer ``addr`` from now on. The caller decides who deserves it
        (the bridge: a sender of at least one accepted, i.e. when signing, signed frame)."""
        if self.uri.mode == "udpin":
            self.peer = addr

    def send(self, data: bytes) -> bool:
        """Send one datagram; False (and counted) when there is no peer or the send failed.
        A GCS that is not listening yet is not an error for a telemetry link."""
        if self.peer is None:
            self.no_peer_drops += 1
            return False
        try:
            self._sock.sendto(data, self.peer)
        except OSError as exc:
            if exc.errno not in (_errno.ECONNREFUSED, _errno.EAGAIN, _errno.ENOBUFS):
                raise TransportError(self.name, f"send failed: {exc.strerror}") from None
            self.send_errors += 1
            return False
        return True

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self._sock.close()


class _Capture:
    """The ``file`` pymavlink writes encoded frames to."""

    def __init__(self) -> None:
        self.frames: list[bytes] = []

    def write(self, data: bytes) -> None:
        self.frames.append(bytes(data))


class MavlinkCodec:
    """Encode (and sign) outgoing messages, decode and judge incoming bytes. No I/O.

    ``decode(data)`` returns the messages that may be acted upon; everything else is counted:
    ``corrupted`` (not a valid frame) and, when signing is on, the verifier's counters.
    """

    def __init__(self, sysid: int, compid: int, key: bytes | None = None, link_id: int = 0,
                 allow_unsigned: frozenset[int] = frozenset()) -> None:
        self._capture = _Capture()
        self.tx = mavlink2.MAVLink(self._capture, srcSystem=sysid, srcComponent=compid)
        self._rx = mavlink2.MAVLink(None, srcSystem=sysid, srcComponent=compid)
        self._rx.robust_parsing = True
        self.verifier: SignatureVerifier | None = None
        if key is not None:
            self.verifier = SignatureVerifier(key, allow_unsigned)
            self.tx.signing.secret_key = key
            self.tx.signing.sign_outgoing = True
            self.tx.signing.link_id = link_id
            self.tx.signing.timestamp = signing_timestamp_now()
        self.corrupted = 0
        self.frames_in = 0

    @property
    def signing(self) -> bool:
        return self.verifier is not None

    def encode(self, msg: Any) -> bytes:
        """One frame for ``msg`` (a pymavlink message object), signed when signing is on."""
        if self.verifier is not None:
            # Outgoing timestamps never fall behind wall time nor behind what peers sent.
            sig = self.tx.signing
            sig.timestamp = max(sig.timestamp, signing_timestamp_now(),
                                self.verifier.newest_timestamp + 1)
        self.tx.send(msg)
        return self._capture.frames.pop()

    def decode(self, data: bytes) -> list[Any]:
        try:
            msgs = self._rx.parse_buffer(data) or []
        except (mavlink2.MAVError, IndexError, ValueError, UnicodeDecodeError):
            # robust parsing already turns bad frames into bad_data; this catches the rest
            self.corrupted += 1
            self._rx.buf = bytearray()
            self._rx.buf_index = 0
            return []
        out: list[Any] = []
        for msg in msgs:
            if msg.get_type() == "BAD_DATA":
                self.corrupted += 1
                continue
            self.frames_in += 1
            if self.verifier is not None and not self.verifier.accept(
                    msg.get_msgbuf(), msg.get_msgId()):
                continue
            out.append(msg)
        return out

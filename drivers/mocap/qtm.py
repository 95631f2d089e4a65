"""Qualisys QTM RT codec (protocol 1.2x, little-endian port): bytes <-> frozen dataclasses. No I/O.

Wire protocol (``protocol-mocap-mavlink.md`` §3a; Qualisys' RT protocol documentation):

- Transport: TCP to QTM, port 22223 (little-endian; QTM's other base ports serve big-endian
  and legacy clients). Data frames may instead be streamed over UDP to a client port
  (``StreamFrames ... UDP:PORT``), one data packet per datagram, same layout. Discovery is a
  UDP broadcast to 22226 (not used: the client always names the host).
- Packet: ``uint32 size`` (including this 8-byte header), ``uint32 type``, body. Types:
  0 error, 1 command, 2 XML, 3 data, 4 no more data, 5 C3D file, 6 event, 7 discover,
  8 QTM file. Command, XML and error bodies are ASCII text terminated by one NUL; an event body
  is one byte (:class:`Event`: 1 connected, 3 capture started, 8 RT from file started, 12 QTM
  shutting down, ...).
- Session: QTM greets with the command ``QTM RT Interface connected``; the client sends
  ``Version 1.25`` (answered ``Version set to 1.25``), then commands such as ``GetState``
  (answered by an event packet), ``GetParameters 6D`` (an XML packet: ``<The_6D><Bodies>N
  </Bodies><Body><Name>...</Name>...</Body>...``; the body order is the index order in data
  frames), ``StreamFrames AllFrames|Frequency:N|FrequencyDivisor:N [UDP[:ADDR]:PORT]
  6D|6DRes|6DEuler|6DEulerRes`` (no answer on success: data packets follow),
  ``StreamFrames Stop`` and ``GetCurrentFrame COMPONENTS`` (one data packet). Commands are
  case-insensitive. A refused command is answered by an error packet.
- Data packet body: ``int64 timestamp`` (µs, capture time on QTM's clock), ``uint32 frame
  number``, ``uint32 component count``; per component ``uint32 size`` (including this 8-byte
  header), ``uint32 type`` (:class:`ComponentType`: 5 6D, 6 6D Euler, 11 6D residual, 12 6D
  Euler residual, others skipped by their size), then for the 6D family ``int32 body count,
  int16 2D drop rate, int16 2D out-of-sync rate`` and per body ``float32 x, y, z`` (mm) and
  either ``float32 rot[9]`` (6D: the 3x3 rotation matrix body -> QTM global, column by column:
  r11 r21 r31 r12 r22 r32 r13 r23 r33) or ``float32 a1, a2, a3`` (6D Euler: degrees, QTM's
  default "Qualisys standard" convention roll about x, pitch about y', yaw about z'', i.e.
  R = Rx(a1) Ry(a2) Rz(a3)); the residual variants append ``float32 residual`` (mm). A body
  that is not tracked has NaN position and rotation.

Positions are QTM's global frame: Z-up, millimetres (see :mod:`drivers.mocap.frames`). Decoders
raise :class:`QtmDecodeError` (a ValueError) for anything truncated, oversize or inconsistent;
they never raise anything else for any input.
"""

from __future__ import annotations

import enum
import math
import struct
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from dataclasses import dataclass

Vec3 = tuple[float, float, float]
RotMatrix = tuple[float, float, float, float, float, float, float, float, float]  # column-major

DEFAULT_PORT = 22223
DISCOVERY_PORT = 22226
PROTOCOL_VERSION = "1.25"  # what the client asks for (the SDK's default too)
WELCOME = "QTM RT Interface connected"
HEADER_SIZE = 8
MAX_PACKET_BYTES = 1 << 22  # far above any 6D frame or parameter XML; anything larger is junk


class PacketType(enum.IntEnum):
    ERROR = 0
    COMMAND = 1
    XML = 2
    DATA = 3
    NO_MORE_DATA = 4
    C3D_FILE = 5
    EVENT = 6
    DISCOVER = 7
    QTM_FILE = 8
    NONE = 9


class Event(enum.IntEnum):
    CONNECTED = 1
    CONNECTION_CLOSED = 2
    CAPTURE_STARTED = 3
    CAPTURE_STOPPED = 4
    CAPTURE_FETCHING_FINISHED = 5
    CALIBRATION_STARTED = 6
    CALIBRATION_STOPPED = 7
    RT_FROM_FILE_STARTED = 8
    RT_FROM_FILE_STOPPED = 9
    WAITING_FOR_TRIGGER = 10
    CAMERA_SETTINGS_CHANGED = 11
    QTM_SHUTTING_DOWN = 12
    CAPTURE_SAVED = 13
    REPROCESSING_STARTED = 14
    REPROCESSING_STOPPED = 15
    TRIGGER = 16


class ComponentType(enum.IntEnum):
    C3D = 1
    C3D_NO_LABELS = 2
    ANALOG = 3
    FORCE = 4
    C6D = 5
    C6D_EULER = 6
    C2D = 7
    C2D_LIN = 8
    C3D_RES = 9
    C3D_NO_LABELS_RES = 10
    C6D_RES = 11
    C6D_EULER_RES = 12
    ANALOG_SINGLE = 13
    IMAGE = 14
    FORCE_SINGLE = 15
    GAZE_VECTOR = 16
    TIMECODE = 17
    SKELETON = 18
    EYE_TRACKER = 19


#: The 6D family: component name in commands -> (type, carries a matrix, carries a residual).
SIX_DOF_COMPONENTS: dict[str, tuple[ComponentType, bool, bool]] = {
    "6d": (ComponentType.C6D, True, False),
    "6dres": (ComponentType.C6D_RES, True, True),
    "6deuler": (ComponentType.C6D_EULER, False, False),
    "6deulerres": (ComponentType.C6D_EULER_RES, False, True),
}
_BY_TYPE = {kind: (name, matrix, res) for name, (kind, matrix, res) in SIX_DOF_COMPONENTS.items()}


class QtmDecodeError(ValueError):
    """Bytes that are not QTM RT (impossible size, truncated or inconsistent body, bad XML)."""


@dataclass(frozen=True, slots=True)
class Packet:
    kind: int  # a PacketType value (unknown types are passed on, not refused)
    body: bytes


@dataclass(frozen=True, slots=True)
class SixDofBody:
    """One rigid body in a 6D-family component; QTM global frame, mm. NaN when not tracked."""

    pos_mm: Vec3
    rot: RotMatrix | None  # 6D, 6DRes: body -> global, column-major
    euler_deg: Vec3 | None  # 6DEuler, 6DEulerRes: (a1, a2, a3), R = Rx(a1) Ry(a2) Rz(a3)
    residual_mm: float = math.nan

    @property
    def tracked(self) -> bool:
        return not any(math.isnan(c) for c in self.pos_mm)


@dataclass(frozen=True, slots=True)
class SixDofComponent:
    kind: ComponentType
    drop_rate_2d: int
    out_of_sync_rate_2d: int
    bodies: tuple[SixDofBody, ...]


@dataclass(frozen=True, slots=True)
class DataFrame:
    timestamp_us: int  # capture time, QTM's clock
    frame_number: int
    components: tuple[SixDofComponent, ...]  # the 6D family, in packet order
    other_components: tuple[int, ...] = ()  # types of the components skipped

    def six_dof(self) -> SixDofComponent | None:
        """The first 6D-family component, if any."""
        return self.components[0] if self.components else None


_HDR = struct.Struct("<II")
_DATA_HDR = struct.Struct("<qII")
_COMP_HDR = struct.Struct("<II")
_6D_HDR = struct.Struct("<ihh")
_POS = struct.Struct("<3f")
_ROT = struct.Struct("<9f")
_F32 = struct.Struct("<f")


# ---------------------------------------------------------------------------- framing


def encode_packet(kind: int, body: bytes) -> bytes:
    return _HDR.pack(HEADER_SIZE + len(body), kind) + body


def encode_command(text: str) -> bytes:
    """Commands are ASCII; body names in them may not be (UTF-8, as QTM's XML)."""
    return encode_packet(PacketType.COMMAND, text.encode("utf-8", errors="replace") + b"\0")


def encode_error(text: str) -> bytes:
    return encode_packet(PacketType.ERROR, text.encode("utf-8", errors="replace") + b"\0")


def encode_xml(text: str) -> bytes:
    return encode_packet(PacketType.XML, text.encode("utf-8") + b"\0")


def encode_event(event: Event) -> bytes:
    return encode_packet(PacketType.EVENT, bytes((int(event),)))


def encode_no_more_data() -> bytes:
    return encode_packet(PacketType.NO_MORE_DATA, b"")


def decode_text(body: bytes) -> str:
    """A command, error or XML body: text up to the first NUL (non-ASCII bytes replaced)."""
    return body.split(b"\0", 1)[0].decode("utf-8", errors="replace")


def decode_event(body: bytes) -> Event:
    if len(body) < 1:
        raise QtmDecodeError("empty event packet")
    try:
        return Event(body[0])
    except ValueError as exc:
        raise QtmDecodeError(f"unknown event {body[0]}") from exc


def decode_packet(datagram: bytes) -> Packet:
    """One whole packet (a UDP datagram). Raises QtmDecodeError."""
    if len(datagram) < HEADER_SIZE:
        raise QtmDecodeError(f"packet of {len(datagram)} bytes is shorter than its header")
    size, kind = _HDR.unpack_from(datagram, 0)
    if size != len(datagram):
        raise QtmDecodeError(f"packet says {size} bytes, datagram has {len(datagram)}")
    return Packet(kind, bytes(datagram[HEADER_SIZE:]))


class QtmStreamParser:
    """Incremental parser of one TCP direction: ``feed(chunk)`` returns the complete packets.

    An impossible size raises :class:`QtmDecodeError`: a TCP stream cannot be resynchronised,
    the caller drops the connection.
    """

    def __init__(self) -> None:
        self._buf = bytearray()

    def feed(self, chunk: bytes) -> list[Packet]:
        buf = self._buf
        buf += chunk
        out: list[Packet] = []
        off = 0
        while len(buf) - off >= HEADER_SIZE:
            size, kind = _HDR.unpack_from(buf, off)
            if size < HEADER_SIZE or size > MAX_PACKET_BYTES:
                del buf[:]
                raise QtmDecodeError(f"impossible packet size {size}")
            if len(buf) - off < size:
                break
            out.append(Packet(kind, bytes(buf[off + HEADER_SIZE:off + size])))
            off += size
        del buf[:off]
        return out


# ---------------------------------------------------------------------------- data frames


def encode_data_frame(frame: DataFrame) -> bytes:
    """A whole data packet (header included) with the frame's 6D-family components."""
    parts = []
    for comp in frame.components:
        _, matrix, residual = _BY_TYPE[comp.kind]
        body = [_6D_HDR.pack(len(comp.bodies), comp.drop_rate_2d, comp.out_of_sync_rate_2d)]
        for b in comp.bodies:
            body.append(_POS.pack(*b.pos_mm))
            if matrix:
                if b.rot is None:
                    raise ValueError(f"{comp.kind.name} needs a rotation matrix per body")
                body.append(_ROT.pack(*b.rot))
            else:
                if b.euler_deg is None:
                    raise ValueError(f"{comp.kind.name} needs Euler angles per body")
                body.append(_POS.pack(*b.euler_deg))
            if residual:
                body.append(_F32.pack(b.residual_mm))
        data = b"".join(body)
        parts.append(_COMP_HDR.pack(_COMP_HDR.size + len(data), comp.kind) + data)
    return encode_packet(PacketType.DATA, _DATA_HDR.pack(
        frame.timestamp_us, frame.frame_number, len(parts)) + b"".join(parts))


def _decode_six_dof(kind: ComponentType, data: bytes) -> SixDofComponent:
    _, matrix, residual = _BY_TYPE[kind]
    if len(data) < _6D_HDR.size:
        raise QtmDecodeError(f"{kind.name} component of {len(data)} bytes")
    count, drop, sync = _6D_HDR.unpack_from(data, 0)
    per_body = _POS.size + (_ROT.size if matrix else _POS.size) + (_F32.size if residual else 0)
    if count < 0 or _6D_HDR.size + count * per_body > len(data):
        raise QtmDecodeError(f"{kind.name} component says {count} bodies in {len(data)} bytes")
    bodies = []
    off = _6D_HDR.size
    for _ in range(count):
        pos = _POS.unpack_from(data, off)
        off += _POS.size
        rot: RotMatrix | None = None
        euler: Vec3 | None = None
        if matrix:
            rot = _ROT.unpack_from(data, off)
            off += _ROT.size
        else:
            euler = _POS.unpack_from(data, off)
            off += _POS.size
        res = math.nan
        if residual:
            (res,) = _F32.unpack_from(data, off)
            off += _F32.size
        bodies.append(SixDofBody(pos, rot, euler, res))
    return SixDofComponent(kind, drop, sync, tuple(bodies))


def decode_data(body: bytes) -> DataFrame:
    """The body of a data packet (after the 8-byte packet header). Raises QtmDecodeError."""
    if len(body) < _DATA_HDR.size:
        raise QtmDecodeError(f"data packet of {len(body)} bytes")
    ts, frame_number, count = _DATA_HDR.unpack_from(body, 0)
    off = _DATA_HDR.size
    comps: list[SixDofComponent] = []
    others: list[int] = []
    for _ in range(count):
        if len(body) - off < _COMP_HDR.size:
            raise QtmDecodeError(f"data packet ends before component {len(comps) + len(others)}")
        size, kind = _COMP_HDR.unpack_from(body, off)
        if size < _COMP_HDR.size or off + size > len(body):
            raise QtmDecodeError(f"component of {size} bytes does not fit the packet")
        data = body[off + _COMP_HDR.size:off + size]
        if kind in _BY_TYPE:
            comps.append(_decode_six_dof(ComponentType(kind), data))
        else:
            others.append(kind)
        off += size
    return DataFrame(ts, frame_number, tuple(comps), tuple(others))


# ---------------------------------------------------------------------------- parameters


def encode_6d_parameters(names: Sequence[str] | None, version: tuple[int, int] = (1, 25),
                         frequency_hz: float | None = None) -> str:
    """The XML answer to ``GetParameters 6D`` (``names`` None: no 6D section) with ``General``
    when ``frequency_hz`` is given.

    Protocol >= 1.21 describes each body with attributes (``<Color R= G= B=/>``, ``<Points>``);
    older versions with child elements (``<RGBColor>``, ``<Point><X>``). Either way the body
    names are ``<Body><Name>`` in index order, and the Euler convention is QTM's default.
    """
    root = ET.Element(f"QTM_Parameters_Ver_{version[0]}.{version[1]:02d}")
    if frequency_hz is not None:
        general = ET.SubElement(root, "General")
        ET.SubElement(general, "Frequency").text = f"{frequency_hz:g}"
        ET.SubElement(general, "Capture_Time").text = "10"
    if names is None:
        return ET.tostring(root, encoding="unicode")
    six = ET.SubElement(root, "The_6D")
    ET.SubElement(six, "Bodies").text = str(len(names))
    for name in names:
        body = ET.SubElement(six, "Body")
        ET.SubElement(body, "Name").text = name
        if version >= (1, 21):
            ET.SubElement(body, "Enabled").text = "true"
            ET.SubElement(body, "Color", R="0", G="255", B="0")
            ET.SubElement(body, "MaximumResidual").text = "10"
            ET.SubElement(body, "MinimumMarkersInBody").text = "3"
            ET.SubElement(body, "BoneLengthTolerance").text = "5"
            ET.SubElement(body, "Filter", Preset="No filter")
            ET.SubElement(body, "Points")
            ET.SubElement(body, "Data_origin").text = "0"
        else:
            ET.SubElement(body, "RGBColor").text = "65280"
    euler = ET.SubElement(six, "Euler")
    for tag, axis in (("First", "X"), ("Second", "Y"), ("Third", "Z")):
        ET.SubElement(euler, tag).text = axis
    return ET.tostring(root, encoding="unicode")


def decode_6d_body_names(xml_text: str) -> tuple[str, ...]:
    """Body names in index order from a ``GetParameters 6D`` answer. Raises QtmDecodeError."""
    try:
        root = ET.fromstring(xml_text)
    except ET.ParseError as exc:
        raise QtmDecodeError(f"parameters are not XML: {exc}") from exc
    six = root.find("The_6D") if root.tag != "The_6D" else root
    if six is None:
        raise QtmDecodeError("parameters hold no The_6D section")
    return tuple((body.findtext("Name") or "").strip() for body in six.findall("Body"))


# ---------------------------------------------------------------------------- rotations


def matrix_to_quat(rot: RotMatrix) -> tuple[float, float, float, float]:
    """Column-major 3x3 rotation matrix -> quaternion (x, y, z, w), not normalised.

    Shepperd's method: the largest of w, x, y, z is computed from the diagonal, the others
    from the off-diagonal sums, which stays accurate for every rotation.
    """
    r11, r21, r31, r12, r22, r32, r13, r23, r33 = rot
    tr = r11 + r22 + r33
    if tr >= max(r11, r22, r33):
        s = 2.0 * math.sqrt(max(0.0, 1.0 + tr))
        return ((r32 - r23) / s, (r13 - r31) / s, (r21 - r12) / s, 0.25 * s)
    if r11 >= r22 and r11 >= r33:
        s = 2.0 * math.sqrt(max(0.0, 1.0 + r11 - r22 - r33))
        return (0.25 * s, (r12 + r21) / s, (r13 + r31) / s, (r32 - r23) / s)
    if r22 >= r33:
        s = 2.0 * math.sqrt(max(0.0, 1.0 + r22 - r11 - r33))
        return ((r12 + r21) / s, 0.25 * s, (r23 + r32) / s, (r13 - r31) / s)
    s = 2.0 * math.sqrt(max(0.0, 1.0 + r33 - r11 - r22))
    return ((r13 + r31) / s, (r23 + r32) / s, 0.25 * s, (r21 - r12) / s)


def quat_to_matrix(q_xyzw: tuple[float, float, float, float]) -> RotMatrix:
    """Unit quaternion (x, y, z, w) -> column-major 3x3 rotation matrix."""
    x, y, z, w = q_xyzw
    return (1 - 2 * (y * y + z * z), 2 * (x * y + w * z), 2 * (x * z - w * y),
            2 * (x * y - w * z), 1 - 2 * (x * x + z * z), 2 * (y * z + w * x),
            2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y))


def euler_to_quat(euler_deg: Vec3) -> tuple[float, float, float, float]:
    """QTM default Euler angles (deg; R = Rx(a1) Ry(a2) Rz(a3)) -> quaternion (x, y, z, w)."""
    h = [math.radians(a) / 2.0 for a in euler_deg]
    cx, sx = math.cos(h[0]), math.sin(h[0])
    cy, sy = math.cos(h[1]), math.sin(h[1])
    cz, sz = math.cos(h[2]), math.sin(h[2])
    # qx ⊗ qy ⊗ qz with qx = (sx, 0, 0, cx), ...
    return (sx * cy * cz + cx * sy * sz, cx * sy * cz - sx * cy * sz,
            cx * cy * sz + sx * sy * cz, cx * cy * cz - sx * sy * sz)


def quat_to_euler(q_xyzw: tuple[float, float, float, float]) -> Vec3:
    """Unit quaternion (x, y, z, w) -> QTM default Euler angles (deg), inverse of
    :func:`euler_to_quat` (a2 in [-90, 90])."""
    r11, r21, _r31, r12, r22, _r32, r13, r23, r33 = quat_to_matrix(q_xyzw)
    # R = Rx Ry Rz: r13 = sin a2, r23 = -sin a1 cos a2, r33 = cos a1 cos a2,
    # r12 = -cos a2 sin a3, r11 = cos a2 cos a3.
    # a2 from its sine and cosine (hypot(r11, r12) = cos a2): asin loses digits near +-90 deg,
    # and a wide gimbal-lock band (|sin a2| > 1 - 1e-9, cos a2 < 4.5e-5) dropped a3 there
    cos_a2 = math.hypot(r11, r12)
    a2 = math.atan2(r13, cos_a2)
    if cos_a2 > 1e-12:
        a1 = math.atan2(-r23, r33)
        a3 = math.atan2(-r12, r11)
    else:  # gimbal lock: only a1 ± a3 is defined; put it all in a1
        a1 = math.atan2(r21 if r13 > 0 else -r21, r22)
        a3 = 0.0
    return (math.degrees(a1), math.degrees(a2), math.degrees(a3))


def parse_stream_command(text: str) -> tuple[str, list[str], int | None, str | None]:
    """``StreamFrames RATE [UDP[:ADDR]:PORT] COMPONENTS...`` (the words after ``StreamFrames``)
    -> (rate word lower-case, component names lower-case, UDP port or None, UDP address or
    None). Raises QtmDecodeError for a missing rate or a bad UDP option."""
    words = text.split()
    if not words:
        raise QtmDecodeError("StreamFrames needs a rate (AllFrames, Frequency:N, ...)")
    rate = words[0].lower()
    port: int | None = None
    addr: str | None = None
    comps: list[str] = []
    for w in words[1:]:
        lw = w.lower()
        if lw.startswith("udp:"):
            fields = w.split(":")
            try:
                port = int(fields[-1])
            except ValueError as exc:
                raise QtmDecodeError(f"bad UDP option {w!r}") from exc
            if not 1 <= port <= 65535 or len(fields) > 3:
                raise QtmDecodeError(f"bad UDP option {w!r}")
            addr = fields[1] if len(fields) == 3 else None
        else:
            comps.append(lw)
    return rate, comps, port, addr

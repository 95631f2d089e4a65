"""OptiTrack NatNet codec (bitstream 3.0, 3.1, 4.0, 4.1): bytes <-> frozen dataclasses. No I/O.

Wire protocol (UDP, all fields little-endian; ``protocol-mocap-mavlink.md`` §2):

- Every datagram: ``uint16 message_id, uint16 payload_length, payload``. IDs: 0 CONNECT,
  1 SERVERINFO, 2 REQUEST, 3 RESPONSE, 4 REQUEST_MODELDEF, 5 MODELDEF, 6 REQUEST_FRAMEOFDATA,
  7 FRAMEOFDATA, 8 MESSAGESTRING, 9 DISCONNECT, 10 KEEPALIVE, 100 UNRECOGNIZED_REQUEST.
- Client -> server command port (1510): CONNECT (payload ``"Ping\\0"``, empty, or the 270-byte
  SDK 4.x form with the requested version at offset 265), KEEPALIVE (unicast: frames go to
  the address that sent it), REQUEST_MODELDEF, REQUEST with a NUL-terminated text command
  (``Bitstream,3.1`` switches the bitstream version; RESPONSE carries int32 0 on success).
- SERVERINFO: ``char name[256]``, u8[4] app version, u8[4] NatNet version, u64
  HighResClockFrequency, u16 data port, u8 is-multicast, u8[4] multicast group (283 bytes with
  the header, NatNet >= 3.0).
- FRAMEOFDATA: int32 frame number; then sections, each an int32 count (4.1: followed by an
  int32 byte count of the section): marker sets (name, int32 n, n x 3 f32), legacy unlabeled
  markers (n x 3 f32), rigid bodies (int32 id, 3 f32 pos, 4 f32 quat x,y,z,w, f32 mean marker
  error, int16 params bit0 = tracking valid), skeletons (int32 id, rigid bodies), assets (4.1
  only), labeled markers (int32 id, 3 f32, f32 size, int16 params, f32 residual), force plates,
  devices (int32 id, int32 channels, per channel int32 n + n f32). Suffix: u32 timecode, u32
  subframe, f64 timestamp (s since server start), u64 CameraMidExposure, DataReceived and
  Transmit stamps (ticks of HighResClockFrequency), u32 + u32 precision timestamp (4.1; some
  4.0 servers too, told apart by the remaining length), int16 params (bit0 recording, bit1
  models changed), optional int32 end-of-data tag 0.
- MODELDEF: int32 dataset count; per dataset int32 type (4.1: + int32 byte size). Marker set
  (0): name, int32 n, n names. Rigid body (1): name, int32 id, int32 parent id, 3 f32 offset,
  int32 n markers, n x 3 f32 positions, n int32 active labels, (4.0+) n names. Skeleton (2):
  name, int32 id, int32 n, n rigid-body descriptions.

Positions are in the server's units and axes (metres, Motive Y-up by default); see
:mod:`drivers.mocap.frames` for the conversion into the ground-station world frame.
Decoders raise :class:`NatNetDecodeError` (a ValueError) for anything truncated, oversize or
inconsistent; they never raise anything else for any input.
"""

from __future__ import annotations

import enum
import socket
import struct
from dataclasses import dataclass, field

Vec3 = tuple[float, float, float]
QuatXyzw = tuple[float, float, float, float]
NatNetVersion = tuple[int, int]

SUPPORTED_VERSIONS: tuple[NatNetVersion, ...] = ((3, 0), (3, 1), (4, 0), (4, 1))
DEFAULT_COMMAND_PORT = 1510
DEFAULT_DATA_PORT = 1511
DEFAULT_MULTICAST_GROUP = "239.255.42.99"
MAX_PACKET_BYTES = 65503  # largest UDP payload over IPv4 + our 4-byte header limit


class MessageId(enum.IntEnum):
    CONNECT = 0
    SERVERINFO = 1
    REQUEST = 2
    RESPONSE = 3
    REQUEST_MODELDEF = 4
    MODELDEF = 5
    REQUEST_FRAMEOFDATA = 6
    FRAMEOFDATA = 7
    MESSAGESTRING = 8
    DISCONNECT = 9
    KEEPALIVE = 10
    UNRECOGNIZED_REQUEST = 100


class DatasetType(enum.IntEnum):
    MARKER_SET = 0
    RIGID_BODY = 1
    SKELETON = 2


class NatNetDecodeError(ValueError):
    """A NatNet datagram is truncated, oversize or inconsistent."""


# ---------------------------------------------------------------------------- messages


@dataclass(frozen=True, slots=True)
class ServerInfo:
    app_name: str
    app_version: tuple[int, int, int, int]
    natnet_version: tuple[int, int, int, int]
    high_res_clock_hz: int
    data_port: int
    is_multicast: bool
    multicast_group: str

    @property
    def version(self) -> NatNetVersion:
        return (self.natnet_version[0], self.natnet_version[1])


@dataclass(frozen=True, slots=True)
class RigidBodyData:
    body_id: int
    pos: Vec3  # server units and axes
    q_xyzw: QuatXyzw
    mean_error_m: float
    tracking_valid: bool


@dataclass(frozen=True, slots=True)
class LabeledMarker:
    marker_id: int
    pos: Vec3
    size_m: float
    params: int
    residual_m: float

    @property
    def occluded(self) -> bool:
        return bool(self.params & 0x01)


@dataclass(frozen=True, slots=True)
class MarkerSetData:
    name: str
    positions: tuple[Vec3, ...]


@dataclass(frozen=True, slots=True)
class SkeletonData:
    skeleton_id: int
    rigid_bodies: tuple[RigidBodyData, ...]


@dataclass(frozen=True, slots=True)
class FrameOfData:
    frame_number: int
    rigid_bodies: tuple[RigidBodyData, ...]
    marker_sets: tuple[MarkerSetData, ...] = ()
    unlabeled_markers: tuple[Vec3, ...] = ()
    skeletons: tuple[SkeletonData, ...] = ()
    labeled_markers: tuple[LabeledMarker, ...] = ()
    timecode: int = 0
    timecode_sub: int = 0
    timestamp_s: float = 0.0
    camera_mid_exposure_ticks: int = 0
    data_received_ticks: int = 0
    transmit_ticks: int = 0
    precision_timestamp: tuple[int, int] | None = None  # (seconds, fraction) if present
    params: int = 0

    @property
    def recording(self) -> bool:
        return bool(self.params & 0x01)

    @property
    def models_changed(self) -> bool:
        return bool(self.params & 0x02)

    def latency_s(self, high_res_clock_hz: int) -> float:
        """System latency (transmit - mid-exposure) in seconds; 0 if the stamps are absent."""
        if high_res_clock_hz <= 0 or self.transmit_ticks < self.camera_mid_exposure_ticks:
            return 0.0
        return (self.transmit_ticks - self.camera_mid_exposure_ticks) / high_res_clock_hz


@dataclass(frozen=True, slots=True)
class RigidBodyDescription:
    name: str
    body_id: int
    parent_id: int = -1
    offset_m: Vec3 = (0.0, 0.0, 0.0)
    marker_positions: tuple[Vec3, ...] = ()
    marker_labels: tuple[int, ...] = ()
    marker_names: tuple[str, ...] = ()  # 4.0+; empty strings otherwise


@dataclass(frozen=True, slots=True)
class MarkerSetDescription:
    name: str
    marker_names: tuple[str, ...]


@dataclass(frozen=True, slots=True)
class ModelDefinitions:
    rigid_bodies: tuple[RigidBodyDescription, ...]
    marker_sets: tuple[MarkerSetDescription, ...] = ()
    skipped_datasets: int = 0  # datasets of other types (skeleton parts, cameras, ...)

    def body_ids_by_name(self) -> dict[str, int]:
        return {rb.name: rb.body_id for rb in self.rigid_bodies}


@dataclass(frozen=True, slots=True)
class Response:
    """RESPONSE to a REQUEST: ``code`` when the payload is one int32, else ``text``."""

    code: int | None
    text: str = ""


@dataclass(frozen=True, slots=True)
class MessageString:
    text: str


@dataclass(frozen=True, slots=True)
class UnrecognizedRequest:
    pass


@dataclass(frozen=True, slots=True)
class ClientRequest:
    """What a client sent to the command port (decoded on the server side)."""

    message_id: MessageId
    text: str = ""  # REQUEST command text; empty otherwise
    requested_version: tuple[int, int, int, int] | None = None  # SDK 4.x CONNECT
    extra: tuple[int, ...] = field(default=())


ServerMessage = (ServerInfo | FrameOfData | ModelDefinitions | Response | MessageString
                 | UnrecognizedRequest)

# ---------------------------------------------------------------------------- structs

_HDR = struct.Struct("<HH")
_I32 = struct.Struct("<i")
_I32X2 = struct.Struct("<ii")
_V3 = struct.Struct("<3f")
_RB = struct.Struct("<i3f4ffh")  # 38 bytes, NatNet >= 3.0
_LM = struct.Struct("<i3ffhf")  # 26 bytes, NatNet >= 3.0
_SUFFIX_TIMES = struct.Struct("<IId3Q")  # 40 bytes
_U32X2 = struct.Struct("<II")
_I16 = struct.Struct("<h")
_SI_TAIL = struct.Struct("<4B4BQHB4B")  # after the 256-byte name
_RB_DESC_HEAD = struct.Struct("<ii3f")  # id, parent id, offset


def _check_version(version: NatNetVersion) -> None:
    if version not in SUPPORTED_VERSIONS:
        raise ValueError(f"unsupported NatNet version {version}; supported: {SUPPORTED_VERSIONS}")


def _cstr(buf: bytes, off: int, end: int) -> tuple[str, int]:
    nul = buf.find(b"\0", off, end)
    if nul < 0:
        raise NatNetDecodeError(f"unterminated string at offset {off}")
    return buf[off:nul].decode("utf-8", errors="replace"), nul + 1


def _count(buf: bytes, off: int, end: int, min_item: int) -> tuple[int, int]:
    if off + 4 > end:
        raise NatNetDecodeError(f"truncated count at offset {off}")
    (n,) = _I32.unpack_from(buf, off)
    if n < 0 or n * min_item > end - off - 4:
        raise NatNetDecodeError(f"implausible count {n} at offset {off}")
    return n, off + 4


def _need(off: int, size: int, end: int) -> None:
    if off + size > end:
        raise NatNetDecodeError(f"truncated at offset {off} (needs {size} bytes)")


# ---------------------------------------------------------------------------- encoding


def _msg(mid: MessageId, payload: bytes) -> bytes:
    if len(payload) > MAX_PACKET_BYTES:
        raise ValueError(f"NatNet payload of {len(payload)} bytes does not fit one datagram")
    return _HDR.pack(mid, len(payload)) + payload


def encode_connect(form: str = "ping", version: tuple[int, int, int, int] = (4, 1, 0, 0)
                   ) -> bytes:
    """CONNECT in one of the three forms servers meet: ``ping``, ``empty`` or ``sdk4``."""
    if form == "ping":
        return _msg(MessageId.CONNECT, b"Ping\0")
    if form == "empty":
        return _msg(MessageId.CONNECT, b"")
    if form == "sdk4":
        payload = bytearray(270)
        payload[0:4] = b"Ping"
        payload[265:269] = bytes(version)
        return _msg(MessageId.CONNECT, bytes(payload))
    raise ValueError(f"unknown CONNECT form {form!r}")


def encode_keepalive() -> bytes:
    return _msg(MessageId.KEEPALIVE, b"")


def encode_disconnect() -> bytes:
    return _msg(MessageId.DISCONNECT, b"")


def encode_request_modeldef() -> bytes:
    return _msg(MessageId.REQUEST_MODELDEF, b"")


def encode_command(text: str) -> bytes:
    return _msg(MessageId.REQUEST, text.encode("utf-8") + b"\0")


def encode_response(code: int) -> bytes:
    return _msg(MessageId.RESPONSE, _I32.pack(code))


def encode_unrecognized() -> bytes:
    return _msg(MessageId.UNRECOGNIZED_REQUEST, b"")


def encode_server_info(info: ServerInfo) -> bytes:
    name = info.app_name.encode("utf-8")[:255].ljust(256, b"\0")
    group = socket.inet_aton(info.multicast_group)
    payload = name + _SI_TAIL.pack(*info.app_version, *info.natnet_version,
                                   info.high_res_clock_hz, info.data_port,
                                   1 if info.is_multicast else 0, *group)
    return _msg(MessageId.SERVERINFO, payload)


def _section(version: NatNetVersion, count: int, body: bytes) -> bytes:
    if version >= (4, 1):
        return _I32X2.pack(count, len(body)) + body
    return _I32.pack(count) + body


def _encode_rb(rb: RigidBodyData) -> bytes:
    return _RB.pack(rb.body_id, *rb.pos, *rb.q_xyzw, rb.mean_error_m,
                    1 if rb.tracking_valid else 0)


def encode_frame(frame: FrameOfData, version: NatNetVersion) -> bytes:
    """FRAMEOFDATA for the given bitstream version (3.0, 3.1, 4.0, 4.1)."""
    _check_version(version)
    parts = [_I32.pack(frame.frame_number)]
    ms = b"".join(m.name.encode("utf-8") + b"\0" + _I32.pack(len(m.positions))
                  + b"".join(_V3.pack(*p) for p in m.positions) for m in frame.marker_sets)
    parts.append(_section(version, len(frame.marker_sets), ms))
    parts.append(_section(version, len(frame.unlabeled_markers),
                          b"".join(_V3.pack(*p) for p in frame.unlabeled_markers)))
    parts.append(_section(version, len(frame.rigid_bodies),
                          b"".join(_encode_rb(rb) for rb in frame.rigid_bodies)))
    sk = b"".join(_I32X2.pack(s.skeleton_id, len(s.rigid_bodies))
                  + b"".join(_encode_rb(rb) for rb in s.rigid_bodies) for s in frame.skeletons)
    parts.append(_section(version, len(frame.skeletons), sk))
    if version >= (4, 1):
        parts.append(_section(version, 0, b""))  # assets
    parts.append(_section(version, len(frame.labeled_markers), b"".join(
        _LM.pack(m.marker_id, *m.pos, m.size_m, m.params, m.residual_m)
        for m in frame.labeled_markers)))
    parts.append(_section(version, 0, b""))  # force plates
    parts.append(_section(version, 0, b""))  # devices
    parts.append(_SUFFIX_TIMES.pack(frame.timecode, frame.timecode_sub, frame.timestamp_s,
                                    frame.camera_mid_exposure_ticks, frame.data_received_ticks,
                                    frame.transmit_ticks))
    if version >= (4, 1):
        parts.append(_U32X2.pack(*(frame.precision_timestamp or (0, 0))))
    parts.append(_I16.pack(frame.params))
    parts.append(_I32.pack(0))  # end-of-data tag
    return _msg(MessageId.FRAMEOFDATA, b"".join(parts))


def _encode_rb_desc(rb: RigidBodyDescription, version: NatNetVersion) -> bytes:
    n = len(rb.marker_positions)
    out = [rb.name.encode("utf-8") + b"\0",
           _RB_DESC_HEAD.pack(rb.body_id, rb.parent_id, *rb.offset_m), _I32.pack(n)]
    out += [_V3.pack(*p) for p in rb.marker_positions]
    labels = rb.marker_labels or tuple(0 for _ in range(n))
    out += [_I32.pack(lab) for lab in labels]
    if version >= (4, 0):
        names = rb.marker_names or tuple("" for _ in range(n))
        out += [nm.encode("utf-8") + b"\0" for nm in names]
    return b"".join(out)


def encode_modeldef(defs: ModelDefinitions, version: NatNetVersion) -> bytes:
    """MODELDEF with the marker sets and rigid bodies of ``defs``."""
    _check_version(version)
    datasets: list[tuple[DatasetType, bytes]] = []
    for ms in defs.marker_sets:
        datasets.append((DatasetType.MARKER_SET, ms.name.encode("utf-8") + b"\0"
                         + _I32.pack(len(ms.marker_names))
                         + b"".join(n.encode("utf-8") + b"\0" for n in ms.marker_names)))
    for rb in defs.rigid_bodies:
        datasets.append((DatasetType.RIGID_BODY, _encode_rb_desc(rb, version)))
    parts = [_I32.pack(len(datasets))]
    for kind, body in datasets:
        parts.append(_I32X2.pack(kind, len(body)) if version >= (4, 1) else _I32.pack(kind))
        parts.append(body)
    return _msg(MessageId.MODELDEF, b"".join(parts))


# ---------------------------------------------------------------------------- decoding


def _payload(data: bytes) -> tuple[int, int]:
    """Validate the header; return (message id, payload end)."""
    if len(data) < 4:
        raise NatNetDecodeError(f"datagram of {len(data)} bytes is shorter than the header")
    mid, length = _HDR.unpack_from(data, 0)
    if length != len(data) - 4:
        raise NatNetDecodeError(f"header says {length} payload bytes, datagram has "
                                f"{len(data) - 4}")
    return mid, len(data)


def _read_rbs(data: bytes, off: int, end: int, n: int) -> tuple[tuple[RigidBodyData, ...], int]:
    _need(off, n * 38, end)
    rbs = tuple(RigidBodyData(bid, (px, py, pz), (qx, qy, qz, qw), err, bool(params & 1))
                for bid, px, py, pz, qx, qy, qz, qw, err, params
                in _RB.iter_unpack(data[off:off + 38 * n]))
    return rbs, off + 38 * n


def _sec(data: bytes, off: int, end: int, version: NatNetVersion, min_item: int
         ) -> tuple[int, int, int]:
    """Section header -> (count, offset of the first item, declared end or -1)."""
    n, off = _count(data, off, end, min_item)
    if version >= (4, 1):
        _need(off, 4, end)
        (size,) = _I32.unpack_from(data, off)
        off += 4
        if size < 0 or off + size > end:
            raise NatNetDecodeError(f"section byte count {size} overruns the datagram")
        return n, off, off + size
    return n, off, -1


def _close(off: int, declared_end: int) -> int:
    if declared_end >= 0 and off != declared_end:
        raise NatNetDecodeError(f"section ends at {off}, byte count says {declared_end}")
    return off


def _skip_channels(data: bytes, off: int, end: int, n: int) -> int:
    """Force plates / devices: int32 id, int32 channels, per channel int32 k + k f32."""
    for _ in range(n):
        _need(off, 4, end)
        nch, off = _count(data, off + 4, end, 4)
        for _ in range(nch):
            k, off = _count(data, off, end, 4)
            off += 4 * k
    return off


def decode_frame_payload(data: bytes, off: int, end: int, version: NatNetVersion,
                         markers: bool = True) -> FrameOfData:
    """FRAMEOFDATA payload ``data[off:end]`` for bitstream ``version``.

    ``markers=False``: the marker sets, unlabeled and labeled markers are checked as always
    (every count and length) but not built (empty in the result): what a pose client needs,
    at less than half the cost for a Motive frame of four bodies and their 16 markers.
    """
    _need(off, 4, end)
    (frame_number,) = _I32.unpack_from(data, off)
    off += 4
    # marker sets
    n, off, dend = _sec(data, off, end, version, 5)
    msets = []
    for _ in range(n):
        name, off = _cstr(data, off, end)
        k, off = _count(data, off, end, 12)
        if markers:
            msets.append(MarkerSetData(name, tuple(_V3.iter_unpack(data[off:off + 12 * k]))))
        off += 12 * k
    off = _close(off, dend)
    # legacy unlabeled markers
    n, off, dend = _sec(data, off, end, version, 12)
    unl = tuple(_V3.iter_unpack(data[off:off + 12 * n])) if markers else ()
    off = _close(off + 12 * n, dend)
    # rigid bodies
    n, off, dend = _sec(data, off, end, version, 38)
    rbs, off = _read_rbs(data, off, end, n)
    off = _close(off, dend)
    # skeletons
    n, off, dend = _sec(data, off, end, version, 8)
    skels = []
    for _ in range(n):
        _need(off, 4, end)
        (sid,) = _I32.unpack_from(data, off)
        k, off = _count(data, off + 4, end, 38)
        srbs, off = _read_rbs(data, off, end, k)
        skels.append(SkeletonData(sid, srbs))
    off = _close(off, dend)
    if version >= (4, 1):  # assets: skipped by byte count
        n, off, dend = _sec(data, off, end, version, 12)
        off = dend
    # labeled markers
    n, off, dend = _sec(data, off, end, version, 26)
    _need(off, 26 * n, end)
    lms = tuple(LabeledMarker(mid, (x, y, z), size, params, resid)
                for mid, x, y, z, size, params, resid in _LM.iter_unpack(data[off:off + 26 * n])
                ) if markers else ()
    off = _close(off + 26 * n, dend)
    # force plates, devices
    for _ in range(2):
        n, off, dend = _sec(data, off, end, version, 8)
        off = _close(_skip_channels(data, off, end, n), dend) if dend < 0 else dend
    # suffix
    _need(off, 40, end)
    tc, tcs, ts, t_mid, t_rx, t_tx = _SUFFIX_TIMES.unpack_from(data, off)
    off += 40
    rest = end - off
    precision: tuple[int, int] | None = None
    if rest in (10, 14):
        precision = _U32X2.unpack_from(data, off)
        off += 8
    elif rest not in (2, 6) or version >= (4, 1):
        raise NatNetDecodeError(f"frame suffix has {rest} trailing bytes")
    (params,) = _I16.unpack_from(data, off)
    return FrameOfData(frame_number, rbs, tuple(msets), unl, tuple(skels), lms,
                       tc, tcs, ts, t_mid, t_rx, t_tx, precision, params & 0xFFFF)


def _decode_rb_desc(data: bytes, off: int, end: int, version: NatNetVersion
                    ) -> tuple[RigidBodyDescription, int]:
    name, off = _cstr(data, off, end)
    _need(off, _RB_DESC_HEAD.size, end)
    bid, parent, ox, oy, oz = _RB_DESC_HEAD.unpack_from(data, off)
    n, off = _count(data, off + _RB_DESC_HEAD.size, end, 16)
    pos = tuple(_V3.unpack_from(data, off + 12 * i) for i in range(n))
    off += 12 * n
    _need(off, 4 * n, end)
    labels = tuple(_I32.unpack_from(data, off + 4 * i)[0] for i in range(n))
    off += 4 * n
    names: list[str] = []
    if version >= (4, 0):
        for _ in range(n):
            nm, off = _cstr(data, off, end)
            names.append(nm)
    return RigidBodyDescription(name, bid, parent, (ox, oy, oz), pos, labels,
                                tuple(names)), off


def decode_modeldef_payload(data: bytes, off: int, end: int, version: NatNetVersion
                            ) -> ModelDefinitions:
    n, off = _count(data, off, end, 4)
    rbs: list[RigidBodyDescription] = []
    msets: list[MarkerSetDescription] = []
    skipped = 0
    for index in range(n):
        _need(off, 4, end)
        (kind,) = _I32.unpack_from(data, off)
        off += 4
        dend = -1
        if version >= (4, 1):
            _need(off, 4, end)
            (size,) = _I32.unpack_from(data, off)
            off += 4
            if size < 0 or off + size > end:
                raise NatNetDecodeError(f"dataset size {size} overruns the datagram")
            dend = off + size
        if kind == DatasetType.MARKER_SET:
            name, off = _cstr(data, off, end)
            k, off = _count(data, off, end, 1)
            mnames = []
            for _ in range(k):
                nm, off = _cstr(data, off, end)
                mnames.append(nm)
            msets.append(MarkerSetDescription(name, tuple(mnames)))
        elif kind == DatasetType.RIGID_BODY:
            rb, off = _decode_rb_desc(data, off, end, version)
            rbs.append(rb)
        elif kind == DatasetType.SKELETON:
            _, off = _cstr(data, off, end)
            _need(off, 4, end)
            k, off = _count(data, off + 4, end, 16)
            for _ in range(k):
                _, off = _decode_rb_desc(data, off, end, version)
            skipped += 1
        elif dend >= 0:
            skipped += 1
            off = dend
        else:
            # Before 4.1 a dataset of unknown layout cannot be skipped: keep what was read.
            skipped += n - index
            break
        off = _close(off, dend)
    return ModelDefinitions(tuple(rbs), tuple(msets), skipped)


def decode_server_info_payload(data: bytes, off: int, end: int) -> ServerInfo:
    if end - off < 256 + 8:
        raise NatNetDecodeError(f"SERVERINFO of {end - off} bytes is too short")
    name = data[off:off + 256].split(b"\0", 1)[0].decode("utf-8", errors="replace")
    off += 256
    if end - off >= _SI_TAIL.size:
        v = _SI_TAIL.unpack_from(data, off)
        group = socket.inet_ntoa(bytes(v[11:15]))
        return ServerInfo(name, (v[0], v[1], v[2], v[3]), (v[4], v[5], v[6], v[7]), v[8],
                          v[9], bool(v[10]), group)
    app = tuple(data[off:off + 4])
    nat = tuple(data[off + 4:off + 8])
    return ServerInfo(name, (app[0], app[1], app[2], app[3]), (nat[0], nat[1], nat[2], nat[3]),
                      0, DEFAULT_DATA_PORT, False, DEFAULT_MULTICAST_GROUP)


def decode_message(data: bytes, version: NatNetVersion | None, markers: bool = True
                   ) -> ServerMessage:
    """Decode one server -> client datagram.

    ``version`` is the bitstream version (from SERVERINFO); None until it is known, in which
    case only SERVERINFO, RESPONSE, MESSAGESTRING and UNRECOGNIZED_REQUEST decode.
    ``markers``: as :func:`decode_frame_payload`.
    Raises :class:`NatNetDecodeError`, and nothing else, for bad input.
    """
    mid, end = _payload(data)
    try:
        if mid == MessageId.SERVERINFO:
            return decode_server_info_payload(data, 4, end)
        if mid == MessageId.RESPONSE:
            if end - 4 == 4:
                return Response(_I32.unpack_from(data, 4)[0])
            return Response(None, data[4:end].split(b"\0", 1)[0].decode("utf-8", "replace"))
        if mid == MessageId.MESSAGESTRING:
            return MessageString(data[4:end].split(b"\0", 1)[0].decode("utf-8", "replace"))
        if mid == MessageId.UNRECOGNIZED_REQUEST:
            return UnrecognizedRequest()
        if version is None:
            raise NatNetDecodeError(f"message {mid} before SERVERINFO")
        if mid == MessageId.FRAMEOFDATA:
            return decode_frame_payload(data, 4, end, version, markers)
        if mid == MessageId.MODELDEF:
            return decode_modeldef_payload(data, 4, end, version)
    except struct.error as exc:  # defensive: every read is length-checked above
        raise NatNetDecodeError(str(exc)) from exc
    raise NatNetDecodeError(f"unexpected message id {mid} from a server")


def decode_request(data: bytes) -> ClientRequest:
    """Decode one client -> server datagram (for emulated servers)."""
    mid, end = _payload(data)
    try:
        kind = MessageId(mid)
    except ValueError as exc:
        raise NatNetDecodeError(f"unknown message id {mid}") from exc
    if kind == MessageId.REQUEST:
        return ClientRequest(kind, data[4:end].split(b"\0", 1)[0].decode("utf-8", "replace"))
    if kind == MessageId.CONNECT:
        req = None
        if end - 4 >= 269 and data[4 + 265] > 0:
            v = data[4 + 265:4 + 269]
            req = (v[0], v[1], v[2], v[3])
        return ClientRequest(kind, requested_version=req)
    if kind in (MessageId.KEEPALIVE, MessageId.REQUEST_MODELDEF,
                MessageId.REQUEST_FRAMEOFDATA, MessageId.DISCONNECT):
        return ClientRequest(kind)
    raise NatNetDecodeError(f"message id {mid} is not a client request")


def parse_version(text: str) -> NatNetVersion:
    """``"4.1"`` -> (4, 1); raises ValueError for an unsupported version."""
    try:
        major, minor = (int(p) for p in text.strip().split(".")[:2])
    except ValueError as exc:
        raise ValueError(f"bad NatNet version {text!r} (expected e.g. 4.1)") from exc
    _check_version((major, minor))
    return (major, minor)

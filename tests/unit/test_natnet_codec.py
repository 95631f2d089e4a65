"""NatNet 3.0-4.1 codec: byte vectors, round trips, an independent parser, hostile bytes."""

from __future__ import annotations

import contextlib
import dataclasses
import struct

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.mocap import natnet
from drivers.mocap.natnet import (
    FrameOfData,
    LabeledMarker,
    MarkerSetData,
    MarkerSetDescription,
    MessageId,
    ModelDefinitions,
    NatNetDecodeError,
    RigidBodyData,
    RigidBodyDescription,
    ServerInfo,
    SkeletonData,
)

VERSIONS = natnet.SUPPORTED_VERSIONS


def _f32(x: float) -> float:
    return struct.unpack("<f", struct.pack("<f", x))[0]


def _rb(body_id: int, valid: bool = True) -> RigidBodyData:
    return RigidBodyData(body_id, (_f32(0.1 * body_id), 1.5, _f32(-0.3)),
                         (0.0, _f32(0.6), 0.0, _f32(0.8)), _f32(0.00025), valid)


def _frame(n_bodies: int = 4) -> FrameOfData:
    return FrameOfData(
        frame_number=123456,
        rigid_bodies=tuple(_rb(i + 1, valid=i != 2) for i in range(n_bodies)),
        marker_sets=(MarkerSetData("hex", ((1.0, 2.0, 3.0), (4.0, 5.0, 6.0))),
                     MarkerSetData("all", ())),
        unlabeled_markers=((0.5, 0.25, 0.125),),
        skeletons=(SkeletonData(9, (_rb(20),)),),
        labeled_markers=(LabeledMarker((1 << 16) | 2, (1.0, 1.0, 1.0), _f32(0.014), 0x05,
                                       _f32(0.0002)),),
        timecode=7, timecode_sub=8, timestamp_s=12.5, camera_mid_exposure_ticks=1_000_000,
        data_received_ticks=1_020_000, transmit_ticks=1_050_000,
        precision_timestamp=(12, 1 << 31), params=0x02)


DEFS = ModelDefinitions(
    rigid_bodies=(RigidBodyDescription("fasthex", 1, -1, (0.0, 0.0, 0.0),
                                       ((0.25, 0.0, 0.0), (0.0, 0.25, 0.0)), (11, 12),
                                       ("m1", "m2")),
                  RigidBodyDescription("pad", 7)),
    marker_sets=(MarkerSetDescription("fasthex", ("m1", "m2")),))


def test_that_a_hand_built_3_1_frame_decodes_to_its_values() -> None:
    # Fixture: NatNet 3.1, one rigid body id 5, nothing else
    payload = (struct.pack("<i", 77)                            # frame number
               + struct.pack("<i", 0) + struct.pack("<i", 0)    # marker sets, unlabeled
               + struct.pack("<i", 1)                           # one rigid body
               + struct.pack("<i3f4ffh", 5, 1.0, 2.0, 3.0, 0.0, 0.0, 0.0, 1.0, 0.001, 1)
               + struct.pack("<i", 0) * 4                       # skeletons, labeled, fp, dev
               + struct.pack("<IIdQQQ", 0, 0, 1.25, 1000, 1500, 3000)
               + struct.pack("<h", 0) + struct.pack("<i", 0))
    wire = struct.pack("<HH", 7, len(payload)) + payload
    # Test
    msg = natnet.decode_message(wire, (3, 1))
    # Assert
    assert isinstance(msg, FrameOfData)
    assert msg.frame_number == 77
    assert msg.rigid_bodies == (RigidBodyData(5, (1.0, 2.0, 3.0), (0.0, 0.0, 0.0, 1.0),
                                              _f32(0.001), True),)
    assert msg.timestamp_s == 1.25
    assert msg.latency_s(1_000_000) == pytest.approx(0.002)
    assert wire == natnet.encode_frame(FrameOfData(77, msg.rigid_bodies, timestamp_s=1.25,
                                                   camera_mid_exposure_ticks=1000,
                                                   data_received_ticks=1500,
                                                   transmit_ticks=3000), (3, 1))


def test_that_4_1_sections_carry_their_byte_counts() -> None:
    wire = natnet.encode_frame(FrameOfData(1, (_rb(1),)), (4, 1))
    # frame number, then marker sets (0, 0 bytes), unlabeled (0, 0), rigid bodies (1, 38)
    assert struct.unpack_from("<iiiiiii", wire, 4) == (1, 0, 0, 0, 0, 1, 38)


def test_that_the_extended_server_info_is_283_bytes_and_round_trips() -> None:
    info = ServerInfo("Motive", (3, 1, 0, 0), (4, 1, 0, 0), 10_000_000, 1511, True,
                      "239.255.42.99")
    wire = natnet.encode_server_info(info)
    assert len(wire) == 283
    assert natnet.decode_message(wire, None) == info


@pytest.mark.parametrize("version", VERSIONS)
def test_that_a_frame_round_trips_in_every_version(version: natnet.NatNetVersion) -> None:
    frame = _frame()
    got = natnet.decode_message(natnet.encode_frame(frame, version), version)
    assert isinstance(got, FrameOfData)
    expected_precision = frame.precision_timestamp if version >= (4, 1) else None
    assert got == FrameOfData(**{**{f: getattr(frame, f) for f in frame.__slots__},
                                 "precision_timestamp": expected_precision})
    assert got.models_changed and not got.recording
    lean = natnet.decode_message(natnet.encode_frame(frame, version), version, markers=False)
    assert lean == dataclasses.replace(got, marker_sets=(), unlabeled_markers=(),
                                       labeled_markers=())


@pytest.mark.parametrize("version", VERSIONS)
def test_that_model_definitions_round_trip_with_marker_names_from_4_0(
        version: natnet.NatNetVersion) -> None:
    got = natnet.decode_message(natnet.encode_modeldef(DEFS, version), version)
    assert isinstance(got, ModelDefinitions)
    assert got.body_ids_by_name() == {"fasthex": 1, "pad": 7}
    assert got.rigid_bodies[0].marker_labels == (11, 12)
    assert got.rigid_bodies[0].marker_names == (("m1", "m2") if version >= (4, 0) else ())
    assert got.marker_sets == DEFS.marker_sets


def test_that_a_4_0_frame_with_a_precision_timestamp_is_accepted() -> None:
    # Some 4.0 servers send the 4.1 precision timestamp: told apart by the length.
    base = natnet.encode_frame(_frame(1), (4, 0))
    body = base[4:-6] + struct.pack("<II", 3, 4) + base[-6:]
    got = natnet.decode_message(struct.pack("<HH", 7, len(body)) + body, (4, 0))
    assert isinstance(got, FrameOfData)
    assert got.precision_timestamp == (3, 4) and got.rigid_bodies == _frame(1).rigid_bodies


@pytest.mark.parametrize("form,requested", [("ping", None), ("empty", None),
                                            ("sdk4", (4, 1, 0, 0))])
def test_that_the_server_side_decodes_all_three_connect_forms(
        form: str, requested: tuple[int, int, int, int] | None) -> None:
    req = natnet.decode_request(natnet.encode_connect(form))
    assert req.message_id == MessageId.CONNECT
    assert req.requested_version == requested


def test_that_a_command_request_carries_its_text() -> None:
    req = natnet.decode_request(natnet.encode_command("Bitstream,3.1"))
    assert (req.message_id, req.text) == (MessageId.REQUEST, "Bitstream,3.1")
    assert natnet.decode_message(natnet.encode_response(0), (4, 1)) == natnet.Response(0)


@pytest.mark.parametrize("markers", [True, False])
@pytest.mark.parametrize("version", VERSIONS)
def test_that_every_truncation_and_any_extra_byte_is_refused(
        version: natnet.NatNetVersion, markers: bool) -> None:
    wire = natnet.encode_frame(_frame(), version)
    for cut in range(len(wire)):
        with pytest.raises(NatNetDecodeError):
            natnet.decode_message(wire[:cut], version, markers)
    with pytest.raises(NatNetDecodeError):
        natnet.decode_message(wire + b"\0", version, markers)


@pytest.mark.parametrize("markers", [True, False])
@pytest.mark.parametrize("version", VERSIONS)
def test_that_a_consistent_header_over_a_cut_payload_is_refused(
        version: natnet.NatNetVersion, markers: bool) -> None:
    # The header is re-forged to match the cut: only the payload parser can notice.
    wire = natnet.encode_frame(_frame(), version)
    for cut in range(4, len(wire) - 2):
        forged = struct.pack("<HH", 7, cut - 4) + wire[4:cut]
        try:
            msg = natnet.decode_message(forged, version, markers)
        except NatNetDecodeError:
            continue
        # A cut inside the trailing end-of-data tag is harmless; anything else is refused.
        assert isinstance(msg, FrameOfData) and cut >= len(wire) - 4


def test_that_the_independent_natnet_parser_reads_our_frames_and_definitions() -> None:
    import natnet as peer  # the test extra installs it: missing is a failure
    from natnet.data_descriptions import DataDescriptions  # type: ignore[import-untyped]
    from natnet.data_frame import DataFrame  # type: ignore[import-untyped]
    from natnet.packet_buffer import PacketBuffer  # type: ignore[import-untyped]
    from natnet.version import Version  # type: ignore[import-untyped]

    assert peer is not None
    frame = _frame()
    for version in VERSIONS:
        wire = natnet.encode_frame(frame, version)
        got = DataFrame.read_from_buffer(PacketBuffer(wire[4:]), Version(*version))
        assert got.prefix.frame_number == frame.frame_number
        assert [(r.id_num, r.pos, r.rot, r.tracking_valid) for r in got.rigid_bodies] == \
            [(r.body_id, r.pos, r.q_xyzw, r.tracking_valid) for r in frame.rigid_bodies]
        assert got.suffix.stamp_transmit == frame.transmit_ticks
        defs = DataDescriptions.read_from_buffer(
            PacketBuffer(natnet.encode_modeldef(DEFS, version)[4:]), Version(*version))
        assert [(d.name, d.id_num) for d in defs.rigid_bodies] == [("fasthex", 1), ("pad", 7)]


@settings(max_examples=400)
@given(data=st.binary(max_size=600), version=st.sampled_from([None, *VERSIONS]))
def test_that_random_datagrams_only_ever_raise_the_decode_error(
        data: bytes, version: natnet.NatNetVersion | None) -> None:
    for wire in (data, struct.pack("<HH", 7, len(data)) + data,
                 struct.pack("<HH", 5, len(data)) + data):
        for markers in (True, False):
            with contextlib.suppress(NatNetDecodeError):
                natnet.decode_message(wire, version, markers)
    with contextlib.suppress(NatNetDecodeError):
        natnet.decode_request(data)


@settings(max_examples=300)
@given(version=st.sampled_from(VERSIONS), pos=st.integers(0, 400), value=st.integers(0, 255))
def test_that_a_corrupted_frame_byte_never_raises_anything_else(
        version: natnet.NatNetVersion, pos: int, value: int) -> None:
    wire = bytearray(natnet.encode_frame(_frame(), version))
    wire[4 + pos % (len(wire) - 4)] = value
    decoded: list[natnet.ServerMessage | None] = []
    for markers in (True, False):
        try:
            decoded.append(natnet.decode_message(bytes(wire), version, markers))
        except NatNetDecodeError:
            decoded.append(None)
    # a pose client's decode (markers not built) accepts exactly the same frames, and reads
    # the same values from them (compared as text: a corrupted float may be a NaN)
    full, lean = decoded
    if isinstance(full, FrameOfData):
        full = dataclasses.replace(full, marker_sets=(), unlabeled_markers=(),
                                   labeled_markers=())
    assert repr(lean) == repr(full)

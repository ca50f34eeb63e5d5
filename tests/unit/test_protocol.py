"""Wire protocol: round trips, validation of every field kind, size caps, typed errors."""

from __future__ import annotations

import math

import cv2
import msgpack
import numpy as np
import pytest
from pydantic import ValidationError

from cpslam import protocol as P
from cpslam.protocol.quant import compress, decompress, is_compressed
from cpslam.protocol.samples import random_poses, sample, samples

ALL = samples(seed=0)
V = P.PROTOCOL_VERSION


def _wire(msg: P.Message) -> dict:
    return msgpack.unpackb(P.encode(msg, zstd_level=0), raw=False)


def _pack(obj: dict) -> bytes:
    return msgpack.packb(obj, use_bin_type=True)


def _fields(msg: P.Message) -> dict:
    """Constructor keyword arguments that rebuild `msg`."""
    return {k: getattr(msg, k) for k in type(msg).model_fields if k not in ("type", "version")}


def _unit(d: int, seed: int = 0) -> np.ndarray:
    v = np.random.default_rng(seed).standard_normal(d).astype(np.float32)
    return v / np.linalg.norm(v)


# --- round trips -----------------------------------------------------------------------------


def test_samples_cover_every_message_type():
    assert sorted(m.type_name() for m in ALL) == sorted(P.MESSAGE_TYPES)


@pytest.mark.parametrize("msg", ALL, ids=lambda m: m.type_name())
def test_round_trip_every_type(msg):
    data = P.encode(msg)
    back = P.decode(data, expected=type(msg))
    assert type(back) is type(msg)
    assert back == msg
    assert hash(back) == hash(msg)
    assert P.encoded_size(msg) == len(data) <= P.max_bytes(msg.type_name())
    if is_compressed(data):
        data = decompress(data, P.max_bytes(msg.type_name()))
    wire = msgpack.unpackb(data, raw=False)
    assert list(wire)[:2] == ["type", "version"]
    assert wire["version"] == P.PROTOCOL_VERSION == 9


def test_decoded_arrays_are_writable_native_copies():
    msg = sample("submap_delta", n_points=10)
    back = P.decode(P.encode(msg))
    assert back.xyz_local.flags.writeable and back.xyz_local.dtype == np.float32
    back.xyz_local[0, 0] = 123.0  # must not touch the message it came from
    assert msg.xyz_local[0, 0] != 123.0


def test_round_trip_20_mb_submap_delta():
    msg = sample("submap_delta", seed=1, n_points=220_000, feature_dim=32)
    data = P.encode(msg, zstd_level=0)
    assert len(data) > 20_000_000
    back = P.decode(data, expected=P.SubmapDelta)
    assert back == msg
    assert back.features.dtype == np.float16 and back.features.shape == (220_000, 32)


def test_equality_is_bitwise_on_arrays():
    msg = sample("frame_poses", n_frames=3)
    other = msg.model_copy(update={"stamps": msg.stamps + 1e-9})
    assert msg != other
    assert msg != sample("ack")


def test_messages_are_frozen():
    msg = sample("ack")
    with pytest.raises(ValidationError):
        msg.seq = 5


def test_every_field_has_a_docstring():
    models = [*P.MESSAGE_TYPES.values(), P.ForeignPoints]
    for cls in models:
        for name, field in cls.model_fields.items():
            if name in ("type",):
                continue
            assert field.description, f"{cls.__name__}.{name} has no docstring"


# --- decode errors ---------------------------------------------------------------------------


@pytest.mark.parametrize(
    "payload, needle",
    [
        (b"", "empty"),
        (b"\x93\x01\x02\x03", "not a msgpack map"),
        (_pack({"version": V, "agent_id": "a", "seq": 1}), "no 'type'"),
        (_pack({"type": "ack", "agent_id": "a", "seq": 1}), "no 'version'"),
        (_pack({"type": "nope", "version": V}), "unknown message type"),
        (_pack({"type": 3, "version": V}), "'type' must be a str"),
        (_pack({"type": "ack", "version": "1"}), "'version' must be an int"),
        (_pack({"type": "ack", "version": V, "agent_id": "a", "seq": 1}) + b"\x00", "after"),
        (_pack({"type": "ack", "version": V, "agent_id": "a", "seq": 1})[:-1], "truncated"),
        (_pack({"type": "ack", "version": V, 5: "x"}), "keys must be str"),
    ],
)
def test_structural_errors(payload, needle):
    with pytest.raises(P.ProtocolError, match=needle):
        P.decode(payload)


@pytest.mark.parametrize("zstd_level", [0, 3])
@pytest.mark.parametrize(("msg_type", "old"), [("submap_delta", 1), ("keyframe", 3),
                                              ("keyframe", 6), ("keyframe_image", 7)])
def test_old_version_is_refused_by_name(zstd_level, msg_type, old):
    wire = _wire(sample(msg_type))
    # 1: float16 features before compression; 3, 6: float descriptors; 7: PNG depth only
    wire["version"] = old
    payload = _pack(wire)
    if zstd_level:
        payload = compress(payload, zstd_level)
    with pytest.raises(P.ProtocolError, match=f"version {old}, this build speaks version "
                                              f"{P.PROTOCOL_VERSION} only") as info:
        P.decode(payload)
    assert info.value.msg_type == msg_type


def test_wrong_expected_type():
    with pytest.raises(P.ProtocolError, match="expected a 'keyframe' message, got 'ack'"):
        P.decode(P.encode(sample("ack")), expected=P.KeyframeMsg)
    got = P.decode(P.encode(sample("ack")), expected=(P.KeyframeMsg, P.Ack))
    assert isinstance(got, P.Ack)


def test_duplicate_keys_are_refused():
    body = b"\x84" + b"".join(
        msgpack.packb(x) for x in ("type", "ack", "version", 1, "seq", 1, "seq", 2)
    )
    with pytest.raises(P.ProtocolError, match="duplicate key 'seq'"):
        P.decode(body)


def test_ext_types_are_refused():
    wire = {"type": "ack", "version": V, "agent_id": msgpack.ExtType(5, b"x"), "seq": 1}
    with pytest.raises(P.ProtocolError, match="extension"):
        P.decode(_pack(wire))


def test_non_bytes_input():
    with pytest.raises(P.ProtocolError, match="expected bytes"):
        P.decode("not bytes")  # type: ignore[arg-type]
    assert P.decode(bytearray(P.encode(sample("ack")))) == sample("ack")
    assert P.decode(memoryview(P.encode(sample("ack")))) == sample("ack")


def test_size_caps_on_decode():
    wire = _wire(sample("control"))
    wire["reason"] = "x" * 20_000  # a field limit would catch it too, but the cap comes first
    with pytest.raises(P.ProtocolError, match="exceeds its cap of 16384"):
        P.decode(_pack(wire))
    with pytest.raises(P.ProtocolError, match="exceeds the largest cap"):
        P.decode(b"\x80" + bytes(P.MAX_MESSAGE_BYTES))


def test_size_cap_on_encode():
    tensors = {"w": np.zeros(4_300_000, np.float32)}  # 17.2 MB > 16 MB
    msg = P.DecoderWeights(agent_id="a", seq=0, group_id="a", round=0, n_samples=1, tensors=tensors)
    with pytest.raises(P.ProtocolError, match="over its cap"):
        P.encode(msg)


def test_encode_refuses_unvalidated_copies_with_a_protocol_error():
    # model_copy(update=...) skips validation; encode must still fail cleanly
    broken = sample("frame_poses", n_frames=2).model_copy(update={"stamps": object()})
    with pytest.raises(P.ProtocolError, match="cannot be serialised"):
        P.encode(broken)
    with pytest.raises(P.ProtocolError, match="expected a protocol message"):
        P.encode({"type": "ack"})  # type: ignore[arg-type]


def test_validation_error_names_field_and_expectation():
    wire = _wire(sample("submap_delta", n_points=5, feature_dim=4))
    wire["features"] = P.array_to_wire(np.zeros((5, 4), np.float32))
    with pytest.raises(P.ProtocolError, match="'features'.*expected dtype float16, got float32"):
        P.decode(_pack(wire))
    wire = _wire(sample("ack"))
    wire["extra"] = 1
    with pytest.raises(P.ProtocolError, match="'extra'"):
        P.decode(_pack(wire))
    wire = _wire(sample("ack"))
    wire["seq"] = -2  # -1 is the floor before any message
    with pytest.raises(P.ProtocolError, match="'seq'"):
        P.decode(_pack(wire))
    wire = _wire(sample("keyframe"))
    wire["seq"] = -1
    with pytest.raises(P.ProtocolError, match="'seq'"):
        P.decode(_pack(wire))
    wire = _wire(sample("ack"))
    wire["received"] = [[5, 6]]  # at or below the floor 10
    with pytest.raises(P.ProtocolError, match="received"):
        P.decode(_pack(wire))


# --- arrays ----------------------------------------------------------------------------------


def test_array_wire_layout_is_little_endian_byte_planes():
    a = np.array([[1, 2, 0x0103]], dtype=">u2")  # big-endian in memory
    wire = P.array_to_wire(a)
    # byte 0 of each element, then byte 1 of each
    assert wire == {"dtype": "uint16", "shape": [1, 3], "data": b"\x01\x02\x03\x00\x00\x01",
                    "filter": "planes"}
    back = P.array_from_wire(wire)
    assert back.dtype == np.uint16 and back.dtype.isnative and back.tolist() == [[1, 2, 0x0103]]
    plain = {"dtype": "uint16", "shape": [3], "data": b"\x01\x00\x02\x00\x03\x01"}
    assert P.array_from_wire(plain).tolist() == [1, 2, 0x0103]  # no filter: plain little-endian


def test_one_d_integers_travel_as_wrapping_differences():
    ids = np.array([5, 7, 8, -2**63, 2**63 - 1], np.int64)  # steps that wrap around
    wire = P.array_to_wire(ids)
    assert wire["filter"] == "delta-planes"
    steps = np.frombuffer(wire["data"], np.uint8).reshape(8, -1).T.copy().view("<i8").ravel()
    assert steps[:3].tolist() == [5, 2, 1]
    back = P.array_from_wire(wire)
    assert back.dtype == np.int64 and back.tolist() == ids.tolist()
    for dtype in ("uint16", "int32"):
        a = np.array([3, 1, np.iinfo(dtype).max, 0, 2], dtype)
        assert P.array_from_wire(P.array_to_wire(a)).tolist() == a.tolist()


def test_filters_shrink_what_zstd_sees():
    rng = np.random.default_rng(0)
    ids = np.sort(rng.choice(100_000, 20_000, replace=False)).astype(np.int64)
    xyz = rng.uniform(-3, 3, (20_000, 3)).astype(np.float32)
    for a, ratio in ((ids, 0.5), (xyz, 0.97)):  # random floats: only sign and exponent repeat
        wire = P.array_to_wire(a)
        plain = a.astype(a.dtype.newbyteorder("<")).tobytes()
        assert len(wire["data"]) == len(plain)
        assert len(compress(wire["data"], 3)) < ratio * len(compress(plain, 3))


@pytest.mark.parametrize(
    "wire, needle",
    [
        ({"dtype": "int8", "shape": [2], "data": b"\x00\x01", "filter": "planes"},
         "wider than a byte"),
        ({"dtype": "float32", "shape": [2], "data": b"\x00" * 8, "filter": "delta-planes"},
         "for integer arrays"),
        ({"dtype": "int32", "shape": [2], "data": b"\x00" * 8, "filter": "zigzag"},
         "filter must be one of"),
        ({"dtype": "int32", "shape": [2], "data": b"\x00" * 7, "filter": "planes"},
         "needs 8 bytes"),
        ({"dtype": "int32", "shape": [2], "data": b"\x00" * 8, "filter": "planes", "x": 1},
         "expected keys"),
    ],
)
def test_array_filter_errors(wire, needle):
    with pytest.raises(P.ProtocolError, match=needle):
        P.array_from_wire(wire)


def test_frame_poses_travel_as_float32():
    msg = sample("frame_poses", n_frames=5)
    assert msg.T_kf_frame.dtype == np.float64
    # what the message holds is already rounded through float32, so it round-trips exactly
    assert np.array_equal(msg.T_kf_frame, msg.T_kf_frame.astype(np.float32).astype(np.float64))
    raw = msgpack.unpackb(P.encode(msg, zstd_level=0), raw=False)["T_kf_frame"]
    assert raw["dtype"] == "float32" and raw["shape"] == [5, 4, 4]
    back = P.decode(P.encode(msg))
    assert back == msg and back.T_kf_frame.dtype == np.float64
    fields = _fields(msg)
    huge = fields["T_kf_frame"].copy()
    huge[0, 0, 3] = 1e39  # finite in float64, not in float32
    with pytest.raises(ValidationError, match="finite"):
        P.FramePoses(**{**fields, "T_kf_frame": huge})
    wire = msgpack.unpackb(P.encode(msg, zstd_level=0), raw=False)
    wire["T_kf_frame"] = P.array_to_wire(msg.T_kf_frame)  # float64 on the wire: refused
    with pytest.raises(P.ProtocolError, match="expected dtype float32"):
        P.decode(msgpack.packb(wire, use_bin_type=True))


def test_positions_travel_in_fixed_point():
    fields = _fields(sample("submap_delta", n_points=4, feature_dim=2))
    xyz = np.array([[0.00026, -0.00024, 1.2345678], [-0.0001, 2.0, -3.0], [0, 0, 0],
                    [2000.0, -2000.0, 0.5]], np.float32)
    msg = P.SubmapDelta(**{**fields, "xyz_local": xyz})
    assert np.abs(msg.xyz_local - xyz).max() <= P.XYZ_STEP_M / 2 + 1e-6
    assert msg.xyz_local[0, 0] == np.float32(P.XYZ_STEP_M) and msg.xyz_local[1, 0] == 0.0
    assert not np.signbit(msg.xyz_local[1, 0])  # no -0.0: it would not survive the wire
    raw = msgpack.unpackb(P.encode(msg, zstd_level=0), raw=False)["xyz_local"]
    assert raw["dtype"] == "int32"
    counts = np.frombuffer(raw["data"], np.uint8).reshape(4, -1).T.copy().view("<i4")
    assert counts.reshape(4, 3)[0].tolist() == [1, 0, 2469]
    back = P.decode(P.encode(msg))
    assert back == msg and back.xyz_local.dtype == np.float32
    with pytest.raises(ValidationError, match="within"):
        P.SubmapDelta(**{**fields, "xyz_local": np.full((4, 3), 3000.0, np.float32)})
    wire = msgpack.unpackb(P.encode(msg, zstd_level=0), raw=False)
    wire["xyz_local"] = P.array_to_wire(np.full((4, 3), 2**30, np.int32))
    with pytest.raises(P.ProtocolError, match="counts must be within"):
        P.decode(msgpack.packb(wire, use_bin_type=True))
    wire["xyz_local"] = P.array_to_wire(np.zeros((4, 3), np.float32))
    with pytest.raises(P.ProtocolError, match="expected dtype int32"):
        P.decode(msgpack.packb(wire, use_bin_type=True))


@pytest.mark.parametrize("dtype", P.DTYPES)
def test_array_round_trip_every_dtype(dtype):
    a = (np.arange(24) % 2).astype(dtype).reshape(2, 3, 4)
    back = P.array_from_wire(P.array_to_wire(a))
    assert back.dtype == a.dtype and np.array_equal(back, a)


@pytest.mark.parametrize(
    "wire, needle",
    [
        ({"dtype": "float32", "shape": [2**31 - 1] * 8, "data": b""}, "needs"),
        ({"dtype": "float32", "shape": [3], "data": b"\x00" * 11}, "needs 12 bytes"),
        ({"dtype": "complex64", "shape": [1], "data": b"\x00" * 8}, "dtype must be one of"),
        ({"dtype": "object", "shape": [1], "data": b"\x00" * 8}, "dtype must be one of"),
        ({"dtype": "uint8", "shape": [-1], "data": b""}, "shape entries"),
        ({"dtype": "uint8", "shape": [True], "data": b"\x00"}, "shape entries"),
        ({"dtype": "uint8", "shape": [1] * 9, "data": b"\x00"}, "at most 8"),
        ({"dtype": "uint8", "shape": 3, "data": b"\x00" * 3}, "shape must be a list"),
        ({"dtype": "uint8", "shape": [1], "data": "x"}, "data must be bin"),
        ({"dtype": "bool", "shape": [2], "data": b"\x01\x02"}, "only bytes 0 and 1"),
        ({"dtype": "uint8", "shape": [1]}, "expected keys"),
        ([1, 2], "expected a map"),
    ],
)
def test_array_from_wire_errors(wire, needle):
    with pytest.raises(P.ProtocolError, match=needle):
        P.array_from_wire(wire)


def test_python_side_casts_that_keep_values():
    fields = _fields(sample("submap_delta", n_points=4, feature_dim=2))
    msg = P.SubmapDelta(**{**fields, "features": fields["features"].astype(np.float64)})
    assert msg.features.dtype == np.float16
    msg = P.SubmapDelta(**{**fields, "anchor_kf_ids": fields["anchor_kf_ids"].astype(np.int64)})
    assert msg.anchor_kf_ids.dtype == np.int32
    with pytest.raises(ValidationError, match="do not fit in int32"):
        P.SubmapDelta(**{**fields, "anchor_kf_ids": np.full(4, 2**40)})
    with pytest.raises(ValidationError, match="expected integer dtype"):
        P.SubmapDelta(**{**fields, "point_ids": fields["point_ids"].astype(np.float64)})
    with pytest.raises(ValidationError, match="must be finite"):
        P.SubmapDelta(**{**fields, "features": np.full((4, 2), 1e6)})  # inf in float16
    with pytest.raises(ValidationError, match=r"expected shape float32 \[N, 3\]"):
        P.SubmapDelta(**{**fields, "xyz_local": np.zeros((4, 2), np.float32)})


def test_point_set_cross_checks():
    fields = _fields(sample("submap_delta", n_points=4, feature_dim=2))
    with pytest.raises(ValidationError, match="colors: has 3 rows"):
        P.SubmapDelta(**{**fields, "colors": fields["colors"][:3]})
    dup = fields["point_ids"].copy()
    dup[1] = dup[0]
    with pytest.raises(ValidationError, match="unique"):
        P.SubmapDelta(**{**fields, "point_ids": dup})
    with pytest.raises(ValidationError, match="both updated and removed"):
        P.SubmapDelta(**{**fields, "removed_ids": fields["point_ids"][:1]})
    with pytest.raises(ValidationError, match=">= 0"):
        P.SubmapDelta(**{**fields, "point_ids": -1 - np.arange(4)})


def test_feature_rows_follow_the_point_rows():
    fields = _fields(sample("submap_delta", n_points=4, feature_dim=2))
    extra = np.array([100, 101], np.int64)
    feats = np.concatenate((fields["features"], np.ones((2, 2), np.float16)))
    msg = P.SubmapDelta(**{**fields, "feature_ids": extra, "features": feats})
    back = P.decode(P.encode(msg), expected=P.SubmapDelta)
    assert back.feature_ids.tolist() == [100, 101]
    np.testing.assert_array_equal(back.feature_values(), fields["features"].astype(np.float32))
    np.testing.assert_array_equal(back.updated_feature_values(), np.ones((2, 2)))
    with pytest.raises(ValidationError, match=r"features: has 4 rows, expected 6"):
        P.SubmapDelta(**{**fields, "feature_ids": extra})
    with pytest.raises(ValidationError, match="cannot also be in point_ids"):
        P.SubmapDelta(**{**fields, "feature_ids": fields["point_ids"][:2], "features": feats})
    with pytest.raises(ValidationError, match="feature_ids: ids must be unique"):
        P.SubmapDelta(**{**fields, "feature_ids": np.array([100, 100]), "features": feats})


def test_a_delta_of_removals_only_decodes_with_int8_features():
    msg = P.SubmapDelta(agent_id="a", seq=1, point_ids=np.zeros(0, np.int64),
                        anchor_kf_ids=np.zeros(0, np.int32), xyz_local=np.zeros((0, 3)),
                        features_int8=np.zeros((0, 32), np.int8),
                        feature_scales=np.zeros(0, np.float32), colors=np.zeros((0, 3), np.uint8),
                        removed_ids=np.array([3, 4]))
    back = P.decode(P.encode(msg), expected=P.SubmapDelta)
    assert back.feature_values().shape == (0, 32) and back.removed_ids.tolist() == [3, 4]


def test_pose_and_descriptor_checks():
    good = dict(agent_id="a", seq=0, kf_id=0, frame_index=0, stamp=0.0, descriptor=_unit(8))
    P.KeyframeMsg(**good, T_world_cam=np.eye(4, dtype=np.float32))  # cast to float64
    skew = np.eye(4)
    skew[0, 1] = 0.1
    with pytest.raises(ValidationError, match="not orthonormal"):
        P.KeyframeMsg(**good, T_world_cam=skew)
    mirror = np.diag([1.0, 1.0, -1.0, 1.0])
    with pytest.raises(ValidationError, match="not orthonormal"):
        P.KeyframeMsg(**good, T_world_cam=mirror)
    bottom = np.eye(4)
    bottom[3, 0] = 1.0
    with pytest.raises(ValidationError, match=r"last row"):
        P.KeyframeMsg(**good, T_world_cam=bottom)
    with pytest.raises(ValidationError, match="all zero"):
        P.KeyframeMsg(**{**good, "descriptor": np.zeros(8, np.int8)}, T_world_cam=np.eye(4))
    with pytest.raises(ValidationError, match="finite"):
        P.KeyframeMsg(**{**good, "descriptor": np.full(8, np.nan)}, T_world_cam=np.eye(4))
    with pytest.raises(ValidationError, match="length"):
        P.KeyframeMsg(**{**good, "descriptor": np.zeros(0, np.int8)}, T_world_cam=np.eye(4))
    with pytest.raises(ValidationError, match="finite"):
        P.KeyframeMsg(**{**good, "stamp": math.nan}, T_world_cam=np.eye(4))
    poses = random_poses(np.random.default_rng(0), 3)
    assert np.allclose(poses[:, :3, :3] @ poses[:, :3, :3].transpose(0, 2, 1), np.eye(3))


def test_descriptor_codes_keep_the_direction():
    """A float descriptor goes as int8 codes (its largest magnitude 127) and comes back as a
    unit vector whose cosines with other descriptors moved by less than 5e-3 (these peaked
    random vectors: 2.3e-3)."""
    rng = np.random.default_rng(3)
    d = np.abs(rng.standard_normal((20, 1536))) ** 2  # non-negative and peaked, like GeM
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    msgs = [P.KeyframeMsg(agent_id="a", seq=0, kf_id=i, frame_index=i, stamp=0.0,
                          T_world_cam=np.eye(4), descriptor=3.0 * x) for i, x in enumerate(d)]
    assert all(m.descriptor.dtype == np.int8 and np.abs(m.descriptor).max() == 127
               for m in msgs)
    back = np.stack([P.decode(P.encode(m), expected=P.KeyframeMsg).unit_descriptor()
                     for m in msgs])
    np.testing.assert_allclose(np.linalg.norm(back, axis=1), 1.0, atol=1e-6)
    assert np.abs(back @ back.T - d @ d.T).max() < 5e-3
    wire = _wire(msgs[0])
    wire["descriptor"]["dtype"] = "float16"  # what version 6 sent
    wire["descriptor"]["data"] = d[0].astype("<f2").tobytes()
    with pytest.raises(P.ProtocolError, match="expected dtype int8"):
        P.decode(_pack(wire))


# --- images ----------------------------------------------------------------------------------


def _image_fields(**over):
    rng = np.random.default_rng(0)
    fields = dict(agent_id="a", kf_id=1, fx=50.0, fy=50.0, cx=31.5, cy=23.5, width=64, height=48)
    fields["rgb"] = rng.integers(0, 256, (48, 64, 3)).astype(np.uint8)
    fields["depth"] = rng.integers(0, 5000, (48, 64)).astype(np.uint16)
    fields.update(over)
    return fields


def test_image_png_is_lossless_and_rgb_in_memory():
    rgb = np.zeros((48, 64, 3), np.uint8)
    rgb[..., 0] = 255  # pure red
    msg = P.KeyframeImage(**_image_fields(rgb=rgb, rgb_codec="png"))
    back = P.decode(P.encode(msg))
    assert back == msg
    raw = _wire(msg)["rgb"]["data"]
    bgr = cv2.imdecode(np.frombuffer(raw, np.uint8), cv2.IMREAD_UNCHANGED)
    assert bgr[0, 0].tolist() == [0, 0, 255]  # OpenCV order on the wire's codec side only


def test_image_jpeg_is_close():
    msg = sample("keyframe_image", width=160, height=120, rgb_codec="jpeg")
    back = P.decode(P.encode(msg))
    assert np.array_equal(back.depth, msg.depth)
    assert np.abs(back.rgb.astype(int) - msg.rgb.astype(int)).mean() < 3.0


def test_depth_metres_conversion():
    depth_m = np.array([[0.0, 1.0, 2.0001], [np.nan, 70.0, -1.0]], np.float32)
    fields = _image_fields(width=3, height=2, rgb=None)
    del fields["depth"]
    msg = P.KeyframeImage.from_metres(depth_m, depth_scale=1000.0, **fields)
    assert msg.depth.tolist() == [[0, 1000, 2000], [0, 0, 0]]
    back = P.decode(P.encode(msg)).depth_metres()
    assert back.dtype == np.float32
    assert np.allclose(back, [[0, 1, 2.0], [0, 0, 0]], atol=5e-4)


@pytest.mark.parametrize(
    "mutate, needle",
    [
        (lambda w: w.update(width=65), "header says 64x48"),
        (lambda w: w["rgb"].update(codec="jpeg"), "differs from rgb_codec"),
        (lambda w: w["depth"].update(data=b"\x89PNG\r\n\x1a\nshort"), "IHDR"),
        (lambda w: w["depth"].update(data=b"GIF89a" + bytes(40)), "neither PNG nor JPEG"),
        (lambda w: w.update(rgb=w["depth"]), "16-bit with 1"),
        (lambda w: w["rgb"].update(extra=1), "codec/data"),
        (lambda w: w.update(width=4096, height=4096), "header says 64x48"),
    ],
)
def test_image_decode_errors(mutate, needle):
    wire = _wire(P.KeyframeImage(**_image_fields(rgb_codec="png", depth_codec="png")))
    mutate(wire)
    with pytest.raises(P.ProtocolError, match=needle):
        P.decode(_pack(wire))


def test_image_corrupt_body_is_a_protocol_error():
    wire = _wire(P.KeyframeImage(**_image_fields(rgb_codec="png", depth_codec="png")))
    data = bytearray(wire["depth"]["data"])
    data[40:-12] = bytes(len(data) - 52)  # keep the header, wipe the compressed stream
    wire["depth"]["data"] = bytes(data)
    with pytest.raises(P.ProtocolError, match="depth"):
        P.decode(_pack(wire))


def test_image_request_needs_something():
    with pytest.raises(ValidationError, match="at least one"):
        P.KeyframeImageRequest(agent_id="a", kf_id=0, want_rgb=False, want_depth=False)


# --- server side -----------------------------------------------------------------------------


def test_server_update_checks():
    msg = sample("server_update", n_points=5, feature_dim=2)
    fields = _fields(msg)
    with pytest.raises(ValidationError, match="must include agent_id"):
        P.ServerUpdate(**{**fields, "group_members": ["agent-1"]})
    with pytest.raises(ValidationError, match="receiving agent"):
        block = msg.foreign[0].model_copy(update={"source_agent_id": "agent-0"})
        P.ServerUpdate(**{**fields, "foreign": [block]})
    with pytest.raises(ValidationError, match="T_group_kf: has 3 poses, kf_ids has 2"):
        P.ServerUpdate(**{**fields, "kf_ids": fields["kf_ids"][:2]})


def test_status_summary_is_json_data():
    msg = P.Status(stamp=1.0, summary={"n": np.int64(3), "t": (1, 2.5), "ok": np.bool_(True)})
    assert msg.summary == {"n": 3, "t": [1, 2.5], "ok": True}
    assert P.decode(P.encode(msg)) == msg
    deep: dict = {}
    node = deep
    for _ in range(20):
        node["x"] = {}
        node = node["x"]
    for bad, needle in ((deep, "deeper"), ({"x": math.inf}, "finite"), ({"s": {1}}, "set")):
        with pytest.raises(ValidationError, match=needle):
            P.Status(stamp=0.0, summary=bad)


def test_tensor_names_and_counts_are_limited():
    ok = dict(agent_id="a", seq=0, group_id="a", round=0, n_samples=1)
    with pytest.raises(ValidationError):
        P.DecoderWeights(**ok, tensors={"bad name!": np.zeros(1, np.float32)})
    with pytest.raises(ValidationError):
        P.DecoderWeights(**ok, tensors={"x" * 200: np.zeros(1, np.float32)})
    with pytest.raises(ValidationError):
        P.DecoderWeights(**ok, tensors={f"t{i}": np.zeros(1, np.float32) for i in range(300)})
    with pytest.raises(ValidationError):
        P.DecoderWeights(**ok, tensors={})


def test_inverse_depth_goes_in_steps_that_grow_as_depth_squared():
    from cpslam.protocol.images import depth_coding, image_to_wire

    rng = np.random.default_rng(0)
    # a slanted wall from 0.3 to 4 m with a sensor's noise (1.5 mm x depth^2)
    wall = np.broadcast_to(np.linspace(0.3, 4.0, 160), (120, 160))
    z = (wall + rng.normal(0.0, 1.5e-3, wall.shape) * wall**2).astype(np.float32)
    z[0, :10], z[1, :10], z[2, :10] = 0.0, np.nan, -1.0  # invalid depths stay invalid
    fields = _image_fields(width=160, height=120, rgb=None)
    del fields["depth"]
    assert depth_coding(0.0) == (1000.0, "linear")
    scale, encoding = depth_coding(1.5)
    assert encoding == "inverse" and scale == pytest.approx(1000 / 1.5)
    inv = P.decode(P.encode(P.KeyframeImage.from_metres(z, scale, encoding, **fields)))
    mm = P.decode(P.encode(P.KeyframeImage.from_metres(z, 1000.0, **fields)))
    assert inv.depth_encoding == "inverse" and mm.depth_encoding == "linear"
    back = inv.depth_metres()
    assert (back[:3, :10] == 0).all()
    ok = np.isfinite(z) & (z > 0)
    zz = z[ok].astype(np.float64)
    step_m = 1.5e-3 * zz**2  # u = scale / z: one unit of u is 1.5 mm x z^2 of depth
    err = np.abs(back[ok] - zz)
    assert (err <= 0.5 * step_m * 1.01 + 1e-6).all()
    assert err[zz < 0.5].max() <= 0.2e-3  # finer than millimetres up close
    assert err[zz > 3.0].max() > 0.5e-3  # coarser than millimetres far away
    for codec in ("png", "zstd-delta"):
        assert len(image_to_wire(inv.depth, "depth", codec)["data"]) < len(
            image_to_wire(mm.depth, "depth", codec)["data"])
    # depths the uint16 range cannot hold are invalid, not clipped: nearer than scale/65535 m
    near = P.KeyframeImage.from_metres(np.full((120, 160), 0.005, np.float32), scale,
                                       encoding, **fields)
    assert (near.depth == 0).all()
    with pytest.raises(ValueError, match="step_mm_per_m2"):
        depth_coding(-1.0)


@pytest.mark.parametrize(("encoding", "scale"), [("linear", 1e-300), ("inverse", 1e300)])
def test_depth_beyond_float32_is_invalid(encoding: str, scale: float) -> None:
    fields = _image_fields(width=3, height=2, rgb=None)
    del fields["depth"]
    msg = P.KeyframeImage(depth=np.array([[0, 1, 7], [65535, 2, 0]], np.uint16),
                          depth_scale=scale, depth_encoding=encoding, **fields)
    back = P.decode(P.encode(msg)).depth_metres()
    assert back.dtype == np.float32 and np.isfinite(back).all() and (back == 0).all()

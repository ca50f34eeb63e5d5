"""Property-based fuzzing of `decode`: whatever the bytes, only ProtocolError comes out.

About 5000 cases in all (500 more in test_protocol_keys). Each property also checks that a
successful decode is a consistent message (it re-encodes and decodes to itself), so lenient
validation cannot hide either.
"""

from __future__ import annotations

import math

import msgpack
import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from cpslam import protocol as P
from cpslam.protocol.quant import is_compressed
from cpslam.protocol.samples import samples

SAMPLES = samples(seed=3)
PLAIN = [P.encode(m, zstd_level=0) for m in SAMPLES]
WIRES = [msgpack.unpackb(p, raw=False) for p in PLAIN]
# truncations and bit flips hit zstd frames too (every sample large enough to be compressed)
PAYLOADS = PLAIN + [p for p in (P.encode(m) for m in SAMPLES) if is_compressed(p)]
FUZZ = settings(max_examples=1000, deadline=None, suppress_health_check=[HealthCheck.too_slow])

# msgpack-representable values, nested a little, including the types we use on the wire
scalars = (
    st.none()
    | st.booleans()
    | st.integers(min_value=-(2**63), max_value=2**64 - 1)
    | st.floats(allow_nan=True, allow_infinity=True)
    | st.text(max_size=12)
    | st.binary(max_size=40)
    | st.sampled_from(["float32", "uint8", "png", "jpeg", "keyframe", "ack", "dtype", "shape",
                       "planes", "delta-planes"])
)
values = st.recursive(
    scalars,
    lambda inner: (
        st.lists(inner, max_size=5)
        | st.dictionaries(
            st.text(max_size=8) | st.sampled_from(["dtype", "shape", "data", "filter"]), inner,
            max_size=5,
        )
    ),
    max_leaves=10,
)


def _decode_or_error(data: bytes) -> None:
    """decode must raise ProtocolError or return a message that round-trips."""
    try:
        msg = P.decode(data)
    except P.ProtocolError:
        return
    assert isinstance(msg, P.Message)
    if isinstance(msg, P.KeyframeImage) and msg.rgb_codec == "jpeg":
        return  # re-encoding a JPEG is lossy by design
    assert P.decode(P.encode(msg)) == msg


@FUZZ
@given(st.binary(max_size=2000))
def test_random_bytes(data):
    _decode_or_error(data)


@FUZZ
@given(st.sampled_from(range(len(PAYLOADS))), st.data())
def test_truncated(index, data):
    payload = PAYLOADS[index]
    cut = data.draw(st.integers(min_value=0, max_value=len(payload) - 1))
    try:
        P.decode(payload[:cut])
    except P.ProtocolError:
        return
    raise AssertionError("a truncated message decoded")


@FUZZ
@given(st.sampled_from(range(len(PAYLOADS))), st.data())
def test_bit_flips(index, data):
    payload = bytearray(PAYLOADS[index])
    for _ in range(data.draw(st.integers(min_value=1, max_value=3))):
        pos = data.draw(st.integers(min_value=0, max_value=len(payload) - 1))
        payload[pos] ^= 1 << data.draw(st.integers(min_value=0, max_value=7))
    _decode_or_error(bytes(payload))


@FUZZ
@given(st.sampled_from(range(len(WIRES))), st.data())
def test_field_mutations(index, data):
    wire = dict(WIRES[index])
    key = data.draw(st.sampled_from(sorted(wire)))
    action = data.draw(st.sampled_from(["replace", "delete", "add", "array"]))
    if action == "replace":
        wire[key] = data.draw(values)
    elif action == "delete":
        del wire[key]
    elif action == "add":
        wire[data.draw(st.text(max_size=10))] = data.draw(values)
    else:  # plausible-looking but hostile array header, with or without a byte filter
        wire[key] = {
            "dtype": data.draw(st.sampled_from([*P.DTYPES, "complex128", "S3"])),
            "shape": data.draw(st.lists(st.integers(min_value=-2, max_value=2**40), max_size=10)),
            "data": data.draw(st.binary(max_size=64)),
        }
        if data.draw(st.booleans()):
            wire[key]["filter"] = data.draw(st.sampled_from([*P.FILTERS, "", "rle"]) | scalars)
    _decode_or_error(msgpack.packb(wire, use_bin_type=True))


@settings(FUZZ, max_examples=500)  # nested value generation is the slow part
@given(st.sampled_from(sorted(P.MESSAGE_TYPES)), st.data())
def test_random_maps_with_valid_header(msg_type, data):
    # keys mostly real field names, so validation gets past "field required"
    names = [f for f in P.MESSAGE_TYPES[msg_type].model_fields if f not in ("type", "version")]
    body = data.draw(
        st.dictionaries(st.sampled_from(names) | st.text(max_size=6), values, max_size=8)
    )
    wire = {"type": msg_type, "version": P.PROTOCOL_VERSION, **body}
    _decode_or_error(msgpack.packb(wire, use_bin_type=True))


@settings(max_examples=300, deadline=None)
@given(
    n=st.integers(min_value=0, max_value=200),
    f=st.integers(min_value=0, max_value=16),
    m=st.integers(min_value=0, max_value=20),
    seed=st.integers(min_value=0, max_value=2**32 - 1),
)
def test_submap_round_trip_random_sizes(n, f, m, seed):
    rng = np.random.default_rng(seed)
    ids = rng.permutation(10 * n + 10)
    msg = P.SubmapDelta(
        agent_id="agent_7",
        seq=int(rng.integers(0, 2**63 - 1)),
        point_ids=ids[:n].astype(np.int64),
        anchor_kf_ids=rng.integers(0, 2**31 - 1, n).astype(np.int32),
        xyz_local=rng.standard_normal((n, 3)).astype(np.float32),
        features=rng.standard_normal((n, f)).astype(np.float16),
        colors=rng.integers(0, 256, (n, 3)).astype(np.uint8),
        removed_ids=ids[n : n + m].astype(np.int64),
    )
    assert P.decode(P.encode(msg), expected=P.SubmapDelta) == msg


@settings(max_examples=300, deadline=None)
@given(
    shapes=st.dictionaries(
        st.from_regex(r"[a-z][a-z0-9_.]{0,20}", fullmatch=True),
        st.lists(st.integers(min_value=0, max_value=6), max_size=4),
        min_size=1,
        max_size=6,
    ),
    seed=st.integers(min_value=0, max_value=2**32 - 1),
)
def test_decoder_round_trip_random_shapes(shapes, seed):
    rng = np.random.default_rng(seed)
    tensors = {
        k: rng.standard_normal(math.prod(s)).astype(np.float32).reshape(s)
        for k, s in shapes.items()
    }
    msg = P.GroupDecoder(group_id="g", round=1, members=["a"], n_samples=3, tensors=tensors)
    back = P.decode(P.encode(msg))
    assert back == msg
    assert {k: v.shape for k, v in back.tensors.items()} == {k: tuple(s) for k, s in shapes.items()}

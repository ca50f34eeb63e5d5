"""The compact link: int8 quantisation and zstd round trips, change thresholds, decoder deltas
on both sides (with a base the server lacks), renders from quantised decoders and features."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import zstandard
from spec_helpers import spec

from cpslam import protocol as P
from cpslam.agent.deltas import DecoderBase, SubmapMirror, encode_features
from cpslam.common.camera import Intrinsics
from cpslam.common.field import NeuralPointMap, render_image
from cpslam.common.trajectory import sensor_seconds
from cpslam.protocol.quant import compress, decompress, dequantise_rows, quantise_rows
from cpslam.protocol.samples import sample
from cpslam.server.bases import DecoderBases
from cpslam.server.registry import Registry
from cpslam.server.traffic import traffic_per_agent

RNG = np.random.default_rng(0)


# --- quantisation and compression ----------------------------------------------------------


@pytest.mark.parametrize("shape", [(), (7,), (50, 32), (4, 3, 5), (3, 0)])
def test_int8_round_trip_error_is_at_most_half_a_step_of_each_row(shape):
    x = (RNG.standard_normal(shape) * RNG.uniform(1e-3, 10.0)).astype(np.float32)
    q, scale = quantise_rows(x)
    assert q.dtype == np.int8 and q.shape == x.shape and np.abs(q.astype(int)).max(initial=0) <= 127
    back = dequantise_rows(q, scale)
    rows = x.reshape(x.shape[0] if x.ndim >= 2 else 1, -1)
    err = np.abs(back - x).reshape(rows.shape)
    peak = np.abs(rows).max(axis=1, initial=0.0)
    # half a step, plus float32 rounding of the product
    assert (err <= peak[:, None] / 254 * (1 + 1e-5) + 1e-12).all()


def test_int8_keeps_zero_rows_exact_and_refuses_non_finite():
    x = np.zeros((3, 4), np.float32)
    x[1] = [1, -2, 3, -4]
    q, scale = quantise_rows(x)
    assert scale[0] == 0 and (dequantise_rows(q, scale)[[0, 2]] == 0).all()
    with pytest.raises(ValueError, match="finite"):
        quantise_rows(np.array([[1.0, np.nan]]))


def test_float16_scales_round_up_so_codes_stay_in_range():
    x = (RNG.standard_normal((500, 32)) * RNG.uniform(1e-6, 100.0, (500, 1))).astype(np.float32)
    x[0] = 0.0
    x[1, 0] = 1e9  # beyond float16 scales: capped, the row clipped
    q, scale = quantise_rows(x, 31, scale_dtype=np.float16)
    assert scale.dtype == np.float16 and np.isfinite(scale).all() and scale[0] == 0
    assert np.abs(q.astype(np.int32)).max() <= 31
    back = dequantise_rows(q, scale)
    err = np.abs(back - x).max(axis=1)[2:]
    peak = np.abs(x).max(axis=1)[2:]
    # half a step of the rounded-up scale (float16 relative spacing 2^-10, subnormals absolute)
    assert (err <= (peak / 62) * (1 + 2**-10) + 2**-25).all()
    assert scale[1] == np.finfo(np.float16).max and q[1, 0] == 31


def test_zstd_round_trip_is_exact_and_shrinks_a_sub_map_delta():
    msg = sample("submap_delta", n_points=2000)
    plain = P.encode(msg, zstd_level=0)
    packed = P.encode(msg)
    assert packed[:4] == b"\x28\xb5\x2f\xfd" and len(packed) < len(plain)
    assert decompress(packed, len(plain)) == plain
    assert P.decode(packed) == msg == P.decode(plain)
    small = P.encode(P.Ack(agent_id="a", seq=1))
    assert small == P.encode(P.Ack(agent_id="a", seq=1), zstd_level=0)  # too small to pack


def test_decompression_is_bounded_before_it_allocates():
    bomb = compress(b"\x00" * 1_000_000, 3)
    assert len(bomb) < 1000
    with pytest.raises(P.ProtocolError, match="declares 1000000 bytes, over the cap of 1000"):
        decompress(bomb, 1000)
    streamed = zstandard.ZstdCompressor(write_content_size=False).compress(b"x" * 5000)
    with pytest.raises(P.ProtocolError, match="does not declare"):
        P.decode(streamed)
    with pytest.raises(P.ProtocolError, match="zstd"):
        P.decode(bomb[:-3])


@pytest.mark.parametrize("levels", [127, 15, 1])
def test_quantisation_with_fewer_levels_is_bounded(levels: int) -> None:
    x = RNG.standard_normal((40, 32)).astype(np.float32)
    q, scale = quantise_rows(x, levels)
    assert q.dtype == np.int8 and np.abs(q.astype(np.int32)).max() == levels
    err = np.abs(dequantise_rows(q, scale) - x).max(axis=1)
    assert (err <= np.abs(x).max(axis=1) / (2 * levels) * (1 + 1e-5)).all()
    with pytest.raises(ValueError, match="levels must be in 1..127"):
        quantise_rows(x, 128)


def test_fewer_feature_bits_make_smaller_sub_map_deltas() -> None:
    feats = RNG.standard_normal((2000, 32)).astype(np.float32)
    sizes, errors = {}, {}
    for bits in (8, 6, 4):
        fields, received = encode_features(feats, "int8", bits)
        msg = P.SubmapDelta(agent_id="a", seq=0, point_ids=np.arange(0),
                            anchor_kf_ids=np.zeros(0, np.int32), xyz_local=np.zeros((0, 3)),
                            colors=np.zeros((0, 3), np.uint8), removed_ids=np.zeros(0, np.int64),
                            feature_ids=np.arange(2000), **fields)
        sizes[bits] = len(P.encode(msg))
        np.testing.assert_array_equal(P.decode(P.encode(msg)).updated_feature_values(), received)
        errors[bits] = float(np.sqrt(np.mean((received - feats) ** 2)))
    # each bit dropped saves about 1/8 of the feature bytes and doubles the rounding error
    assert sizes[8] > sizes[6] * 1.15 > sizes[4] * 1.15 * 1.2
    assert errors[8] < errors[6] / 3 < errors[4] / 9
    with pytest.raises(ValueError, match="feature bits must be in 2..8"):
        encode_features(feats, "int8", 1)


def test_int8_sub_map_delta_validates_and_decodes():
    fields, received = encode_features(RNG.standard_normal((5, 8)), "int8")
    base = {
        "agent_id": "a",
        "seq": 0,
        "point_ids": np.arange(5),
        "anchor_kf_ids": np.zeros(5, np.int32),
        "xyz_local": np.zeros((5, 3)),
        "colors": np.zeros((5, 3), np.uint8),
        "removed_ids": np.zeros(0, np.int64),
    }
    msg = P.decode(P.encode(P.SubmapDelta(**base, **fields)))
    np.testing.assert_array_equal(msg.feature_values(), received)
    assert msg.feature_dim == 8
    with pytest.raises(ValueError, match="exactly one"):
        P.SubmapDelta(**base, **fields, features=np.zeros((5, 8)))
    with pytest.raises(ValueError, match="feature_scales: required"):
        P.SubmapDelta(**base, features_int8=fields["features_int8"])
    with pytest.raises(ValueError, match="feature_scales: has 4 rows"):
        P.SubmapDelta(
            **base,
            features_int8=fields["features_int8"],
            feature_scales=fields["feature_scales"][:4],
        )


# --- what to send ----------------------------------------------------------------------------


def test_threshold_is_relative_to_the_servers_copy():
    mirror = SubmapMirror(4, threshold=0.1, codec="float16")
    ids = np.array([1, 2, 3])
    feats = np.array([[1, 0, 0, 0], [10, 0, 0, 0], [0.01, 0, 0, 0]], np.float32)
    send, gone = mirror.select(ids, feats)
    assert send.all() and gone.size == 0  # all new
    _, received = encode_features(feats[send], "float16")
    mirror.commit(ids, send, received, seq=0)
    # the same absolute change: large for point 1 (scale 1), small for point 2 (scale 10)
    moved = feats + np.array([[0.5, 0, 0, 0]], np.float32)
    moved[2] = feats[2]
    send, gone = mirror.select(np.array([1, 2, 3]), moved)
    assert send.tolist() == [True, False, False]
    # drift below the threshold adds up against the server's copy, not the last local value
    mirror.commit(ids, send, encode_features(moved[send], "float16")[1], seq=1)
    drift = moved.copy()
    drift[1, 0] = 10.6  # 0.6 above the copy's 10 after several small steps
    assert mirror.select(ids, drift)[0].tolist() == [False, False, False]
    drift[1, 0] = 11.2
    assert mirror.select(ids, drift)[0].tolist() == [False, True, False]
    # a point that disappeared is reported once the mirror forgets it
    send, gone = mirror.select(np.array([1, 3]), moved[[0, 2]])
    assert gone.tolist() == [2] and not send.any()


def test_threshold_zero_resends_every_change_that_survives_float16():
    mirror = SubmapMirror(2)
    ids, feats = np.array([4]), np.array([[1.0, 2.0]], np.float32)
    mirror.commit(ids, np.array([True]), encode_features(feats, "float16")[1], seq=0)
    assert not mirror.select(ids, feats + 1e-6)[0].any()  # rounds away in float16
    assert mirror.select(ids, feats + 0.01)[0].all()


def test_known_points_go_as_features_alone_once_their_full_row_is_acknowledged():
    mirror = SubmapMirror(2, threshold=0.1, codec="float16")
    ids, feats = np.array([1, 2]), np.array([[1.0, 0.0], [2.0, 0.0]], np.float32)
    send, _ = mirror.select(ids, feats)
    assert not mirror.feature_only(ids, send, acked_seq=10).any()  # new points: whole
    mirror.commit(ids, send, encode_features(feats, "float16")[1], seq=5)
    # point 3 is new in message 6; points 1 and 2 moved
    ids3 = np.array([1, 2, 3])
    moved = np.array([[2.0, 0.0], [3.0, 0.0], [1.0, 1.0]], np.float32)
    send, _ = mirror.select(ids3, moved)
    assert send.all()
    # before the server acknowledged message 5 every row goes whole; after, 1 and 2 alone
    assert not mirror.feature_only(ids3, send, acked_seq=4).any()
    alone = mirror.feature_only(ids3, send, acked_seq=5)
    assert alone.tolist() == [True, True, False]
    mirror.commit(ids3, send, encode_features(moved, "float16")[1], seq=6, feature_only=alone)
    # a feature-only row keeps the seq of the point's full row; the new point gets its own
    assert mirror.seqs.tolist() == [5, 5, 6]
    np.testing.assert_array_equal(mirror.features, moved)
    # not sent at all: the old copy and seq stay
    mirror.commit(ids3, np.array([False, False, True]), moved[2:] + 1, seq=7)
    assert mirror.seqs.tolist() == [5, 5, 7]
    np.testing.assert_array_equal(mirror.features[:2], moved[:2])


# --- decoder deltas on both sides ------------------------------------------------------------


def _weights(seed: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {
        "l0.weight": rng.standard_normal((64, 32)).astype(np.float32),
        "l0.bias": rng.standard_normal(64).astype(np.float32),
        "gain": np.float32(rng.standard_normal()).reshape(()),
    }


def test_decoder_delta_agent_to_server_round_trip():
    group = _weights(1)
    local = {
        k: v + 0.01 * np.random.default_rng(2).standard_normal(v.shape).astype(np.float32)
        for k, v in group.items()
    }
    agent = DecoderBase()
    assert "tensors_f16" in agent.fields("g", local)  # no base yet: full weights
    agent.set("g", 3, group)
    fields = agent.fields("g", local)
    assert fields["base_round"] == 3 and "tensors_f16" not in fields
    assert "tensors_f16" in agent.fields("other", local)  # base of another group
    msg = P.decode(
        P.encode(
            P.DecoderWeights(agent_id="a", seq=0, group_id="g", round=3, n_samples=5, **fields)
        )
    )
    server = DecoderBases()
    server.add("g", 3, group)
    rebuilt = server.apply("g", 3, msg.values())
    for name, value in local.items():
        step = np.abs(value - group[name]).max() / 254
        np.testing.assert_allclose(rebuilt[name], value, atol=step * 1.01 + 1e-7)
    full = P.DecoderWeights(
        agent_id="a", seq=0, group_id="g", round=3, n_samples=5, **agent.fields("g", local)
    )
    assert (
        len(P.encode(msg, zstd_level=0))
        < len(
            P.encode(
                full.model_copy(
                    update={
                        "tensors": local,
                        "tensors_int8": None,
                        "tensor_scales": None,
                        "base_round": None,
                    }
                ),
                zstd_level=0,
            )
        )
        / 3
    )


def test_full_decoder_weights_travel_as_float16_and_the_own_base_is_what_arrived():
    local = _weights(4)
    agent = DecoderBase(full_every=10)
    fields = agent.fields("a", local)
    msg = P.decode(P.encode(P.DecoderWeights(agent_id="a", seq=0, group_id="a", round=0,
                                             n_samples=5, **fields)))
    assert msg.tensors is None and msg.tensors_f16 is not None
    for name, value in msg.values().items():
        assert value.dtype == np.float32
        np.testing.assert_allclose(value, local[name], rtol=2**-11, atol=1e-7)
    agent.sent(0, fields)
    agent.acked(0)
    # the own base is the float16 copy the server holds, so a later delta rebuilds exactly
    for name, value in msg.values().items():
        np.testing.assert_array_equal(agent.own[name], value)
    # a weight beyond float16's range goes whole at float32 rather than as infinity
    huge = {**local, "gain": np.float32(1e6).reshape(())}
    assert "tensors" in DecoderBase().fields("a", huge)


def test_registry_applies_decoder_deltas_and_drops_an_unknown_base():
    group = _weights(1)
    local = {k: v + 0.5 for k, v in group.items()}
    base = DecoderBase()
    base.set("g", 2, group)
    reg = Registry(4, decoder_shapes={k: v.shape for k, v in group.items()})
    msg = P.DecoderWeights(
        agent_id="a", seq=0, group_id="g", round=2, n_samples=5, **base.fields("g", local)
    )
    reg.handle(msg)  # the server never published g#2
    assert any("g#2, a group decoder this server does not hold" in r for r in reg.dropped)
    assert reg.agents["a"].decoder is None
    reg.decoder_bases.add("g", 2, group)
    reg.handle(msg.model_copy(update={"seq": 1}))
    for name, value in local.items():
        np.testing.assert_allclose(reg.agents["a"].decoder[name], value, atol=0.5 / 254 + 1e-6)


def test_decoder_bases_are_bounded_per_group_and_overall():
    bases = DecoderBases(per_group=2, max_entries=3)
    w = {"w": np.zeros(2, np.float32)}
    for r in (1, 2, 3):
        bases.add("g", r, w)
    assert isinstance(bases.apply("g", 1, w), str) and isinstance(bases.apply("g", 3, w), dict)
    bases.add("h", 1, w)
    bases.add("k", 1, w)
    assert len(bases) == 3
    assert "other tensors" in bases.apply("k", 1, {"v": np.zeros(2, np.float32)})
    assert "shape" in bases.apply("k", 1, {"w": np.zeros(3, np.float32)})


# --- renders from quantised decoders and features --------------------------------------------

INTR = Intrinsics(fx=40.0, fy=40.0, cx=23.5, cy=17.5, width=48, height=36)
SPEC = spec(c_hidden=32, g_hidden=32, u_hidden=32)


def _plane_map() -> NeuralPointMap:
    m = NeuralPointMap(feature_dim=32, cell_size=0.1)
    m.set_keyframe_poses(0, np.eye(4))
    g = torch.arange(-1.6, 1.6, 0.1, dtype=torch.float64) + 0.05
    xx, yy = torch.meshgrid(g, g, indexing="ij")
    xyz = torch.stack((xx.reshape(-1), yy.reshape(-1), torch.full((xx.numel(),), 2.0)), -1)
    feats = 0.1 * torch.randn(len(xyz), 32, generator=torch.Generator().manual_seed(0))
    m.add_points(xyz.float(), 0, feats, torch.full((len(xyz), 3), 200, dtype=torch.uint8))
    return m


def _render(point_map, decoders) -> dict[str, torch.Tensor]:
    with torch.no_grad():
        return render_image(
            point_map,
            decoders,
            INTR,
            torch.eye(4, dtype=torch.float64),
            SPEC.sampler(perturb=False),
            k=SPEC.k_neighbors,
            radius=SPEC.radius,
            step=2,
        )


def _assert_closer(ref: dict, got: dict, far: dict, fraction: float) -> None:
    """`got` renders colour and depth closer to `ref` than `fraction` of how far `far` does
    (the reference change must be non-zero)."""
    for key in ("color", "depth"):
        change = (far[key] - ref[key]).abs().mean()
        err = (got[key] - ref[key]).abs().mean()
        assert change > 0 and err <= fraction * change, (key, float(err), float(change))


def test_decoder_from_a_quantised_delta_renders_like_the_unquantised_one():
    """Tolerance: the quantised decoder's render is closer to the exact one than 2 % of the
    change the delta itself makes (its elements are off by at most 1/254 of a row's peak)."""
    point_map = _plane_map()
    exact = SPEC.decoders(0)
    base = {
        k: v + 0.05 * torch.randn(v.shape, generator=torch.Generator().manual_seed(1))
        for k, v in exact.state_dict().items()
    }
    agent = DecoderBase()
    agent.set("g", 1, {k: v.numpy() for k, v in base.items()})
    fields = agent.fields("g", {k: v.numpy() for k, v in exact.state_dict().items()})
    msg = P.decode(
        P.encode(
            P.DecoderWeights(agent_id="a", seq=0, group_id="g", round=1, n_samples=1, **fields)
        )
    )
    server = DecoderBases()
    server.add("g", 1, {k: v.numpy() for k, v in base.items()})
    rebuilt, on_base = SPEC.decoders(0), SPEC.decoders(0)
    rebuilt.load_state_dict(
        {k: torch.as_tensor(v) for k, v in server.apply("g", 1, msg.values()).items()}
    )
    on_base.load_state_dict(base)
    ref, got, old = (_render(point_map, d) for d in (exact, rebuilt, on_base))
    assert (ref["acc"] > 0).any()
    _assert_closer(ref, got, old, 0.02)


def test_decoder_from_full_int8_weights_renders_like_the_exact_one():
    """Tolerance: full weights as int8 rows (each off by at most 1/254 of its row's peak,
    about 1/440 RMS) move the render less than 15 % of what noise of 5 % of each row's peak
    does (5-7 % measured, about what a render near linear in such small changes gives)."""
    point_map, exact = _plane_map(), SPEC.decoders(0)
    weights = {k: v.numpy() for k, v in exact.state_dict().items()}
    fields = DecoderBase(full_codec="int8").fields("a", weights)
    msg = P.decode(P.encode(
        P.DecoderWeights(agent_id="a", seq=0, group_id="a", round=0, n_samples=1, **fields)))
    assert msg.tensors_int8 is not None
    rebuilt, noisy = SPEC.decoders(0), SPEC.decoders(0)
    rebuilt.load_state_dict({k: torch.as_tensor(v) for k, v in msg.values().items()})
    gen = torch.Generator().manual_seed(5)
    noisy.load_state_dict({
        k: v + 0.05 * v.abs().amax(dim=-1, keepdim=True) * torch.randn(v.shape, generator=gen)
        for k, v in exact.state_dict().items()})
    ref, got, far = (_render(point_map, d) for d in (exact, rebuilt, noisy))
    assert (ref["acc"] > 0).any()
    _assert_closer(ref, got, far, 0.15)


def test_int8_features_render_like_float16_ones():
    """Tolerance: int8 features (off by at most 1/254 of a point's peak, about 1/1000 on
    average) move the render less than 5 % of what noise of 10 % of the peak does."""
    point_map, decoders = _plane_map(), SPEC.decoders(0)
    feats = point_map.features.detach().clone()
    rows = torch.arange(len(point_map))
    _, received = encode_features(feats.numpy(), "int8")
    ref = _render(point_map, decoders)
    point_map.set_features(rows, torch.from_numpy(received))
    got = _render(point_map, decoders)
    noise = (
        0.1
        * feats.abs().amax(1, keepdim=True)
        * torch.randn(feats.shape, generator=torch.Generator().manual_seed(3))
    )
    point_map.set_features(rows, feats + noise)
    noisy = _render(point_map, decoders)
    _assert_closer(ref, got, noisy, 0.05)


# --- bytes per sensor second -----------------------------------------------------------------


def test_bytes_per_sensor_second_per_key_and_agent():
    assert sensor_seconds([0.0, 0.1, 0.2, 0.3]) == pytest.approx(0.4)
    assert sensor_seconds([5.0]) is None
    traffic = {
        "received": {
            "cpslam/s/agent/a0/submap": {"messages": 2, "bytes": 1000},
            "cpslam/s/agent/a0/decoder": {"messages": 1, "bytes": 600},
        }
    }
    out = traffic_per_agent("s", traffic, seconds=100.0, sensor_s={"a0": 4.0})
    a0 = out["a0"]
    assert a0["sensor_s"] == 4.0
    assert a0["from_agent"]["submap"]["bytes_per_sensor_s"] == 250.0
    assert a0["from_agent_bytes_per_sensor_s"] == 400.0
    assert a0["from_agent_bytes_per_s"] == 16.0
    assert (
        "bytes_per_sensor_s"
        not in traffic_per_agent("s", traffic, 1.0)["a0"]["from_agent"]["submap"]
    )


def _send_decoder(agent: DecoderBase, seq: int, w: dict) -> P.DecoderWeights:
    """Agent "a"'s decoder message of `seq` for weights `w`, as its link would make it."""
    fields = agent.fields("a", w)
    msg = P.DecoderWeights(agent_id="a", seq=seq, group_id="a", round=0, n_samples=1, **fields)
    agent.sent(seq, fields)
    return msg


def test_own_decoder_chain_follows_acks_and_goes_full_every_n():
    """Before any shared decoder the deltas refer to the agent's own acknowledged weights;
    the server rebuilds them bit for bit as the agent predicts, refuses a chain it lost, and
    a full message every `full_every` puts it back in step."""
    agent, reg = DecoderBase(full_every=3), Registry(4)
    w = _weights(1)
    sent = []
    for seq in range(7):
        w = {k: v + 0.01 * (seq + 1) for k, v in w.items()}
        msg = _send_decoder(agent, seq, w)
        sent.append(msg)
        if seq == 4:  # the server restarts from a state without the chain
            state = reg.state_dict()
            state["agents"][0].update(decoder=None, decoder_seq=-1)
            reg = Registry(4)
            reg.load_state_dict(state)
        reg.handle(P.decode(P.encode(msg)))
        agent.acked(seq)
        if seq not in (4, 5):  # deltas against seqs 3 and 4, refused; 6: full again
            np.testing.assert_array_equal(
                reg.agents["a"].decoder["l0.weight"], agent.own["l0.weight"]
            )
    kinds = ["full" if m.tensors_f16 is not None else m.base_seq for m in sent]
    assert kinds == ["full", 0, 1, "full", 3, 4, "full"]
    assert sum("the server holds its weights of seq -1" in r for r in reg.dropped) == 2
    assert reg.agents["a"].decoder_seq == 6


def test_full_decoder_weights_as_int8_are_rebuilt_as_the_agent_predicts():
    """With ``full_codec`` int8 the full messages go as int8 rows (63 % of the float16 bytes
    for these 32-wide rows, the scales included), within half a step of each row's scale;
    the server holds exactly what the agent predicts, and the own deltas after them stay in
    step."""
    agent, reg = DecoderBase(full_every=3, full_codec="int8"), Registry(4)
    w = _weights(1)
    f16 = P.encoded_size(_send_decoder(DecoderBase(), 0, w))
    for seq in range(4):
        w = {k: v + 0.01 * (seq + 1) for k, v in w.items()}
        msg = _send_decoder(agent, seq, w)
        if seq in (0, 3):  # full
            assert msg.tensors_int8 is not None and msg.base_seq is None
            assert P.encoded_size(msg) < 0.7 * f16
            for k, v in w.items():
                step = np.atleast_1d(msg.tensor_scales[k]).reshape(-1, *[1] * max(v.ndim - 1, 0))
                assert np.all(np.abs(msg.values()[k] - v) <= 0.5 * step + 1e-7)
        else:
            assert msg.base_seq == seq - 1
        reg.handle(P.decode(P.encode(msg)))
        agent.acked(seq)
        for k in w:
            np.testing.assert_array_equal(reg.agents["a"].decoder[k], agent.own[k])
    with pytest.raises(ValueError, match="full_codec"):
        DecoderBase(full_codec="float32")


def test_no_own_delta_while_an_earlier_decoder_message_is_unacknowledged():
    """Two decoder messages before the first one's ack: the server takes the first and keeps
    only its weights, so the second must not be a delta against the older acknowledged ones
    (it would be dropped); it goes full, and deltas resume once the acks catch up."""
    agent, reg = DecoderBase(full_every=100), Registry(4)
    w = _weights(1)
    msgs = []
    for seq in range(4):
        w = {k: v + 0.01 * (seq + 1) for k, v in w.items()}
        msgs.append(_send_decoder(agent, seq, w))
        reg.handle(P.decode(P.encode(msgs[-1])))
        if seq != 1:  # the ack of seq 1 comes late, after seq 2 was sent
            agent.acked(seq)
    kinds = ["full" if m.tensors_f16 is not None else m.base_seq for m in msgs]
    assert kinds == ["full", 0, "full", 2]
    assert not reg.dropped
    assert reg.agents["a"].decoder_seq == 3
    np.testing.assert_array_equal(reg.agents["a"].decoder["l0.weight"], agent.own["l0.weight"])


def test_agent_reports_bytes_per_sensor_second_per_key():
    from types import SimpleNamespace

    from cpslam.agent.node import AgentNode

    node = SimpleNamespace(results=[SimpleNamespace(timestamp=t) for t in (0.0, 0.5, 1.0, 1.5)])
    stats = {"sent": {"cpslam/s/agent/a/submap": {"messages": 3, "bytes": 8000}}}
    assert AgentNode.sent_per_sensor_s(node, stats) == {"cpslam/s/agent/a/submap": 4000.0}
    assert AgentNode.sent_per_sensor_s(SimpleNamespace(results=[]), stats) == {}

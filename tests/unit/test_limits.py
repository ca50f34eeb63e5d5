"""Every cap on peer-keyed state and every plausibility check: each attack does no harm."""

from __future__ import annotations

import json
import time

import numpy as np
import pytest

from cpslam import protocol
from cpslam.common.bounds import OTHER, CappedCounter, LogThrottle, tensor_mismatch
from cpslam.common.bus import InMemoryBus, InMemoryNetwork
from cpslam.common.bus.subscription import Sample, Subscription
from cpslam.common.bus.zenoh_bus import zenoh_config
from cpslam.common.config import ConfigError, load_config
from cpslam.common.place_recognition import descriptor_dim
from cpslam.protocol import (
    Ack,
    DecoderWeights,
    FramePoses,
    KeyframeImage,
    KeyframeMsg,
    Status,
    SubmapDelta,
    keys,
)
from cpslam.server.bounds import fit_status, status_size
from cpslam.server.registry import Registry, registry_args
from cpslam.server.traffic import KeyCounter

F = 4
D = 8


def keyframe(seq, kf, agent="a", d=D, t=(0.0, 0.0, 0.0)):
    desc = np.zeros(d, np.float32)
    desc[kf % d] = 1
    T = np.eye(4)
    T[:3, 3] = t
    return KeyframeMsg(
        agent_id=agent,
        seq=seq,
        kf_id=kf,
        frame_index=10 * kf,
        stamp=kf,
        T_world_cam=T,
        descriptor=desc,
    )


def delta(seq, ids, anchor=0, removed=(), agent="a"):
    n = len(ids)
    return SubmapDelta(
        agent_id=agent,
        seq=seq,
        point_ids=np.asarray(ids, np.int64),
        anchor_kf_ids=np.full(n, anchor, np.int32),
        xyz_local=np.zeros((n, 3), np.float32),
        features=np.zeros((n, F)),
        colors=np.zeros((n, 3), np.uint8),
        removed_ids=np.asarray(removed, np.int64),
    )


def frames(seq, indices, kf):
    n = len(indices)
    return FramePoses(
        agent_id="a",
        seq=seq,
        frame_indices=np.asarray(indices, np.int64),
        stamps=np.zeros(n),
        kf_ids=np.full(n, kf, np.int32),
        T_kf_frame=np.repeat(np.eye(4)[None], n, 0),
    )


# ---------------------------------------------------------------------------- bookkeeping


def test_capped_counter_counts_keys_beyond_the_cap_as_other() -> None:
    c = CappedCounter(3)
    for i in range(100):
        c.add(f"k{i}")
    c.add("k0", 5)
    assert len(c) == 3 and dict(c) == {"k0": 6, "k1": 1, OTHER: 98}
    assert c["never"] == 0 and c.total() == 105


def test_log_throttle_lets_one_line_per_interval_and_counts_the_rest() -> None:
    t = [0.0]
    throttle = LogThrottle(interval_s=5.0, max_subjects=2, now=lambda: t[0])
    assert throttle.allow("a") == 0
    assert throttle.allow("a") is None and throttle.allow("a") is None
    t[0] = 5.0
    assert throttle.allow("a") == 2
    for s in ("b", "c", "d"):
        throttle.allow(s)
    assert len(throttle._last) == 2  # bounded even when subjects come from peers


def test_key_counter_keeps_max_keys_then_other() -> None:
    counter = KeyCounter(max_keys=2)
    for i in range(1000):
        counter.add(f"cpslam/default/agent/x{i}/keyframe", 10)
    table = counter.table()
    assert len(table) == 3 and table[OTHER] == {"messages": 998, "bytes": 9980}


def test_tensor_mismatch_names_field_expected_and_got() -> None:
    expected = {"w": (2, 2)}
    assert tensor_mismatch({"w": np.zeros((2, 2))}, expected) == ""
    assert "tensors['w'] has shape [3, 2], expected [2, 2]" in tensor_mismatch(
        {"w": np.zeros((3, 2))}, expected
    )
    assert "missing ['w'], unknown ['v']" in tensor_mismatch({"v": np.zeros(1)}, expected)


# --------------------------------------------------------------------------------- config


def test_limits_section_is_in_the_config_with_its_caps() -> None:
    cfg = load_config("tiny", overrides=["limits.max_agents=3"], env={})
    assert cfg.limits.max_agents == 3
    args = registry_args(cfg.limits, 99)
    assert args["max_agents"] == 3 and args["descriptor_dim"] == 99
    with pytest.raises(ConfigError, match="status_reply_kb"):
        load_config("tiny", overrides=["limits.status_reply_kb=4096"], env={})
    with pytest.raises(ConfigError):
        load_config("tiny", overrides=["limits.max_agents=0"], env={})


def test_descriptor_length_follows_the_place_recognition_section(tmp_path) -> None:
    cfg = load_config("tiny", env={})
    assert descriptor_dim(cfg.place_recognition) == 8 * 192  # NetVLAD, 8 clusters, stage6
    gem = load_config(
        "tiny",
        overrides=["place_recognition.aggregation=gem", "place_recognition.layer=head"],
        env={},
    )
    assert descriptor_dim(gem.place_recognition) == 1280
    wide = load_config("tiny", overrides=["place_recognition.layer=head"], env={})
    assert descriptor_dim(wide.place_recognition) == 4096  # count-sketched
    path = tmp_path / "w.npz"
    np.savez(
        path,
        centroids=np.zeros((4, 192), np.float32),
        **{"pca.weight": np.zeros((32, 768), np.float32)},
    )
    pca = load_config("tiny", overrides=[f"place_recognition.weights={path}"], env={})
    assert descriptor_dim(pca.place_recognition) == 32


def test_the_agents_extractor_makes_descriptors_of_that_length() -> None:
    from cpslam.agent.descriptor import DescriptorExtractor
    from cpslam.agent.efficientnet import STAGES
    from cpslam.common.place_recognition import LAYER_CHANNELS

    assert LAYER_CHANNELS == {k: c for k, (c, _) in STAGES.items()}
    cfg = load_config("tiny", env={})
    ex = DescriptorExtractor.from_config(cfg.place_recognition, seed=cfg.run.seed)
    assert ex.dim == descriptor_dim(cfg.place_recognition)


def test_zenoh_receive_limit_and_session_count_follow_the_config() -> None:
    conf = zenoh_config(
        "router", listen=["tcp/127.0.0.1:0"], max_payload_bytes=2**20, max_sessions=7
    )
    assert int(conf.get_json("transport/unicast/max_sessions")) == 7
    limit = int(conf.get_json("transport/link/rx/max_message_size"))
    assert 2**20 < limit <= 2**20 + 2**17
    default = zenoh_config("router", listen=["tcp/127.0.0.1:0"])
    assert int(default.get_json("transport/unicast/max_sessions")) == 1000  # Zenoh's own


# ------------------------------------------------------------------------------------ bus


def test_subscription_queue_is_bounded_in_bytes_dropping_the_oldest() -> None:
    sub = Subscription("k", queue_size=1000, max_bytes=100)
    for i in range(50):
        sub.deliver(Sample("k", bytes([i]) * 30, 0.0))
    assert len(sub) == 3 and sub.queued_bytes == 90 and sub.dropped == 47
    assert sub.get(timeout=0).payload[0] == 47
    assert sub.queued_bytes == 60
    big = Subscription("k", queue_size=10, max_bytes=10)
    big.deliver(Sample("k", b"x" * 50, 0.0))  # alone over the budget: the newest is kept
    assert len(big) == 1


def test_bus_subscriptions_and_oversized_counter_are_bounded() -> None:
    net = InMemoryNetwork()
    with (
        InMemoryBus(net, max_payload_bytes=64, max_queue_bytes=256, max_counter_keys=4) as rx,
        InMemoryBus(net) as tx,
    ):
        sub = rx.subscribe("flood/**", queue_size=10_000)
        for i in range(200):
            tx.publish(f"flood/k{i}", b"x" * (100 if i % 2 else 32))
        with rx.subscribe("flood/end") as end:
            tx.publish("flood/end", b"")
            assert end.get(timeout=30) is not None
        assert sub.queued_bytes <= 256
        oversized = rx.stats()["oversized"]
        assert len(oversized) <= 4 and sum(oversized.values()) == 100


# ------------------------------------------------------------------------------- registry


def test_agent_ids_beyond_the_cap_are_refused_and_counted() -> None:
    reg = Registry(F, max_agents=3)
    for i in range(10_000):
        reg.handle(keyframe(0, 0, agent=f"x{i}"))
    assert len(reg.agents) == 3 and reg.refused_agents == 9_997
    assert reg.dropped["agent cap reached"] == 9_997
    assert reg.handle(keyframe(1, 1, agent="x0")) == [Ack(agent_id="x0", seq=1)]


def test_seqs_far_ahead_are_dropped_unacknowledged() -> None:
    reg = Registry(F, max_seq_ahead=100)
    reg.handle(delta(0, []))  # the stream's first message binds the id
    for seq in range(1000, 101_000, 7):
        reg.handle(delta(seq, []))
    rec = reg.agents["a"]
    assert not rec.seqs_above and reg.dropped["seq too far ahead"] > 10_000
    # Within the window: held (nothing contiguous yet), its range acknowledged.
    assert reg.handle(delta(50, [])) == [Ack(agent_id="a", seq=0, received=[(50, 50)])]
    assert rec.seqs_above == {50}


def test_a_one_element_descriptor_does_not_fix_the_length_for_the_session() -> None:
    reg = Registry(F, descriptor_dim=D)
    reg.handle(keyframe(0, 0, agent="evil", d=1))
    reg.handle(keyframe(0, 0, agent="good"))
    reg.handle(keyframe(1, 1, agent="good"))
    assert list(reg.agents["good"].keyframes) == [0, 1]
    assert not reg.agents["evil"].keyframes
    reason = next(iter(reg.agents["evil"].dropped))
    assert "descriptor has length 1, expected 8" in reason


def test_poses_must_be_plausible() -> None:
    reg = Registry(F, max_translation_m=100.0)
    reg.handle(keyframe(0, 0, t=(0.0, 1e6, 0.0)))
    assert not reg.agents["a"].keyframes
    assert any("T_world_cam has |t| 1e+06 m, expected at most 100 m" in r for r in reg.dropped)
    reg.handle(keyframe(1, 0, t=(1.0, 2.0, 3.0)))
    far = frames(2, [1, 2], 0)
    far.T_kf_frame[1, 0, 3] = 1e5
    reg.handle(far)
    assert list(reg.agents["a"].keyframes) == [0] and not reg.agents["a"].frames


def test_keyframe_ids_must_increase_with_seq() -> None:
    reg = Registry(F)
    reg.handle(keyframe(0, 5))
    reg.handle(keyframe(1, 3))  # later message, earlier keyframe
    reg.handle(keyframe(3, 9))
    reg.handle(keyframe(2, 7))  # out of order but consistent: accepted
    assert sorted(reg.agents["a"].keyframes) == [5, 7, 9]
    assert any("kf_id 3 (seq 1) does not increase with seq" in r for r in reg.dropped)


def test_federated_sample_counts_are_capped() -> None:
    reg = Registry(F, max_federated_samples=1000)
    tensors = {"w": np.zeros((2, 2), np.float32)}
    reg.handle(
        DecoderWeights(
            agent_id="a", seq=0, group_id="a", round=0, n_samples=10**12, tensors=tensors
        )
    )
    assert reg.agents["a"].decoder is None and not reg.new_decoders
    assert any("n_samples is 1000000000000, expected at most 1000" in r for r in reg.dropped)
    reg.handle(
        DecoderWeights(agent_id="a", seq=1, group_id="a", round=0, n_samples=1000, tensors=tensors)
    )
    assert reg.agents["a"].decoder_samples == 1000


def test_a_huge_removed_id_list_is_refused_fast_without_touching_the_tables() -> None:
    reg = Registry(F, max_removed_per_message=1000)
    reg.handle(keyframe(0, 0))
    reg.handle(delta(1, [1, 2, 3]))
    msg = delta(2, [], removed=np.arange(1_000_000))
    t0 = time.perf_counter()
    reg.handle(msg)
    elapsed = time.perf_counter() - t0
    rec = reg.agents["a"]
    assert len(rec.points) == 3 and not rec.points.tombstones
    assert any("removed_ids has 1000000 ids, expected at most 1000" in r for r in reg.dropped)
    # Generous: refusing must not cost what removing a million ids one by one does.
    assert elapsed < 0.5


def test_tombstones_are_capped_forgetting_the_oldest() -> None:
    reg = Registry(F, max_tombstones=1000)
    reg.handle(keyframe(0, 0))
    for i in range(30):
        reg.handle(delta(1 + i, [], removed=np.arange(i * 100, i * 100 + 100)))
    tomb = reg.agents["a"].points.tombstones
    assert len(tomb) <= 1000
    assert 2999 in tomb and 0 not in tomb  # the newest removals are remembered


def test_keyframes_per_agent_are_capped() -> None:
    reg = Registry(F, max_keyframes_per_agent=5)
    for kf in range(8):
        reg.handle(keyframe(kf, kf))
    assert sorted(reg.agents["a"].keyframes) == [0, 1, 2, 3, 4]
    assert reg.agents["a"].seq_floor == 7  # dropped, not left hanging
    assert sum(n for r, n in reg.dropped.items() if "max_keyframes_per_agent" in r) == 3


def test_points_per_agent_are_capped_counting_replacements_and_removals() -> None:
    reg = Registry(F, max_points_per_agent=100)
    reg.handle(keyframe(0, 0))
    reg.handle(delta(1, range(80)))
    reg.handle(delta(2, range(70, 120)))  # 40 new: 120 > 100, refused whole
    assert len(reg.agents["a"].points) == 80
    reg.handle(delta(3, range(70, 120), removed=range(20)))  # 40 new, 20 gone: 100, taken
    assert sorted(reg.agents["a"].points.ids.tolist()) == list(range(20, 120))
    reg.handle(delta(4, range(50)))  # 30 replaced, 20 new: 120, refused whole
    reg.handle(delta(5, range(20, 120)))  # all replaced: 100, taken
    assert sorted(reg.agents["a"].points.ids.tolist()) == list(range(20, 120))
    assert reg.agents["a"].seq_floor == 5
    assert sum(n for r, n in reg.dropped.items() if "max_points_per_agent" in r) == 2


def test_pending_frames_are_capped() -> None:
    reg = Registry(F, max_pending_frames=50)
    for seq in range(10):
        reg.handle(frames(seq, range(seq * 20, seq * 20 + 20), kf=99))
    pending = reg.agents["a"].pending_frames
    assert len(pending) == 50 and min(pending) == 150  # the newest frames wait
    assert reg.dropped["too many frames waiting for keyframes"] == 150


def test_distinct_drop_reasons_are_capped() -> None:
    reg = Registry(F, descriptor_dim=D, max_counter_keys=16)
    for i in range(200):
        reg.handle(keyframe(i, i, d=9 + i))  # every length wrong, every reason distinct
    assert len(reg.dropped) <= 16 and len(reg.agents["a"].dropped) <= 32
    assert reg.dropped.total() == 200


# --------------------------------------------------------------------------------- status


def _size(summary: dict) -> int:
    """The real reply's size before compression (status_size must agree with it where the
    codec allows); the bytes on the wire are never more."""
    n = status_size(summary)
    if n < Status.max_bytes:
        status = Status(stamp=0.0, summary=summary)
        assert n == len(protocol.encode(status, zstd_level=0))
        assert len(protocol.encode(status)) <= n
    return n


def test_status_always_fits_its_budget() -> None:
    rng = np.random.default_rng(0)
    agents = {
        f"agent{i:05d}": {
            "index": i,
            "alive": True,
            "keyframes": int(rng.integers(100)),
            "messages": int(rng.integers(10_000)),
            "dropped": {f"reason {j} " * 5: j for j in range(40)},
        }
        for i in range(2000)
    }
    summary = {
        "agents": agents,
        "bus_dropped": {f"cpslam/x/agent/k{i}/z": 1 for i in range(20_000)},
        "loops": {"found": 3, "recent": [{"loop_id": i} for i in range(500)]},
        "merges": 2,
    }
    for budget in (4096, 64 * 1024, 512 * 1024):
        out = fit_status(summary, _size, budget)
        assert _size(out) <= budget
        assert out["merges"] == 2 and out["truncated"]["budget_bytes"] == budget
        kept = out["agents"]
        assert all(isinstance(v, dict) for v in kept.values())  # rows stay rows
        if kept:
            busiest = max(a["messages"] for a in agents.values())
            assert max(a["messages"] for a in kept.values()) == busiest
        if out["bus_dropped"]:
            assert sum(out["bus_dropped"].values()) == 20_000  # cut counts go to "other"
    small = {"agents": {"a": {"messages": 1}}, "merges": 0}
    assert fit_status(small, _size, 4096) is small
    json.dumps(fit_status(summary, _size, 100))  # even a tiny budget gives valid JSON


# ------------------------------------------------------------------------- node, pipeline


def _image(agent: str, kf: int, side: int = 64) -> KeyframeImage:
    return KeyframeImage.from_metres(
        np.ones((side, side), np.float32),
        agent_id=agent,
        kf_id=kf,
        fx=50.0,
        fy=50.0,
        cx=side / 2,
        cy=side / 2,
        width=side,
        height=side,
        rgb_codec="png",
        rgb=np.zeros((side, side, 3), np.uint8),
    )


def test_image_cache_is_bounded_in_bytes() -> None:
    from cpslam.server.loops import LoopPipeline

    one = 64 * 64 * 5  # rgb uint8 x3 + depth uint16
    cfg = load_config("tiny", env={})
    pipeline = LoopPipeline(
        cfg.loop, lambda a, k: _image(a, k), time.monotonic, 0.0, image_cache_bytes=3 * one
    )
    for kf in range(10):
        assert pipeline.image("a", kf).kf_id == kf
    assert len(pipeline._images) == 3 and pipeline._image_bytes == 3 * one
    assert list(pipeline._images) == [("a", 7), ("a", 8), ("a", 9)]


def test_an_image_reply_for_another_keyframe_is_dropped(tmp_path) -> None:
    from cpslam.server.node import ServerNode

    cfg = load_config("tiny", env={})
    network = InMemoryNetwork()
    with InMemoryBus(network) as server_bus, InMemoryBus(network) as agent_bus:
        node = ServerNode(cfg, server_bus, tmp_path, image_timeout_s=5.0).start()
        answer = {"kf": 3}

        def serve(key: str, payload: bytes | None) -> bytes:
            return protocol.encode(_image("a", answer["kf"]))

        with agent_bus.declare_queryable(keys.agent_image_queryable("default", "a"), serve):
            assert node.fetch_image("a", 3).kf_id == 3
            answer["kf"] = 4  # a buggy or hostile agent answers with another keyframe
            assert node.fetch_image("a", 3) is None
        assert sum(node.dropped.values()) == 1
        node.close()


def test_presence_of_agents_beyond_the_cap_is_ignored(tmp_path) -> None:
    from cpslam.server.node import ServerNode

    cfg = load_config("tiny", overrides=["limits.max_agents=4"], env={})
    with InMemoryBus() as bus:
        node = ServerNode(cfg, bus, tmp_path)
        presence = node.presence
        for i in range(1000):
            presence.joined(keys.alive_agent("default", f"x{i}"))
        for i in range(1000):
            presence.joined(f"cpslam/default/alive/agent/bad{i}/x")  # malformed token keys
        assert len(presence.alive()) == 4 and len(presence._events) <= 16
        presence.left(keys.alive_agent("default", "x0"))
        assert presence.gone("x0") and presence.alive()["x0"] is False
        assert presence.take_events()[-1] == ("leave", "x0") and not presence.take_events()


def test_the_agent_daemon_survives_server_messages_it_cannot_apply(
    tmp_path, monkeypatch, caplog
) -> None:
    from cpslam.agent.node import AgentNode
    from cpslam.common.datasets import open_sequence
    from cpslam.protocol import GroupDecoder, ServerUpdate
    from cpslam.tools.synth import generate

    seq = open_sequence(generate(tmp_path / "s", frames=3, width=64, height=48).agent_dirs[0])
    cfg = load_config("tiny", env={})

    def describe(rgb: np.ndarray) -> np.ndarray:
        return np.full(D, D**-0.5, np.float32)

    with InMemoryBus() as bus:
        node = AgentNode(cfg, seq, bus, "a0", tmp_path / "run", describe=describe).start()
        shapes = {k: tuple(v.shape) for k, v in node.odometry.decoders.state_dict().items()}
        wrong = {k: np.zeros((3, 1), np.float32) for k in shapes}  # a server on another preset
        decoder = GroupDecoder(group_id="a0", round=1, members=["a0"], n_samples=1, tensors=wrong)
        bus.publish(keys.server_agent_group_decoder("default", "a0"), protocol.encode(decoder))
        update = ServerUpdate(
            agent_id="a0",
            seq=1,
            epoch=1,
            group_id="a0",
            group_members=["a0"],
            T_group_agent=np.eye(4),
            kf_ids=np.zeros(0, np.int32),
            T_group_kf=np.zeros((0, 4, 4)),
        )

        def fail(msg: ServerUpdate) -> None:
            raise RuntimeError("cannot apply")

        monkeypatch.setattr(node.link, "apply_update", fail)
        bus.publish(keys.server_agent_update("default", "a0"), protocol.encode(update))
        with bus.subscribe("test/settle") as marker:
            bus.publish("test/settle", b"")
            assert marker.get(timeout=30.0) is not None
        with caplog.at_level("WARNING"):
            assert node.poll() == 2
        assert node.dropped == 1 and node.link.round == 0
        assert "has shape [3, 1], expected" in caplog.text and "applying it failed" in caplog.text
        assert {k: tuple(v.shape) for k, v in node.odometry.decoders.state_dict().items()} == shapes
        node.close()

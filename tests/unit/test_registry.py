"""Registry: idempotence by seq, acks, buffering of unknown anchors, bad content dropped."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from cpslam.common.geometry import compose, se3_exp
from cpslam.protocol import Ack, DecoderWeights, FramePoses, KeyframeMsg, SubmapDelta
from cpslam.server.registry import Registry

F = 4


def keyframe(seq, kf, T=None, epoch=0, agent="a"):
    d = np.zeros(8, np.float32)
    d[kf % 8] = 1
    return KeyframeMsg(agent_id=agent, seq=seq, kf_id=kf, frame_index=10 * kf, stamp=kf,
                       T_world_cam=np.eye(4) if T is None else T, world_epoch=epoch,
                       descriptor=d)


def delta(seq, ids, anchor, f=F, removed=(), agent="a", x=0.0):
    n = len(ids)
    return SubmapDelta(agent_id=agent, seq=seq, point_ids=np.asarray(ids, np.int64),
                       anchor_kf_ids=np.full(n, anchor, np.int32),
                       xyz_local=np.full((n, 3), x, np.float32), features=np.zeros((n, f)),
                       colors=np.zeros((n, 3), np.uint8),
                       removed_ids=np.asarray(removed, np.int64))


def test_replayed_seq_is_ignored_and_acked():
    reg = Registry(F)
    assert reg.handle(keyframe(0, 0)) == [Ack(agent_id="a", seq=0)]
    assert reg.handle(delta(1, [0, 1], 0)) == [Ack(agent_id="a", seq=1)]
    assert reg.handle(delta(1, [5, 6, 7], 0)) == [Ack(agent_id="a", seq=1)]  # replay
    assert len(reg.agents["a"].points) == 2
    assert reg.take_new_keyframes() == [("a", 0)]


def test_out_of_order_seqs_ack_the_floor_and_the_ranges_above_it():
    reg = Registry(F)
    # Before the stream's first message nothing binds the id: dropped, unacknowledged.
    assert reg.handle(delta(3, [0], 0)) == [] and "a" not in reg.agents
    assert reg.dropped["stream start not seen"] == 1
    assert reg.handle(keyframe(0, 0)) == [Ack(agent_id="a", seq=0)]
    # A gap: the floor stays, the received range says what is in.
    assert reg.handle(delta(3, [0], 0)) == [Ack(agent_id="a", seq=0, received=[(3, 3)])]
    assert reg.handle(keyframe(2, 2)) == [Ack(agent_id="a", seq=0, received=[(2, 3)])]
    assert reg.handle(keyframe(1, 1)) == [Ack(agent_id="a", seq=3)]


def test_feature_rows_replace_only_the_features_of_held_points():
    reg = Registry(F)
    reg.handle(keyframe(0, 0))
    reg.handle(delta(1, [0, 1], 0, x=0.5))
    reg.handle(delta(2, [2], 7))  # anchored to a keyframe still to come: waiting
    update = SubmapDelta(agent_id="a", seq=4, point_ids=np.zeros(0, np.int64),
                         anchor_kf_ids=np.zeros(0, np.int32), xyz_local=np.zeros((0, 3)),
                         colors=np.zeros((0, 3), np.uint8), removed_ids=np.zeros(0, np.int64),
                         feature_ids=np.array([1, 2, 9]), features=np.full((3, F), 2.0))
    reg.handle(update)
    rec = reg.agents["a"]
    np.testing.assert_array_equal(rec.points.features, [[0] * F, [2] * F])
    np.testing.assert_array_equal(rec.points.xyz, np.full((2, 3), 0.5))  # position kept
    np.testing.assert_array_equal(rec.pending_points.features, [[2] * F])
    assert rec.points.seq.tolist() == [1, 4]
    assert reg.dropped["features of points not held"] == 1  # point 9 was never sent
    # an older message arriving late does not undo the newer features
    older = update.model_copy(update={"seq": 3, "features": np.full((3, F), 1.0)})
    reg.handle(older)
    np.testing.assert_array_equal(rec.points.features[1], [2] * F)


def test_unknown_anchor_waits_for_its_keyframe():
    reg = Registry(F)
    reg.handle(keyframe(0, 0))
    reg.handle(delta(1, [0, 1, 2], 3))
    reg.handle(FramePoses(agent_id="a", seq=2, frame_indices=[31], stamps=[3.1], kf_ids=[3],
                          T_kf_frame=np.eye(4)[None]))
    rec = reg.agents["a"]
    assert len(rec.points) == 0 and len(rec.pending_points) == 3 and 31 in rec.pending_frames
    reg.handle(keyframe(3, 3))
    assert len(rec.points) == 3 and len(rec.pending_points) == 0 and 31 in rec.frames
    reg.handle(delta(4, [9], 7))
    assert reg.drop_unresolved() == 1
    assert reg.dropped["anchor keyframe never arrived"] == 1


def test_bad_content_is_dropped_with_a_reason_not_raised():
    reg = Registry(F, decoder_shapes={"w": (2, 2)})
    reg.handle(keyframe(0, 0))
    reg.handle(delta(1, [0], 0, f=F + 1))
    reg.handle(keyframe(2, 1, epoch=3))
    reg.handle(DecoderWeights(agent_id="a", seq=3, group_id="a", round=0, n_samples=1,
                              tensors={"w": np.zeros((3, 2), np.float32)}))
    reg.handle(keyframe(4, 0))  # same keyframe id again
    rec = reg.agents["a"]
    assert len(rec.points) == 0 and list(rec.keyframes) == [0] and rec.decoder is None
    reasons = " | ".join(reg.dropped)
    assert "width 5" in reasons and "world_epoch 3" in reasons
    assert "shape [3, 2]" in reasons and "already known" in reasons
    assert rec.seq_floor == 4  # dropped messages are handled: acked, not resent forever


def test_updates_removals_and_stale_writes():
    reg = Registry(F)
    reg.handle(keyframe(0, 0))
    reg.handle(delta(2, [0, 1], 0, x=2.0))
    reg.handle(delta(1, [0, 1, 2], 0, x=1.0))  # older, arrives late: only id 2 is new
    rec = reg.agents["a"]
    assert rec.points.ids.tolist() == [0, 1, 2]
    assert rec.points.xyz[:, 0].tolist() == [2.0, 2.0, 1.0]
    reg.handle(delta(4, [], 0, removed=[1]))
    reg.handle(delta(3, [1], 0, x=3.0))  # older than the removal: stays removed
    assert rec.points.ids.tolist() == [0, 2]


def test_poses_after_an_alignment_map_back_to_the_own_world():
    reg = Registry(F)
    reg.handle(keyframe(0, 0))
    T_group_agent = se3_exp(np.array([1.0, 0, 0, 0, 0, 0.3]))
    reg.set_alignment("a", 1, T_group_agent)
    T_own = se3_exp(np.array([0.1, 0.2, 0, 0, 0.1, 0]))
    reg.handle(keyframe(1, 1, T=compose(T_group_agent, T_own), epoch=1))
    np.testing.assert_allclose(reg.agents["a"].keyframes[1].T_own_kf, T_own, atol=1e-12)


def test_state_dict_round_trip():
    reg = Registry(F)
    reg.handle(keyframe(0, 0))
    reg.handle(delta(1, [0, 1], 0))
    reg.handle(delta(2, [4], 9))
    other = Registry(F)
    other.load_state_dict(reg.state_dict())
    a, b = reg.agents["a"], other.agents["a"]
    assert b.points.ids.tolist() == a.points.ids.tolist() and len(b.pending_points) == 1
    assert b.seq_floor == 2 and b.keyframes[0].frame_index == 0


def test_a_state_snapshot_shares_the_points_and_later_messages_leave_it_as_taken():
    reg = Registry(F)
    reg.handle(keyframe(0, 0))
    reg.handle(delta(1, [0, 1, 2], 0))
    snap = reg.state_dict()
    taken = {k: v.clone() for k, v in snap["agents"][0]["points"].items()}
    table = reg.agents["a"].points
    assert np.shares_memory(snap["agents"][0]["points"]["xyz"].numpy(), table.xyz)  # no copy
    with pytest.raises(ValueError, match="read-only"):
        table.features[0, 0] = 1.0  # columns are replaced, never written in place
    reg.handle(delta(2, [1, 5], 0))  # replaces point 1, adds 5
    reg.handle(delta(3, [], 0, removed=[0]))
    assert table.ids.tolist() == [1, 2, 5]
    for name, value in snap["agents"][0]["points"].items():
        assert torch.equal(value, taken[name]), name


def test_a_state_with_keyframes_as_a_list_of_dicts_still_loads():
    reg = Registry(F)
    reg.handle(keyframe(0, 0))
    reg.handle(keyframe(1, 1))
    state = reg.state_dict()
    columns = state["agents"][0]["keyframes"]
    state["agents"][0]["keyframes"] = [  # the layout before keyframes were columns
        {"kf_id": int(columns["kf_id"][i]), "frame_index": int(columns["frame_index"][i]),
         "stamp": float(columns["stamp"][i]), "T_own_kf": columns["T_own_kf"][i],
         "descriptor": columns["descriptor"][i],
         "T_prev_kf_kf": columns["T_prev_kf_kf"][i] if columns["has_prev"][i] else None}
        for i in range(2)]
    other = Registry(F)
    other.load_state_dict(state)
    for kf in (0, 1):
        a, b = reg.agents["a"].keyframes[kf], other.agents["a"].keyframes[kf]
        assert (a.kf_id, a.frame_index, a.stamp) == (b.kf_id, b.frame_index, b.stamp)
        np.testing.assert_array_equal(a.descriptor, b.descriptor)
        assert (a.T_prev_kf_kf is None) == (b.T_prev_kf_kf is None)


def test_a_late_resend_of_older_decoder_weights_keeps_the_newer_ones():
    reg = Registry(F)
    reg.handle(keyframe(0, 0))  # the stream's first message binds the id
    newer = {"w": np.full(3, 2.0, np.float32)}
    reg.handle(DecoderWeights(agent_id="a", seq=5, group_id="a", round=0, n_samples=1,
                              tensors=newer))
    reg.handle(DecoderWeights(agent_id="a", seq=3, group_id="a", round=0, n_samples=1,
                              tensors={"w": np.zeros(3, np.float32)}))  # resent, arrives late
    rec = reg.agents["a"]
    assert rec.decoder_seq == 5 and np.array_equal(rec.decoder["w"], newer["w"])
    assert dict(rec.dropped) == {
        "decoder weights of seq 3, older than the agent's seq 5 the server holds": 1}
    assert rec.seq_floor == 0 and rec.seqs_above == {3, 5}  # handled all the same: acked

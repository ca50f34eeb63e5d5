"""AgentLink: messages per step, outbox trimming, server updates moving poses and map
consistently, foreign points, shared decoders and keyframe image requests."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from cpslam import protocol
from cpslam.agent.deltas import SubmapMirror
from cpslam.agent.link import AgentLink
from cpslam.agent.odometry import Odometry
from cpslam.common.camera import Intrinsics
from cpslam.common.config import load_config
from cpslam.common.datasets import RGBDFrame
from cpslam.common.field_config import field_spec
from cpslam.common.geometry import se3_exp
from cpslam.protocol import (
    Ack,
    DecoderWeights,
    ErrorReply,
    ForeignPoints,
    FramePoses,
    GroupDecoder,
    KeyframeImage,
    KeyframeImageRequest,
    KeyframeMsg,
    ServerUpdate,
    SubmapDelta,
)

INTR = Intrinsics(fx=64.0, fy=64.0, cx=39.5, cy=29.5, width=80, height=60)


def _frame(i: int) -> RGBDFrame:
    """A textured wall 2 m ahead; the camera slides 1 mm per frame."""
    v, u = np.mgrid[0:60, 0:80]
    u = u + i * 0.032  # 1 mm at 2 m with fx 64
    rgb = np.stack(((u * 3) % 256, (v * 4) % 256, ((u + v) * 2) % 256), -1).astype(np.uint8)
    return RGBDFrame(i, i / 30.0, rgb, np.full((60, 80), 2.0, np.float32), None)


def _describe(rgb: np.ndarray) -> np.ndarray:
    d = rgb.reshape(-1, 3).mean(0).astype(np.float32) + 1.0
    return d / np.linalg.norm(d)


def _link(frames_every: int = 3, rounds: int = 1, **link_args) -> AgentLink:
    cfg = load_config("tiny", overrides=["mapping.iters_first=10", "mapping.iters=3",
                                                "tracking.iters=3"], env={})
    odometry = Odometry.from_config(cfg, INTR, "cpu", agent_id=0)
    return AgentLink("a0", odometry, _describe, frames_every=frames_every,
                     round_every_mappings=rounds, **link_args)


def _run(link: AgentLink, start: int, stop: int) -> list[protocol.Message]:
    out = []
    for i in range(start, stop):
        frame = _frame(i)
        out += link.after_step(frame, link.odometry.step(frame))
    return out


@pytest.fixture(scope="module")
def warm() -> tuple[AgentLink, list[protocol.Message]]:
    link = _link()
    return link, _run(link, 0, 6)


def _update(link: AgentLink, seq: int, T: np.ndarray, kf_ids=(), poses=None, foreign=(),
            group: str = "a0", members=("a0",), epoch: int = 1) -> ServerUpdate:
    kf = np.asarray(kf_ids, np.int32)
    return ServerUpdate(agent_id=link.agent_id, seq=seq, epoch=epoch, group_id=group,
                        group_members=list(members), T_group_agent=T, kf_ids=kf,
                        T_group_kf=np.zeros((0, 4, 4)) if poses is None else poses,
                        foreign=list(foreign))


def test_messages_per_step(warm) -> None:
    link, msgs = warm
    kinds = [type(m).__name__ for m in msgs]
    # frame 0: keyframe, sub-map, decoder weights (a round every mapping), frame poses (kf);
    # frame 3: frame poses (batch of 3); frame 5: the same for the second keyframe.
    assert kinds == ["KeyframeMsg", "SubmapDelta", "DecoderWeights", "FramePoses",
                     "FramePoses",
                     "KeyframeMsg", "SubmapDelta", "DecoderWeights", "FramePoses"]
    assert [m.seq for m in msgs] == list(range(len(msgs)))
    for m in msgs:  # every message is valid on the wire
        protocol.decode(protocol.encode(m), expected=type(m))
    kf0, kf1 = msgs[0], msgs[5]
    assert isinstance(kf0, KeyframeMsg) and kf0.kf_id == 0 and kf0.T_prev_kf_kf is None
    assert kf1.kf_id == 1 and kf1.frame_index == 5 and kf1.world_epoch == 0
    np.testing.assert_allclose(kf1.T_prev_kf_kf, np.linalg.inv(kf0.T_world_cam)
                               @ kf1.T_world_cam, atol=1e-9)
    frames = [m for m in msgs if isinstance(m, FramePoses)]
    assert np.concatenate([f.frame_indices for f in frames]).tolist() == list(range(6))
    assert frames[-1].kf_ids.tolist() == [0, 1]
    np.testing.assert_allclose(frames[-1].T_kf_frame[1], np.eye(4), atol=1e-9)
    delta0 = msgs[1]
    assert isinstance(delta0, SubmapDelta)
    assert len(delta0.point_ids) > 0 and delta0.removed_ids.size == 0
    weights = msgs[2]
    assert isinstance(weights, DecoderWeights) and weights.round == 0
    assert weights.group_id == "a0" and weights.n_samples > 0
    assert set(weights.tensors) == set(link.odometry.decoders.state_dict())


def test_submap_delta_sends_only_new_or_changed_own_points() -> None:
    link = _link(frames_every=100, rounds=100)
    first = [m for m in _run(link, 0, 1) if isinstance(m, SubmapDelta)][0]
    pm = link.odometry.point_map
    assert sorted(first.point_ids.tolist()) == sorted(pm.point_id.tolist())
    # Nothing changed since: no delta.
    assert link._submap_delta() is None
    # One point removed, one feature changed.
    gone, touched = int(pm.point_id[0]), int(pm.point_id[1])
    pm.set_features(torch.tensor([1]), pm.features.detach()[1:2] + 1.0)
    pm.remove([gone])
    delta = link._submap_delta()
    assert delta.removed_ids.tolist() == [gone] and delta.point_ids.tolist() == [touched]


def test_acknowledged_points_go_back_as_features_alone() -> None:
    link = _link(frames_every=100, rounds=100)
    link.feature_rows = True
    first = [m for m in _run(link, 0, 1) if isinstance(m, SubmapDelta)][0]
    pm = link.odometry.point_map
    moved = [int(pm.point_id[1]), int(pm.point_id[2])]
    rows = torch.tensor([1, 2])
    pm.set_features(rows, pm.features.detach()[rows] + 1.0)
    # not acknowledged yet: the server may not hold them, so they go whole again
    delta = link._submap_delta()
    assert sorted(delta.point_ids.tolist()) == sorted(moved) and delta.feature_ids.size == 0
    link.on_ack(Ack(agent_id="a0", seq=first.seq))  # not the second delta yet
    pm.set_features(rows, pm.features.detach()[rows] + 1.0)
    delta = link._submap_delta()
    assert sorted(delta.point_ids.tolist()) == sorted(moved) and delta.feature_ids.size == 0
    link.on_ack(Ack(agent_id="a0", seq=delta.seq))
    pm.set_features(rows, pm.features.detach()[rows] + 1.0)
    delta = protocol.decode(protocol.encode(link._submap_delta()), expected=SubmapDelta)
    assert delta.point_ids.size == 0 and sorted(delta.feature_ids.tolist()) == sorted(moved)
    # what the server decodes is what the agent holds, and what its mirror says it holds
    got = dict(zip(delta.feature_ids.tolist(), delta.updated_feature_values(), strict=True))
    for row, pid in zip((1, 2), moved, strict=True):
        np.testing.assert_allclose(got[pid], pm.features.detach()[row].numpy(), atol=1e-2)
    pos = np.searchsorted(link.mirror.ids, delta.feature_ids)
    np.testing.assert_array_equal(link.mirror.features[pos], delta.updated_feature_values())


@pytest.mark.parametrize("bits", [8, 5])
def test_the_servers_copy_is_the_agents_mirror_with_feature_rows(bits: int) -> None:
    from cpslam.server.registry import Registry

    link = _link(frames_every=100, rounds=100, feature_rows=True, feature_codec="int8",
                 feature_threshold=0.1, feature_bits=bits)
    pm = link.odometry.point_map
    registry = Registry(pm.feature_dim)
    feature_rows, peak = 0, 0
    for i in range(12):
        for msg in _run(link, i, i + 1):
            msg = protocol.decode(protocol.encode(msg))
            if isinstance(msg, SubmapDelta):
                feature_rows += msg.feature_ids.size
                peak = max(peak, int(np.abs(msg.features_int8.astype(np.int32)).max(initial=0)))
            for ack in registry.handle(msg):
                link.on_ack(ack)
        # the field keeps learning features of points it has: some of them move enough
        rows = torch.arange(0, len(pm), 7)
        pm.set_features(rows, pm.features.detach()[rows] * 1.5 + 0.1)
    link.on_ack(registry.handle(link._submap_delta())[0])
    assert feature_rows > 0
    assert peak == 2 ** (bits - 1) - 1  # every row's largest element takes the top code
    rec = registry.agents["a0"]
    tables = [t for t in (rec.points, rec.pending_points) if len(t)]
    ids = np.concatenate([t.ids for t in tables])
    feats = np.concatenate([t.features for t in tables])
    xyz = np.concatenate([t.xyz for t in tables])
    order = np.argsort(ids)
    np.testing.assert_array_equal(ids[order], link.mirror.ids)
    np.testing.assert_array_equal(feats[order], link.mirror.features.astype(np.float16))
    own = pm.point_id.numpy()
    np.testing.assert_array_equal(np.sort(own), link.mirror.ids)
    # positions travel in fixed point: a quarter of a millimetre at most
    local = pm.xyz_local.detach().numpy()[np.argsort(own)]
    assert np.abs(xyz[order] - local).max() <= protocol.XYZ_STEP_M / 2 + 1e-6


def test_a_delta_of_removals_only_goes_out_with_int8_features() -> None:
    link = _link(frames_every=100, rounds=100, feature_codec="int8", feature_threshold=0.1)
    _run(link, 0, 1)
    gone = int(link.odometry.point_map.point_id[0])
    link.odometry.point_map.remove([gone])
    delta = protocol.decode(protocol.encode(link._submap_delta()), expected=SubmapDelta)
    assert delta.removed_ids.tolist() == [gone] and delta.point_ids.size == 0
    assert delta.feature_values().shape == (0, link.odometry.point_map.feature_dim)


def test_outbox_trimmed_by_acks(warm) -> None:
    link = _link()
    msgs = _run(link, 0, 1)
    n = len(msgs)
    assert [m.seq for m in link.unacked()] == list(range(n))
    assert link.on_ack(Ack(agent_id="other", seq=n)) == 0
    assert link.on_ack(Ack(agent_id="a0", seq=1)) == 2
    assert [m.seq for m in link.unacked()] == list(range(2, n))
    assert link.on_ack(Ack(agent_id="a0", seq=0)) == 0  # an older ack changes nothing
    link.on_ack(Ack(agent_id="a0", seq=n - 1))
    assert link.unacked() == [] and link.next_seq == n


def test_alignment_moves_poses_and_map_together() -> None:
    link = _link()
    _run(link, 0, 6)
    odo = link.odometry
    xyz_before = odo.point_map.xyz_world().double().numpy()
    kf_before = {kf.kf_id: kf.T_world_cam.copy() for kf in odo.keyframes}
    _, traj_before = odo.trajectory()
    T = se3_exp(np.array([0.5, -0.2, 1.0, 0.1, -0.3, 0.2]))
    assert link.apply_update(_update(link, 1, T))
    assert not link.apply_update(_update(link, 1, T))  # replayed seq: ignored
    xyz = odo.point_map.xyz_world().double().numpy()
    np.testing.assert_allclose(xyz, xyz_before @ T[:3, :3].T + T[:3, 3], atol=1e-4)
    for kf in odo.keyframes:
        np.testing.assert_allclose(kf.T_world_cam, T @ kf_before[kf.kf_id], atol=1e-9)
        np.testing.assert_allclose(odo.point_map.keyframe_pose(kf.kf_id).numpy(),
                                   kf.T_world_cam, atol=1e-9)
    _, traj = odo.trajectory()
    np.testing.assert_allclose(traj, T @ traj_before, atol=1e-9)
    assert link.epoch == 1 and np.allclose(link.T_group_agent, T)
    # Tracking continues in the group frame, and keyframes say which world they are in.
    msgs = _run(link, 6, 11)
    kf = [m for m in msgs if isinstance(m, KeyframeMsg)][0]
    assert kf.world_epoch == 1
    step = np.linalg.inv(traj[-1]) @ odo.trajectory()[1][-1]
    assert np.linalg.norm(step[:3, 3]) < 0.05  # no jump back to the old world
    np.testing.assert_allclose(kf.T_world_cam, odo.keyframes.get(kf.kf_id).T_world_cam)
    with pytest.raises(ValueError, match="expected 11 poses"):
        odo.set_frame_poses(odo.trajectory()[1][:-1])


def test_corrected_keyframe_moves_its_points_and_frames() -> None:
    link = _link()
    _run(link, 0, 8)
    odo = link.odometry
    pm = odo.point_map
    rows1 = (pm.anchor_kf == 1).nonzero(as_tuple=True)[0]
    rows0 = (pm.anchor_kf == 0).nonzero(as_tuple=True)[0]
    xyz_before = pm.xyz_world().double().numpy()
    _, traj_before = odo.trajectory()
    fix = se3_exp(np.array([0.05, 0.0, 0.0, 0.0, 0.0, 0.02]))
    T1 = fix @ odo.keyframes.get(1).T_world_cam
    link.apply_update(_update(link, 1, np.eye(4), kf_ids=[0, 1],
                              poses=np.stack([odo.keyframes.get(0).T_world_cam, T1]), epoch=0))
    xyz = pm.xyz_world().double().numpy()
    np.testing.assert_allclose(xyz[rows0.numpy()], xyz_before[rows0.numpy()], atol=1e-5)
    if len(rows1):
        moved = xyz_before[rows1.numpy()] @ fix[:3, :3].T + fix[:3, 3]
        np.testing.assert_allclose(xyz[rows1.numpy()], moved, atol=1e-4)
    _, traj = odo.trajectory()
    np.testing.assert_allclose(traj[:5], traj_before[:5], atol=1e-9)  # frames of kf 0
    np.testing.assert_allclose(traj[5:], fix @ traj_before[5:], atol=1e-9)  # frames of kf 1


def _foreign(link: AgentLink, n: int = 5, removed=()) -> ForeignPoints:
    F = link.odometry.point_map.feature_dim
    T_kf = se3_exp(np.array([0.0, 0.0, 5.0, 0.0, 0.0, 0.0]))
    xyz = np.column_stack([np.arange(n) * 0.3, np.zeros(n), np.full(n, 1.0)]).astype(np.float32)
    return ForeignPoints(
        source_agent_id="b1", kf_ids=np.array([7], np.int32), T_group_kf=T_kf[None],
        point_ids=np.arange(n, dtype=np.int64), anchor_kf_ids=np.full(n, 7, np.int32),
        xyz_local=xyz, features=np.full((n, F), 0.5, np.float16),
        colors=np.full((n, 3), 9, np.uint8), removed_ids=np.asarray(removed, np.int64))


def test_foreign_points_join_the_map_and_are_never_sent_back() -> None:
    link = _link(frames_every=100, rounds=100)
    _run(link, 0, 2)
    pm = link.odometry.point_map
    own = len(pm)
    upd = _update(link, 1, np.eye(4), foreign=[_foreign(link)], group="a0",
                  members=("a0", "b1"), epoch=0)
    assert link.apply_update(upd)
    assert link.foreign_index == {"b1": 1} and len(pm) == own + 5
    assert link.odometry.fused
    rows = (pm.agent_id == 1).nonzero(as_tuple=True)[0]
    xyz = pm.xyz_world()[rows].double().numpy()
    np.testing.assert_allclose(xyz[:, 2], 6.0, atol=1e-5)
    # The next delta carries own points only.
    pm.set_features(rows, pm.features.detach()[rows] + 1.0)
    link.mirror = SubmapMirror(pm.feature_dim)  # force a full resend of own points
    delta = link._submap_delta()
    assert len(delta.point_ids) == own
    # A later block removes two of them and moves the keyframe.
    block = _foreign(link, n=0, removed=[0, 1])
    link.apply_update(_update(link, 2, np.eye(4), foreign=[block], members=("a0", "b1"),
                              epoch=0))
    assert len(pm) == own + 3


def test_group_decoder_loaded_and_rounds_tracked() -> None:
    link = _link()
    _run(link, 0, 1)
    dec = link.odometry.decoders
    tensors = {k: np.full(tuple(v.shape), 0.25, np.float32) for k, v in dec.state_dict().items()}
    other = GroupDecoder(group_id="g2", round=4, members=["b1"], n_samples=10, tensors=tensors)
    assert not link.apply_decoder(other)  # another group's: kept for later
    mine = GroupDecoder(group_id="a0", round=1, members=["a0", "b1"], n_samples=10,
                        tensors=tensors)
    assert link.apply_decoder(mine) and link.round == 1
    for v in dec.state_dict().values():
        assert torch.all(v == 0.25)
    assert not link.apply_decoder(mine)  # same round again: ignored
    # Joining g2 loads its waiting decoder; later weights answer g2's round.
    link.apply_update(_update(link, 1, np.eye(4), group="g2", members=("a0", "b1"), epoch=1))
    assert link.group_id == "g2" and link.round == 4
    msgs = _run(link, 1, 6)
    weights = [m for m in msgs if isinstance(m, DecoderWeights)][0]
    assert weights.group_id == "g2" and weights.round == 4


def test_image_request_answered_from_the_keyframe_store(warm) -> None:
    link, _ = warm
    reply = link.answer_image(KeyframeImageRequest(agent_id="a0", kf_id=1))
    assert isinstance(reply, KeyframeImage)
    store = link.odometry.keyframes
    full = store.intrinsics  # the processed frame's size: registration at full resolution
    assert (reply.width, reply.height, reply.fx) == (full.width, full.height, full.fx)
    rgb, depth = store.full_rgbd(1)
    # inverse depth in steps of 0.5 mm x depth^2 on the wire: off by half a step at most
    assert (reply.depth_encoding, reply.depth_scale) == ("inverse", 2000.0)
    step_m = 0.5e-3 * depth.astype(np.float64) ** 2
    assert (np.abs(reply.depth_metres() - depth) <= 0.51 * step_m + 1e-6).all()
    assert rgb.shape == (full.height, full.width, 3)
    protocol.decode(protocol.encode(reply), expected=KeyframeImage)
    missing = link.answer_image(KeyframeImageRequest(agent_id="a0", kf_id=99))
    assert isinstance(missing, ErrorReply) and missing.code == "not_found"


def test_noisy_images_go_smaller_only_once_the_agent_has_merged(warm) -> None:
    from cpslam.agent.images import ImageReplies

    link, _ = warm
    kept = link.images, link.group_members
    link.images = ImageReplies(noisy_scale=0.5)
    link.images.noise.update({97: 2.0, 98: 2.0})  # keyframes answered before were noisy
    try:
        request = KeyframeImageRequest(agent_id="a0", kf_id=1)
        alone = link.answer_image(request)
        link.group_members = ["a0", "b0"]
        merged = link.answer_image(request)
    finally:
        link.images, link.group_members = kept
    full = link.odometry.keyframes.intrinsics
    assert link.images is kept[0] and alone.width == full.width
    assert merged.width == round(full.width / 2)


def test_image_request_at_half_scale_gets_half_the_size_with_matching_intrinsics(warm) -> None:
    link, _ = warm
    full = link.answer_image(KeyframeImageRequest(agent_id="a0", kf_id=1))
    half = link.answer_image(KeyframeImageRequest(agent_id="a0", kf_id=1, scale=0.5,
                                                  want_rgb=False))
    assert isinstance(half, KeyframeImage) and half.rgb is None
    intr = link.odometry.keyframes.intrinsics.scaled(0.5)
    assert (half.width, half.height) == (intr.width, intr.height)
    assert (half.width, half.height) == (round(full.width / 2), round(full.height / 2))
    np.testing.assert_allclose([half.fx, half.fy, half.cx, half.cy],
                               [intr.fx, intr.fy, intr.cx, intr.cy])
    # Every other pixel of the full depth, where the 2x2 block around it agrees, is what a
    # half-size depth holds there (no holes invented, no edge's two sides mixed).
    d_full, d_half = full.depth_metres(), half.depth_metres()
    assert (d_half > 0).mean() >= 0.9 * (d_full > 0).mean()
    block = d_full[:2 * half.height, :2 * half.width].reshape(half.height, 2, half.width, 2)
    flat = (block.max(axis=(1, 3)) - block.min(axis=(1, 3)) < 1e-3) & (block.min(axis=(1, 3)) > 0)
    np.testing.assert_allclose(d_half[flat], block.mean(axis=(1, 3))[flat], atol=1.5e-3)
    protocol.decode(protocol.encode(half), expected=KeyframeImage)


def test_inverse_depth_reply_keeps_its_coding_when_answered_again(warm) -> None:
    from cpslam.agent.images import image_reply, rescale_reply

    link, _ = warm
    store = link.odometry.keyframes
    rgb, depth = store.full_rgbd(1)
    request = KeyframeImageRequest(agent_id="a0", kf_id=1)
    reply = image_reply(request, rgb, depth, store.intrinsics, depth_step_mm_per_m2=1.0)
    back = protocol.decode(protocol.encode(reply), expected=KeyframeImage)
    assert (back.depth_encoding, back.depth_scale) == ("inverse", 1000.0)
    ok = depth > 0
    step_m = 1e-3 * depth[ok].astype(np.float64) ** 2  # 1 mm x depth^2
    assert (np.abs(back.depth_metres()[ok] - depth[ok]) <= 0.51 * step_m + 1e-6).all()
    assert (back.depth_metres()[~ok] == 0).all()
    half = rescale_reply(back, KeyframeImageRequest(agent_id="a0", kf_id=1, scale=0.5))
    assert (half.depth_encoding, half.depth_scale) == ("inverse", 1000.0)
    assert half.width == round(back.width / 2)


def _wall() -> tuple[Intrinsics, np.ndarray, np.ndarray, KeyframeImageRequest]:
    """A 160x120 camera, the exact depth [H, W] (m) of a slanted wall 1.5-2.9 m away, grey
    colour and a full-size image request for keyframe 1."""
    intr = Intrinsics(fx=160.0, fy=160.0, cx=79.5, cy=59.5, width=160, height=120)
    u = np.linspace(-1.0, 1.0, 160)[None, :]
    v = np.linspace(-1.0, 1.0, 120)[:, None]
    wall = (1.0 / (0.5 + 0.1 * u + 0.05 * v)).astype(np.float32)
    return (intr, wall, np.full((120, 160, 3), 128, np.uint8),
            KeyframeImageRequest(agent_id="a0", kf_id=1))


def test_noisy_depth_is_answered_at_the_noisy_scale_and_exact_depth_as_asked() -> None:
    from cpslam.agent.images import ImageReplies

    rng = np.random.default_rng(0)
    intr, wall, rgb, full = _wall()
    noisy = (wall + rng.normal(0.0, 1.5e-3, wall.shape) * wall**2).astype(np.float32)
    replies = ImageReplies(noisy_scale=0.5, noisy_depth_mm_per_m2=0.3)
    exact = replies.answer(full, rgb, wall, intr)
    assert (exact.width, exact.height) == (160, 120) and not replies.noisy
    for kf in (2, 3):  # the median of the keyframes seen decides
        replies.answer(full.model_copy(update={"kf_id": kf}), rgb, noisy, intr)
    alone = replies.answer(full.model_copy(update={"kf_id": 4}), rgb, noisy, intr,
                           merged=False)  # no pose to start from yet: features need full size
    assert replies.noisy and alone.width == 160
    half = replies.answer(full.model_copy(update={"kf_id": 4}), rgb, noisy, intr)
    assert (half.width, half.height, half.fx) == (80, 60, 80.0)
    replies.answer(full, rgb, noisy, intr)  # keyframe 1 again: it keeps its first measure
    assert list(replies.noise) == [1, 2, 3, 4] and replies.noise[1] < 0.1
    smaller = replies.answer(full.model_copy(update={"scale": 0.4, "kf_id": 5}), rgb, noisy,
                             intr)
    assert smaller.width == 64  # a smaller request is answered as asked
    blind = ImageReplies(noisy_scale=1.0, step_noise_ratio=0)  # answers as asked
    assert blind.answer(full, rgb, noisy, intr).width == 160 and not blind.noise
    with pytest.raises(ValueError, match="noisy_scale"):
        ImageReplies(noisy_scale=0.0)
    with pytest.raises(ValueError, match="step_noise_ratio"):
        ImageReplies(step_noise_ratio=-1.0)


def test_depth_steps_follow_the_measured_noise() -> None:
    """Inverse depth goes in steps of twice the noise (sigma / z²) measured so far, at most
    `MAX_NOISE_STEP`: a plane with noise 0.6 mm/m² in steps near 1.2 mm/m² and within half a
    step of its values, one with noise 1.5 in steps of 1.5, the exact one in the configured
    0.5; millimetres stay millimetres."""
    from cpslam.agent.images import MAX_NOISE_STEP, ImageReplies

    rng = np.random.default_rng(1)
    intr, wall, rgb, full = _wall()
    exact = ImageReplies(depth_step_mm_per_m2=0.5).answer(full, rgb, wall, intr)
    assert exact.depth_encoding == "inverse" and exact.depth_scale == pytest.approx(2000.0)
    steps = []
    for sigma in (0.6e-3, 1.5e-3):
        noisy = (wall + rng.normal(0.0, sigma, wall.shape) * wall**2).astype(np.float32)
        replies = ImageReplies(depth_step_mm_per_m2=0.5)
        reply = replies.answer(full, rgb, noisy, intr)
        steps.append(1000.0 / reply.depth_scale)
        assert steps[-1] == pytest.approx(replies.depth_step())
        # what the server decodes is the depth to within half a step of z² (mm at 1 m)
        err_mm = np.abs(reply.depth_metres() - noisy) / noisy**2 * 1e3
        assert err_mm.max() <= 0.5 * steps[-1] * 1.01
    assert 1.0 < steps[0] < 1.4 and steps[1] == pytest.approx(MAX_NOISE_STEP)
    mm = ImageReplies(depth_step_mm_per_m2=0.0).answer(full, rgb, noisy, intr)
    assert mm.depth_encoding == "linear"


def test_joining_a_group_offers_weights_at_the_next_mapping() -> None:
    link = _link(rounds=100)  # without a merge, weights would wait for 100 mapping calls
    msgs = _run(link, 0, 3)
    assert not any(isinstance(m, DecoderWeights) for m in msgs)
    assert link.apply_update(_update(link, 1, np.eye(4), group="g", members=("a0", "b0")))
    msgs = _run(link, 3, 6)
    weights = [m for m in msgs if isinstance(m, DecoderWeights)]
    assert len(weights) == 1 and weights[0].group_id == "g" and weights[0].round == 0


def test_shared_decoder_is_fitted_to_the_map_before_the_next_frame_is_tracked() -> None:
    # Decoders that do not match the agent's features (what an average of two agents' is)
    # make tracking worse until the map is re-fitted; the re-fit runs before the next track.
    other = field_spec(load_config("tiny", env={}).field).decoders(seed=123).state_dict()
    losses = {}
    for refit in (True, False):
        link = _link(rounds=100)
        link.odometry.iters_after_fusion = 30
        _run(link, 0, 4)  # frames 0-3; tiny maps every 5 frames, so frame 4 does not map
        tensors = {k: (0.5 * v + 0.5 * other[k]).numpy()
                   for k, v in link.odometry.decoders.state_dict().items()}
        assert link.apply_decoder(GroupDecoder(group_id="a0", round=1, members=["a0"],
                                               n_samples=1, tensors=tensors))
        assert link.odometry.fused
        if not refit:
            link.odometry.fused = False
        result = link.odometry.step(_frame(4))
        assert result.map_steps == (30 if refit else 0)
        assert not link.odometry.fused
        # The median depth error, not the loss: "lm" normalises its loss by the residuals'
        # own robust scale, which hides how well the map explains the frame.
        losses[refit] = result.track_residual_m
    assert losses[True] < 0.5 * losses[False], losses


def test_a_wrong_shaped_group_decoder_is_dropped_and_the_agent_goes_on(caplog) -> None:
    link = _link()
    _run(link, 0, 1)
    dec = link.odometry.decoders
    before = {k: v.clone() for k, v in dec.state_dict().items()}
    name = next(iter(before))
    wrong = {k: np.zeros(tuple(v.shape), np.float32) for k, v in before.items()}
    wrong[name] = np.zeros((3, 1), np.float32)  # a server on another preset
    msg = GroupDecoder(group_id="a0", round=1, members=["a0"], n_samples=1, tensors=wrong)
    with caplog.at_level("WARNING", logger="cpslam.agent.link"):
        assert not link.apply_decoder(msg)
    assert link.round == 0
    assert f"tensors['{name}'] has shape [3, 1], expected" in caplog.text
    for k, v in dec.state_dict().items():
        assert torch.equal(v, before[k])
    missing = {k: v for k, v in wrong.items() if k != name}
    assert not link.apply_decoder(GroupDecoder(group_id="a0", round=1, members=["a0"],
                                               n_samples=1, tensors=missing))
    assert "names differ" in caplog.text
    _run(link, 1, 2)  # the agent still tracks


def test_decoders_held_for_other_groups_are_capped() -> None:
    from cpslam.agent.link import MAX_WAITING_DECODERS

    link = _link()
    tensors = {k: v.detach().numpy() for k, v in link.odometry.decoders.state_dict().items()}
    for g in range(MAX_WAITING_DECODERS + 10):
        link.apply_decoder(GroupDecoder(group_id=f"g{g}", round=1, members=["b"], n_samples=1,
                                        tensors=tensors))
    assert len(link._decoders_waiting) == MAX_WAITING_DECODERS
    assert f"g{MAX_WAITING_DECODERS + 9}" in link._decoders_waiting  # the newest kept


def test_submap_deltas_coalesce_mapping_calls_and_travel_as_int8() -> None:
    link = _link(frames_every=100, rounds=100, submap_every_mappings=2, feature_codec="int8",
                 feature_threshold=0.05)
    mapped, deltas = [], []
    for i in range(11):
        frame = _frame(i)
        result = link.odometry.step(frame)
        mapped.append(result.map_steps > 0)
        deltas.append([m for m in link.after_step(frame, result) if isinstance(m, SubmapDelta)])
    calls = np.flatnonzero(mapped)
    assert len(calls) >= 3
    # the first call's map at once, then a delta after every second mapping call only
    assert [i for i, d in enumerate(deltas) if d] == calls[0::2].tolist()
    last = [d for d in deltas if d][-1][0]
    assert last.features is None and last.features_int8.dtype == np.int8
    # the mirror holds exactly what the server decodes
    pos = np.searchsorted(link.mirror.ids, last.point_ids)
    np.testing.assert_array_equal(link.mirror.features[pos], last.feature_values())
    # a change below the threshold stays local; above it, the point goes out again
    link._submap_delta()  # whatever the last mapping call moved
    pm = link.odometry.point_map
    pid = int(link.mirror.ids[0])
    row = int((pm.point_id == pid).nonzero()[0, 0])
    scale = float(np.abs(link.mirror.features[0]).max())
    base = pm.features.detach()[row:row + 1].clone()
    pm.set_features(torch.tensor([row]), base + 0.01 * scale)
    assert link._submap_delta() is None
    pm.set_features(torch.tensor([row]), base + 0.2 * scale)
    assert pid in link._submap_delta().point_ids.tolist()
    # the end of the stream sends what the coalescing still held back
    pm.set_features(torch.tensor([row]), base + 0.6 * scale)
    assert any(isinstance(m, SubmapDelta) for m in link.finish())


def test_decoder_weights_are_int8_deltas_against_the_loaded_group_decoder() -> None:
    link = _link(rounds=1, decoder_delta=True)
    first = [m for m in _run(link, 0, 1) if isinstance(m, DecoderWeights)][0]
    assert first.base_round is None and first.tensors_f16 is not None  # nothing agreed yet
    dec = link.odometry.decoders
    base = {k: v.detach().numpy().copy() + 0.01 for k, v in dec.state_dict().items()}
    assert link.apply_decoder(GroupDecoder(group_id="a0", round=2, members=["a0", "b1"],
                                           n_samples=10, tensors=base))
    weights = [m for m in _run(link, 1, 6) if isinstance(m, DecoderWeights)][-1]
    assert weights.base_round == 2 and weights.tensors_f16 is None
    local = {k: v.detach().numpy() for k, v in dec.state_dict().items()}
    for name, delta in weights.values().items():
        step = np.abs(local[name] - base[name]).max() / 254 + 1e-7
        np.testing.assert_allclose(base[name] + delta, local[name], atol=step)
    # another group: no agreed base there yet, so full weights again
    link.apply_update(_update(link, 1, np.eye(4), group="g2", members=("a0", "b1"), epoch=1))
    weights = [m for m in _run(link, 6, 11) if isinstance(m, DecoderWeights)][-1]
    assert weights.group_id == "g2" and weights.base_round is None and weights.tensors_f16


def test_held_points_go_again_only_with_every_nth_delta_and_the_last() -> None:
    """With a period longer than the run, points the server holds wait for the last delta
    (`finish`): only new points may go before; with a period of 1 they go with each."""
    deltas, lasts = {}, {}
    for every in (1, 1000):
        link = _link(held_every_deltas=every, feature_rows=True)
        deltas[every] = [m for m in _run(link, 0, 12) if isinstance(m, SubmapDelta)]
        lasts[every] = [m for m in link.finish() if isinstance(m, SubmapDelta)]
    first = set(deltas[1000][0].point_ids.tolist())
    assert first == set(deltas[1][0].point_ids.tolist())
    # the held points moved: with a period of 1 they go again (whole: nothing is acked here)
    assert any(first & set(d.point_ids.tolist()) for d in deltas[1][1:])
    for delta in deltas[1000][1:]:
        assert not delta.feature_ids.size and not first & set(delta.point_ids.tolist())
    last = lasts[1000][0]
    assert first <= {*last.point_ids.tolist(), *last.feature_ids.tolist()}
    with pytest.raises(ValueError, match="held_every_deltas"):
        _link(held_every_deltas=0)

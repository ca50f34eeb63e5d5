"""Fusion: grid-filtered group map, foreign points only where needed and only once,
decoder fine-tune lowers the mapping loss."""

from __future__ import annotations

import numpy as np
import torch
from spec_helpers import spec

from cpslam.common.camera import Intrinsics
from cpslam.common.field import NeuralPointMap
from cpslam.server.fusion import MemberMap, View, finetune_decoders, fuse
from cpslam.server.ledger import ForeignTracker

CELL = 0.1


def member(agent, index, xyz, kf_pose=None, f=4):
    pm = NeuralPointMap(f, CELL, index)
    pm.set_keyframe_poses([0], np.eye(4) if kf_pose is None else kf_pose)
    n = len(xyz)
    state = pm.state_dict()
    state.update(anchor_kf=torch.zeros(n, dtype=torch.int64),
                 xyz_local=torch.as_tensor(xyz, dtype=torch.float32),
                 features=torch.randn(n, f, generator=torch.Generator().manual_seed(index)),
                 agent_id=torch.full((n,), index, dtype=torch.int32),
                 point_id=torch.arange(n), color=torch.zeros(n, 3, dtype=torch.uint8),
                 next_point_id=torch.tensor([[index, n]]))
    pm.load_state_dict(state)
    return MemberMap(agent, index, pm)


def grid_points(x0, x1):
    xs = np.arange(x0, x1, CELL) + CELL / 2
    return np.stack([xs, np.full_like(xs, 0.05), np.full_like(xs, 0.05)], 1)


def test_fuse_keeps_one_point_per_cell():
    a = member("a", 0, grid_points(0, 1.0))
    b = member("b", 1, grid_points(0.5, 1.5) + 0.01)
    fused = fuse([a, b], 4, CELL)
    assert len(fused) == 15
    assert len(fuse([a, b], 4, CELL, grid_filter=False)) == 20


def test_foreign_points_cover_only_new_cells_and_are_sent_once_acknowledged():
    a = member("a", 0, grid_points(0, 1.0))
    b = member("b", 1, grid_points(0.5, 1.5))
    tracker = ForeignTracker()
    versions = {"b": np.zeros(10, np.int64)}
    (block,) = tracker.blocks(a, [b], versions, CELL, seq=1)
    assert block.source_agent_id == "b" and block.kf_ids.tolist() == [0]
    assert sorted(block.point_ids.tolist()) == [5, 6, 7, 8, 9]  # x in [1.0, 1.5)
    # Not acknowledged: the next update carries them again (a lost update is repaired).
    (again,) = tracker.blocks(a, [b], versions, CELL, seq=2)
    assert sorted(again.point_ids.tolist()) == [5, 6, 7, 8, 9]
    assert tracker.delivered("a") == {} and tracker.pending("a")
    assert tracker.acked("a", 2) and not tracker.acked("a", 2)  # a repeat confirms nothing
    assert tracker.delivered("a") == {"b": dict.fromkeys([5, 6, 7, 8, 9], 0)}
    (quiet,) = tracker.blocks(a, [b], versions, CELL, seq=3)
    assert len(quiet.point_ids) == 0 and len(quiet.removed_ids) == 0
    versions["b"][7] = 3  # point 7 changed
    (changed,) = tracker.blocks(a, [b], versions, CELL, seq=4)
    assert changed.point_ids.tolist() == [7]
    assert 7 not in tracker.delivered("a")["b"]  # in flight: its state is unknown
    state = tracker.state_dict()
    other = ForeignTracker()
    other.load_state_dict(state)
    assert other.held == tracker.held and other.maybe == tracker.maybe


def test_foreign_update_split_into_parts_each_consistent_alone():
    a = member("a", 0, grid_points(0, 1.0))
    b = member("b", 1, grid_points(0.5, 1.5))
    tracker = ForeignTracker()
    versions = {"b": np.zeros(10, np.int64)}
    parts = tracker.parts(a, [b], versions, CELL, first_seq=1, max_points=2)
    assert [len(p[0].point_ids) for p in parts] == [2, 2, 1]
    assert all(p[0].kf_ids.tolist() == [0] for p in parts)  # any part is usable alone
    # Part 2 (seq 2) was lost; parts 1 and 3 arrived and were acknowledged.
    assert tracker.acked("a", 1) and tracker.acked("a", 3)
    delivered = set(tracker.delivered("a")["b"])
    assert delivered == set(parts[0][0].point_ids) | set(parts[2][0].point_ids)
    (repair,) = tracker.blocks(a, [b], versions, CELL, seq=4)
    assert set(repair.point_ids.tolist()) == set(parts[1][0].point_ids.tolist())


def test_finetune_lowers_the_loss_on_a_plane():
    intr = Intrinsics(40.0, 40.0, 15.5, 11.5, 32, 24)
    depth = np.full((24, 32), 1.0, np.float32)
    rgb = np.full((24, 32, 3), 200, np.uint8)
    v, u = np.mgrid[0:24:2, 0:32:2]
    xyz = np.stack([(u - 15.5) / 40.0, (v - 11.5) / 40.0, np.ones_like(u, float)], -1)
    m = member("a", 0, xyz.reshape(-1, 3), f=4)
    small = spec(feature_dim=4, pe_offset_order=2, c_hidden=16, g_hidden=16, u_hidden=16,
                 u_layers=1, radius=0.1)
    dec = small.decoders(seed=0)
    views = [View(rgb, depth, np.eye(4), intr)]
    losses = finetune_decoders(dec, m.point_map, views, iters=15, lr=0.02, seed=0, spec=small,
                               color_weight=0.2, n_pixels=64)
    assert len(losses) == 15 and np.mean(losses[-3:]) < 0.8 * np.mean(losses[:3])
    assert finetune_decoders(dec, m.point_map, [], 5, 0.01, 0, small, color_weight=0.2) == []

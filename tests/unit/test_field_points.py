"""NeuralPointMap: grid filter, anchoring to keyframes, merge, save/load."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from cpslam.common.field import NeuralPointMap
from cpslam.common.field.grid import grid_winners


def _pose(angle: float, t: tuple[float, float, float]) -> np.ndarray:
    T = np.eye(4)
    c, s = math.cos(angle), math.sin(angle)
    T[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    T[:3, 3] = t
    return T


def _add(m: NeuralPointMap, xyz: torch.Tensor, kf: int, agent: int | None = None) -> torch.Tensor:
    n = len(xyz)
    feats = torch.arange(n * m.feature_dim, dtype=torch.float32).reshape(n, m.feature_dim)
    colors = torch.full((n, 3), 7, dtype=torch.uint8)
    return m.add_points(xyz, kf, feats, colors, agent_id=agent)


def test_grid_filter_keeps_one_point_per_cell_nearest_centre() -> None:
    gen = torch.Generator().manual_seed(0)
    xyz = torch.rand(4000, 3, generator=gen, dtype=torch.float64) * 2.0 - 1.0
    cell = 0.25
    keep = grid_winners(xyz.numpy(), cell)
    cells = np.floor(xyz.numpy() / cell).astype(np.int64)
    d2 = (((cells + 0.5) * cell - xyz.numpy()) ** 2).sum(1)
    kept_cells = {tuple(c) for c in cells[keep]}
    assert len(kept_cells) == int(keep.sum())  # one per cell
    assert kept_cells == {tuple(c) for c in cells}  # every occupied cell keeps one
    for c in list(kept_cells)[:50]:
        members = np.nonzero((cells == c).all(1))[0]
        winner = members[keep[members]]
        assert d2[winner[0]] == d2[members].min()


def test_add_points_keeps_existing_and_filters_new() -> None:
    m = NeuralPointMap(feature_dim=4, cell_size=1.0)
    m.set_keyframe_poses(0, np.eye(4))
    first = _add(m, torch.tensor([[0.1, 0.1, 0.1], [3.5, 3.5, 3.5]]), 0)
    assert first.tolist() == [0, 1]
    # Cell (0,0,0) is taken: the new point nearer its centre is still dropped. Cell (1,1,1)
    # gets the new point nearest its centre of the two offered.
    second = _add(m, torch.tensor([[0.5, 0.5, 0.5], [1.1, 1.1, 1.1], [1.45, 1.5, 1.5]]), 0)
    assert second.tolist() == [2]
    torch.testing.assert_close(m.xyz_world()[2], torch.tensor([1.45, 1.5, 1.5]))
    assert len(m) == 3 and m.features.shape == (3, 4)
    assert m.color.dtype == torch.uint8 and m.agent_id.dtype == torch.int32


def test_no_scene_bounds() -> None:
    m = NeuralPointMap(feature_dim=2, cell_size=0.14)
    m.set_keyframe_poses(0, np.eye(4))
    xyz = torch.tensor([[1.0e4, -1.0e4, 2.0], [-1.0e4, 1.0e4, -3.0], [1.0e4, 1.0e4, 1.0e4]])
    assert len(_add(m, xyz, 0)) == 3
    assert len(_add(m, xyz + 0.01, 0)) == 0  # same cells, far from the origin
    torch.testing.assert_close(m.xyz_world(), xyz)


def test_keyframe_pose_change_moves_only_its_points() -> None:
    m = NeuralPointMap(feature_dim=3, cell_size=0.1)
    m.set_keyframe_poses([0, 1], np.stack([np.eye(4), _pose(0.3, (1.0, 0.0, 0.0))]))
    _add(m, torch.tensor([[0.0, 0.0, 1.0], [0.5, 0.0, 1.0]]), 0)
    _add(m, torch.tensor([[2.0, 1.0, 1.0], [2.5, 1.0, 1.0]]), 1)
    before = m.xyz_world().clone()
    version = m.version
    correction = _pose(-0.2, (0.0, 0.5, 0.2))
    m.set_keyframe_poses(1, correction @ m.keyframe_pose(1).numpy())
    after = m.xyz_world()
    assert m.version > version
    torch.testing.assert_close(after[:2], before[:2])
    moved = before[2:].double() @ torch.from_numpy(correction[:3, :3]).T + torch.from_numpy(
        correction[:3, 3]
    )
    torch.testing.assert_close(after[2:], moved.float())
    assert m.neighbour_index().version == m.version


def test_unknown_keyframe_and_bad_input_raise() -> None:
    m = NeuralPointMap(feature_dim=2, cell_size=0.14)
    with pytest.raises(KeyError, match="keyframe 5"):
        m.add_points(torch.zeros(1, 3), 5, torch.zeros(1, 2), torch.zeros(1, 3, dtype=torch.uint8))
    m.set_keyframe_poses(0, np.eye(4))
    with pytest.raises(ValueError, match="features"):
        m.add_points(torch.zeros(1, 3), 0, torch.zeros(1, 3), torch.zeros(1, 3, dtype=torch.uint8))
    with pytest.raises(ValueError, match="rigid"):
        m.set_keyframe_poses(1, 2.0 * np.eye(4))


def test_remove_subset_and_ids_monotonic() -> None:
    m = NeuralPointMap(feature_dim=2, cell_size=0.1)
    m.set_keyframe_poses(0, np.eye(4))
    ids = _add(m, torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0]]), 0)
    assert m.remove(ids[1:2]) == 1
    assert m.point_id.tolist() == [0, 2]
    assert _add(m, torch.tensor([[5.0, 0.0, 0.0]]), 0).tolist() == [3]
    sub = m.subset(m.point_id >= 2)
    assert sub.point_id.tolist() == [2, 3] and len(m) == 3
    torch.testing.assert_close(sub.xyz_world(), m.xyz_world()[1:])
    assert sub.features.data_ptr() != m.features.data_ptr()


def test_merge_moves_other_map_and_filters() -> None:
    a = NeuralPointMap(feature_dim=2, cell_size=0.2, default_agent=0)
    a.set_keyframe_poses(0, np.eye(4))
    _add(a, torch.tensor([[0.1, 0.1, 0.1]]), 0)
    b = NeuralPointMap(feature_dim=2, cell_size=0.2, default_agent=1)
    b.set_keyframe_poses(0, np.eye(4))
    _add(b, torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]]), 0)
    T_a_b = _pose(0.0, (0.1, 0.1, 0.1))  # b's first point lands exactly on a's
    a.merge(b, T_a_b)
    assert len(a) == 2  # the duplicate in cell (0,0,0) is filtered
    assert a.has_keyframe(0, agent_id=1)
    torch.testing.assert_close(a.keyframe_pose(0, agent_id=1), torch.from_numpy(T_a_b))
    far = a.xyz_world()[a.agent_id == 1]
    torch.testing.assert_close(far, torch.tensor([[1.1, 1.1, 1.1]]))
    with pytest.raises(ValueError, match="keyframes"):
        a.merge(b, np.eye(4))


def test_save_load_round_trip(tmp_path: Path) -> None:
    m = NeuralPointMap(feature_dim=5, cell_size=0.1, default_agent=2)
    m.set_keyframe_poses([0, 3], np.stack([np.eye(4), _pose(1.0, (0.0, 1.0, 2.0))]))
    _add(m, torch.rand(50, 3, generator=torch.Generator().manual_seed(1)), 3)
    path = tmp_path / "sub" / "map.pt"
    m.save(path)
    loaded = NeuralPointMap.load(path)
    assert loaded.feature_dim == 5 and loaded.cell_size == 0.1 and loaded.default_agent == 2
    for name in ("anchor_kf", "xyz_local", "features", "agent_id", "point_id", "color"):
        assert torch.equal(getattr(loaded, name).detach(), getattr(m, name).detach()), name
    assert torch.equal(loaded.kf_poses, m.kf_poses)
    torch.testing.assert_close(loaded.xyz_world(), m.xyz_world())
    assert isinstance(loaded.features, torch.nn.Parameter)
    assert loaded.next_point_id == m.next_point_id
    torch.load(path, weights_only=True)  # plain tensors only


def test_load_rejects_bad_files(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="missing.pt"):
        NeuralPointMap.load(tmp_path / "missing.pt")
    bad = tmp_path / "bad.pt"
    torch.save({"format_version": 1}, bad)
    with pytest.raises(ValueError, match="bad.pt.*missing fields"):
        NeuralPointMap.load(bad)


def test_merge_rejects_duplicate_points_without_changing_the_map() -> None:
    a = NeuralPointMap(feature_dim=2, cell_size=0.2, default_agent=0)
    a.set_keyframe_poses(0, np.eye(4))
    _add(a, torch.tensor([[0.1, 0.1, 0.1]]), 0)
    b = NeuralPointMap(feature_dim=2, cell_size=0.2, default_agent=0)
    b.set_keyframe_poses(1, np.eye(4))
    _add(b, torch.tensor([[2.0, 2.0, 2.0]]), 1)  # point id 0 of agent 0 again
    with pytest.raises(ValueError, match="point id"):
        a.merge(b, np.eye(4))
    assert len(a) == 1 and len(a.kf_keys) == 1


def test_grid_filter_same_beyond_packed_range() -> None:
    gen = np.random.default_rng(2)
    xyz = gen.random((500, 3)) * 3.0
    keep = grid_winners(xyz, 0.5)
    far = grid_winners(xyz + np.array([0.0, 0.0, 1.0e6]), 0.5)  # cells beyond 2^20: row sort
    assert np.array_equal(keep, far)


def test_patch_points_back_projects_patch_centres() -> None:
    from cpslam.common.camera import Intrinsics
    from cpslam.common.field import FeatureCNN, patch_points

    intr = Intrinsics(fx=10.0, fy=10.0, cx=3.5, cy=3.5, width=8, height=8)
    depth = np.full((8, 8), 2.0, dtype=np.float32)
    depth[2, 2] = 0.0  # the first patch centre has no depth
    rgb = np.zeros((8, 8, 3), dtype=np.uint8)
    rgb[6, 6] = (10, 20, 30)
    T = _pose(0.0, (1.0, 0.0, 0.0))
    cnn = FeatureCNN(16, seed=0)
    xyz, feats, colors = patch_points(rgb, depth, intr, T, cnn, patch=4)
    assert xyz.shape == (3, 3) and feats.shape == (3, 16) and colors.dtype == torch.uint8
    # Centres (u, v) = (6, 2), (2, 6), (6, 6) remain, in row-major order.
    u = torch.tensor([6.0, 2.0, 6.0])
    v = torch.tensor([2.0, 6.0, 6.0])
    expected = torch.stack(((u - 3.5) / 10 * 2 + 1.0, (v - 3.5) / 10 * 2, torch.full((3,), 2.0)), 1)
    torch.testing.assert_close(xyz, expected)
    assert colors[2].tolist() == [10, 20, 30]
    torch.testing.assert_close(feats[2], cnn(rgb)[6, 6])

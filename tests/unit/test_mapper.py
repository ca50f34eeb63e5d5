"""Mapper: points only where the map does not explain the frame, grid filter, optimisation of
visible features only, and keyframe pose changes moving anchored points."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from spec_helpers import mapper_args, spec

from cpslam.agent.mapper import Mapper, View
from cpslam.common.camera import Intrinsics
from cpslam.common.field import Decoders, FeatureCNN, NeuralPointMap
from cpslam.common.field.grid import grid_winners
from cpslam.common.geometry import se3_exp

INTR = Intrinsics(fx=64.0, fy=64.0, cx=39.5, cy=29.5, width=80, height=60)
CELL = 0.1


def _wall_frame(depth_m: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """A textured fronto-parallel wall."""
    v, u = np.mgrid[0:60, 0:80]
    rgb = np.stack(((u * 3) % 256, (v * 4) % 256, ((u + v) * 2) % 256), -1).astype(np.uint8)
    return rgb, np.full((60, 80), depth_m, dtype=np.float32)


SPEC = spec(feature_dim=8, grid_size=CELL, c_hidden=16, g_hidden=16, u_hidden=16, u_layers=1,
            n_near=4, n_uniform=2, patch_size=4, k_neighbors=4, radius=0.12)


def _setup() -> tuple[NeuralPointMap, Decoders, FeatureCNN, Mapper]:
    point_map = SPEC.point_map(0, "cpu")
    point_map.set_keyframe_poses(0, np.eye(4))
    return point_map, SPEC.decoders(0), SPEC.cnn(0), Mapper(SPEC, **mapper_args())


def _view(rgb: np.ndarray, depth: np.ndarray, T: np.ndarray) -> View:
    return View(torch.from_numpy(rgb).float() / 255, torch.from_numpy(depth), T, INTR)


def test_points_added_only_where_unexplained_and_grid_filtered() -> None:
    point_map, decoders, cnn, mapper = _setup()
    rgb, depth = _wall_frame()
    first = mapper.add_points(point_map, decoders, cnn, rgb, depth, INTR, np.eye(4), 0)
    assert len(first) == len(point_map) > 20
    xyz = point_map.xyz_world().double().numpy()
    assert grid_winners(xyz, CELL).all()  # at most one point per cell
    # The same view again: everything is explained, nothing is added.
    again = mapper.add_points(point_map, decoders, cnn, rgb, depth, INTR, np.eye(4), 0)
    assert len(again) == 0
    # A view shifted sideways by 1 m: only the newly seen strip gets points, each farther
    # than the search radius from every old point.
    T_shift = se3_exp(np.array([1.0, 0, 0, 0, 0, 0]))
    new = mapper.add_points(point_map, decoders, cnn, rgb, depth, INTR, T_shift, 0)
    assert len(new) > 0
    new_xyz = point_map.xyz_world()[point_map.rows_of(new)].double().numpy()
    d = np.linalg.norm(new_xyz[:, None] - xyz[None], axis=-1).min(axis=1)
    assert (d > mapper.radius).all()
    assert new_xyz[:, 0].min() > xyz[:, 0].max() - CELL  # the new strip is on the right
    assert grid_winners(point_map.xyz_world().double().numpy(), CELL).all()


def test_depth_error_rule_adds_where_rendered_depth_misses() -> None:
    point_map, decoders, cnn, mapper = _setup()
    rgb, depth = _wall_frame(2.0)
    mapper.add_points(point_map, decoders, cnn, rgb, depth, INTR, np.eye(4), 0)
    n_before = len(point_map)
    mapper.add_points_depth_err = 0.05
    # An untrained map renders nothing sensible at 1.5 m: the closer wall is unexplained
    # everywhere, so points are added although the old ones are within reach of some pixels.
    _, near = _wall_frame(1.5)
    added = mapper.add_points(point_map, decoders, cnn, rgb, near, INTR, np.eye(4), 0,
                              torch.Generator().manual_seed(0))
    assert len(added) > 0 and len(point_map) == n_before + len(added)


def test_optimise_lowers_loss_and_leaves_unseen_points_alone() -> None:
    point_map, decoders, cnn, mapper = _setup()
    rgb, depth = _wall_frame()
    mapper.add_points(point_map, decoders, cnn, rgb, depth, INTR, np.eye(4), 0)
    # A far-away point nobody sees.
    point_map.add_points(torch.tensor([[50.0, 0.0, -3.0]]), 0, torch.ones(1, 8),
                         torch.zeros(1, 3, dtype=torch.uint8))
    before = point_map.features.detach().clone()
    gen = torch.Generator().manual_seed(0)
    result = mapper.optimise(point_map, decoders, [_view(rgb, depth, np.eye(4))], 60, 300, gen)
    assert result.steps == 60
    assert result.loss_last < 0.5 * result.loss_first
    after = point_map.features.detach()
    assert torch.equal(after[-1], before[-1])
    assert not torch.equal(after[:-1], before[:-1])


def test_checkpoints_publish_mid_way_and_change_nothing() -> None:
    """Checkpoints write the features so far into the map and call back every few steps;
    the optimisation ends with the same bits as without them."""
    rgb, depth = _wall_frame()
    finals, seen = [], []
    for every in (0, 7):
        point_map, decoders, cnn, mapper = _setup()
        mapper.add_points(point_map, decoders, cnn, rgb, depth, INTR, np.eye(4), 0)
        start = point_map.features.detach().clone()

        def checkpoint(point_map: NeuralPointMap = point_map) -> None:
            seen.append(point_map.features.detach().clone())

        mapper.optimise(point_map, decoders, [_view(rgb, depth, np.eye(4))], 30, 200,
                        torch.Generator().manual_seed(0), checkpoint_every=every,
                        checkpoint=checkpoint)
        finals.append((point_map.features.detach().clone(),
                       [p.detach().clone() for p in decoders.parameters()]))
    assert len(seen) == 4  # after steps 7, 14, 21, 28 of 30 (none after the last)
    assert not torch.equal(seen[0], start) and not torch.equal(seen[0], seen[1])
    assert torch.equal(finals[0][0], finals[1][0])
    assert all(torch.equal(a, b) for a, b in zip(finals[0][1], finals[1][1], strict=True))


def test_lr_scale_is_the_same_as_scaled_rates() -> None:
    """optimise(lr_scale=s) runs as a mapper whose two learning rates are s times larger:
    the same bits; and it changes the result."""
    rgb, depth = _wall_frame()
    finals = []
    for scale, rates in ((1.0, 2.0), (2.0, 1.0), (1.0, 1.0)):
        point_map, decoders, cnn, _ = _setup()
        args = mapper_args()
        mapper = Mapper(SPEC, **{**args, "lr_decoders": rates * args["lr_decoders"],
                                 "lr_features": rates * args["lr_features"]})
        mapper.add_points(point_map, decoders, cnn, rgb, depth, INTR, np.eye(4), 0)
        mapper.optimise(point_map, decoders, [_view(rgb, depth, np.eye(4))], 20, 200,
                        torch.Generator().manual_seed(0), lr_scale=scale)
        finals.append(torch.cat([point_map.features.detach().reshape(-1),
                                 *(p.detach().reshape(-1) for p in decoders.parameters())]))
    assert torch.equal(finals[0], finals[1])
    assert not torch.equal(finals[1], finals[2])


def test_keyframe_pose_change_moves_anchored_points() -> None:
    point_map, decoders, cnn, mapper = _setup()
    rgb, depth = _wall_frame()
    point_map.set_keyframe_poses(1, np.eye(4))
    ids0 = mapper.add_points(point_map, decoders, cnn, rgb, depth, INTR, np.eye(4), 0)
    T_side = se3_exp(np.array([3.0, 0, 0, 0, 0, 0]))
    ids1 = mapper.add_points(point_map, decoders, cnn, rgb, depth, INTR, T_side, 1)
    rows0, rows1 = point_map.rows_of(ids0), point_map.rows_of(ids1)
    before = point_map.xyz_world().clone()
    correction = se3_exp(np.array([0.0, 0.2, 0, 0, 0, 0.1]))
    point_map.set_keyframe_poses(1, correction)
    after = point_map.xyz_world()
    assert torch.equal(after[rows0], before[rows0])
    expected = before[rows1].double() @ torch.from_numpy(correction[:3, :3]).T \
        + torch.from_numpy(correction[:3, 3])
    torch.testing.assert_close(after[rows1].double(), expected, atol=1e-5, rtol=0)


def test_view_checks_shapes() -> None:
    rgb, depth = _wall_frame()
    with pytest.raises(ValueError, match="intrinsics"):
        View(torch.zeros(10, 10, 3), torch.zeros(10, 10), np.eye(4), INTR)
    view = _view(rgb, depth, np.eye(4))
    assert len(view.valid) == 60 * 80

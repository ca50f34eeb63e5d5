"""Keyframe store: downsampled copies, co-visibility by projected overlap, serialisation."""

from __future__ import annotations

import io

import numpy as np
import pytest
import torch

from cpslam.agent.keyframes import DEPTH_SCALE, KeyframeStore
from cpslam.common.camera import Intrinsics
from cpslam.common.geometry import se3_exp

INTR = Intrinsics(fx=64.0, fy=64.0, cx=39.5, cy=29.5, width=80, height=60)


def _frame(depth_m: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    rgb = np.random.default_rng(0).integers(0, 255, (60, 80, 3), dtype=np.uint8)
    return rgb, np.full((60, 80), depth_m, dtype=np.float32)


def _pose(t: tuple[float, float, float] = (0, 0, 0), phi: tuple[float, float, float] = (0, 0, 0)
          ) -> np.ndarray:
    return se3_exp(np.array([*t, *phi], dtype=np.float64))


def test_add_downsamples_and_numbers_keyframes() -> None:
    store = KeyframeStore(INTR, downscale=2)
    rgb, depth = _frame()
    a = store.add(10, 0.5, np.eye(4), rgb, depth)
    b = store.add(20, 1.0, _pose((0.1, 0, 0)), rgb, depth)
    assert (a.kf_id, b.kf_id) == (0, 1) and store.ids() == [0, 1] and len(store) == 2
    assert a.rgb_small.shape == (30, 40, 3) and a.rgb_small.dtype == np.uint8
    assert a.depth_small.shape == (30, 40) and a.depth_small.dtype == np.float32
    assert store.latest is b and store.get(0) is a
    with pytest.raises(KeyError, match="keyframe 7"):
        store.get(7)
    with pytest.raises(ValueError, match="intrinsics"):
        store.add(30, 1.5, np.eye(4), rgb[:30], depth[:30])


def test_covisible_prefers_overlapping_keyframes() -> None:
    store = KeyframeStore(INTR, downscale=2)
    rgb, depth = _frame()
    store.add(0, 0.0, np.eye(4), rgb, depth)  # same view as the query
    store.add(1, 0.1, _pose(phi=(0, np.pi, 0)), rgb, depth)  # looks the other way
    store.add(2, 0.2, _pose((0.3, 0, 0)), rgb, depth)  # shifted: partial overlap
    store.add(3, 0.3, _pose((5.0, 0, 0)), rgb, depth)  # far to the side: none
    scores = store.overlap(np.eye(4), INTR)
    assert scores[0] == pytest.approx(1.0)
    assert scores[1] == 0.0 and scores[3] == 0.0
    assert 0.3 < scores[2] < 1.0
    assert store.covisible(np.eye(4), INTR, k=5) == [0, 2]
    assert store.covisible(np.eye(4), INTR, k=1) == [0]
    assert store.covisible(np.eye(4), INTR, k=5, exclude=(0,)) == [2]
    # Correcting a pose moves its points: keyframe 3 brought back in front now overlaps.
    store.set_pose(3, np.eye(4))
    assert store.covisible(np.eye(4), INTR, k=5)[:2] == [3, 0]


def test_full_size_images_are_kept_losslessly() -> None:
    store = KeyframeStore(INTR, downscale=2)
    rgb, depth = _frame(2.3456)
    depth[5, 7], depth[6, 8] = 0.0, 20.0  # invalid, and beyond the stored range: invalid
    store.add(0, 0.0, np.eye(4), rgb, depth)
    rgb_full, depth_full = store.full_rgbd(0)
    np.testing.assert_array_equal(rgb_full, rgb)
    assert depth_full.shape == INTR.shape and depth_full[5, 7] == 0 and depth_full[6, 8] == 0
    ok = depth > 0
    ok[6, 8] = False
    np.testing.assert_allclose(depth_full[ok], depth[ok], atol=0.5 / DEPTH_SCALE)


def test_state_dict_round_trip_with_weights_only() -> None:
    store = KeyframeStore(INTR, downscale=2)
    rgb, depth = _frame()
    store.add(4, 0.4, _pose((0.1, 0.2, 0.3), (0.01, 0.02, 0.03)), rgb, depth)
    store.add_point_ids(0, torch.tensor([3, 5, 8]))
    buffer = io.BytesIO()
    torch.save(store.state_dict(), buffer)
    buffer.seek(0)
    state = torch.load(buffer, weights_only=True)
    other = KeyframeStore(INTR, downscale=2)
    other.load_state_dict(state)
    a, b = store.get(0), other.get(0)
    assert b.frame_index == 4 and b.timestamp == 0.4
    np.testing.assert_array_equal(a.T_world_cam, b.T_world_cam)
    np.testing.assert_array_equal(a.rgb_small, b.rgb_small)
    np.testing.assert_array_equal(b.point_ids, [3, 5, 8])
    for x, y in zip(store.full_rgbd(0), other.full_rgbd(0), strict=True):
        np.testing.assert_array_equal(x, y)
    with pytest.raises(ValueError, match="made at"):
        KeyframeStore(INTR.scaled(0.5), downscale=2).load_state_dict(state)

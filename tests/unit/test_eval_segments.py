"""Jumps in a reference trajectory and the ATE over the pieces between them."""

from __future__ import annotations

import numpy as np
import pytest

from cpslam.common.geometry import se3_exp
from cpslam.tools.eval import evaluate_ate, reference_jumps, segmented_ate


def _walk(n: int, speed: np.ndarray) -> np.ndarray:
    """Poses [n, 4, 4] of a camera moving by speed[i] m (and 0.3 deg) per frame along x."""
    poses = [np.eye(4)]
    for i in range(n - 1):
        step = se3_exp(np.array([speed[i], 0.002, 0.0, 0.0, np.radians(0.3), 0.0]))
        poses.append(poses[-1] @ step)
    return np.stack(poses)


def test_a_one_frame_spike_is_a_jump_and_fast_motion_is_not() -> None:
    speed = np.full(80, 0.007)
    speed[30:45] = np.linspace(0.007, 0.04, 15)  # accelerates over 15 frames: real motion
    speed[45:50] = 0.04
    assert len(reference_jumps(_walk(80, speed))) == 0
    speed[60] = 0.036  # one step five times its neighbours: the reference jumped
    assert reference_jumps(_walk(80, speed)).tolist() == [60]
    turned = _walk(80, np.full(80, 0.007))
    turned[41:] = turned[41:] @ se3_exp(np.array([0, 0, 0, 0, 0, np.radians(2.0)]))[None]
    assert reference_jumps(turned).tolist() == [40]  # a rotation spike counts too
    with pytest.raises(ValueError, match=r"\[N, 4, 4\]"):
        reference_jumps(np.eye(4))


def test_pieces_leave_the_jump_out_and_keep_the_rest() -> None:
    n = 100
    stamps = np.arange(n) / 30.0
    true_speed = np.full(n, 0.007)
    est = _walk(n, true_speed)
    jumped = true_speed.copy()
    jumped[59] = 0.04
    gt = _walk(n, jumped)
    jumps = reference_jumps(gt)
    assert jumps.tolist() == [59]
    whole = evaluate_ate(stamps, gt, stamps, est, align="se3").rmse
    pieces = segmented_ate(stamps, gt, stamps, est, jumps)
    assert whole > 0.005 and pieces.rmse < 1e-9
    assert pieces.pieces == [(0, 59), (60, 99)]
    # Drift inside a piece still counts: the estimate walks 10 % short.
    short = segmented_ate(stamps, gt, stamps, _walk(n, 0.9 * true_speed), jumps)
    assert short.rmse > 0.003
    # Pieces below min_frames are dropped; nothing left is an error that names the jumps.
    assert segmented_ate(stamps, gt, stamps, est, np.array([5, 59])).pieces == [(6, 59),
                                                                               (60, 99)]
    with pytest.raises(ValueError, match="no piece of at least 200 frames"):
        segmented_ate(stamps, gt, stamps, est, jumps, min_frames=200)

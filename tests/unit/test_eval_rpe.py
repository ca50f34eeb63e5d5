"""Relative pose error: zero for the same motion in any world frame, the size of a known
glitch at the pairs that span it, clear errors for bad input."""

from __future__ import annotations

import numpy as np
import pytest

from cpslam.common.geometry import se3_exp
from cpslam.tools.eval import evaluate_rpe


def _walk(n: int = 40) -> tuple[np.ndarray, np.ndarray]:
    """A wavy walk: stamps [n] and T_world_cam [n, 4, 4]."""
    rng = np.random.default_rng(3)
    poses = [np.eye(4)]
    for _ in range(n - 1):
        poses.append(poses[-1] @ se3_exp(np.concatenate((rng.normal(0, 0.01, 3),
                                                          rng.normal(0, 0.01, 3)))))
    return np.arange(n) / 30.0, np.stack(poses)


def test_same_motion_in_another_world_frame_has_no_error() -> None:
    stamps, gt = _walk()
    T_other_world = se3_exp(np.array([1.0, -2.0, 0.5, 0.3, -0.2, 1.0]))
    result = evaluate_rpe(stamps, gt, stamps, T_other_world @ gt, delta=5)
    assert result.pairs == len(stamps) - 5
    assert result.trans_rmse < 1e-9 and result.rot_rmse_deg < 1e-6


def test_a_glitch_shows_in_the_pairs_that_span_it() -> None:
    stamps, gt = _walk()
    glitch = se3_exp(np.array([0.03, 0.0, -0.04, 0.0, np.radians(2.0), 0.0]))  # 5 cm, 2 deg
    est = gt.copy()
    est[20:] = gt[19] @ glitch @ np.linalg.inv(gt[19]) @ gt[20:]  # world-frame jump after 19
    one = evaluate_rpe(stamps, gt, stamps, est, delta=1)
    assert one.trans[19] > 0.01 and one.rot[19] == pytest.approx(2.0, abs=1e-6)
    assert np.delete(one.rot, 19).max() < 1e-6
    assert one.rot_mean_deg == pytest.approx(2.0 / one.pairs, rel=1e-6)
    ten = evaluate_rpe(stamps, gt, stamps, est, delta=10)
    spanning = np.arange(ten.pairs)
    spanning = (spanning <= 19) & (spanning + 10 >= 20)
    assert ten.rot[spanning].min() == pytest.approx(2.0, abs=1e-6)
    assert ten.rot[~spanning].max() < 1e-6


def test_bad_input_is_named() -> None:
    stamps, gt = _walk(5)
    with pytest.raises(ValueError, match="delta must be >= 1"):
        evaluate_rpe(stamps, gt, stamps, gt, delta=0)
    with pytest.raises(ValueError, match="need more than delta = 5"):
        evaluate_rpe(stamps, gt, stamps, gt, delta=5)
    with pytest.raises(ValueError, match=r"estimate: poses must be \[N, 4, 4\]"):
        evaluate_rpe(stamps, gt, stamps, gt[:, :3], delta=1)


@pytest.mark.parametrize("delta", [1, 10])
def test_matches_evo(tmp_path, delta: int) -> None:
    from evo.core import metrics
    from evo.tools import file_interface

    from cpslam.common.trajectory import write_tum

    stamps, gt = _walk(120)
    rng = np.random.default_rng(4)
    est = np.stack([p @ se3_exp(np.concatenate((rng.normal(0, 0.005, 3),
                                                rng.normal(0, 0.005, 3)))) for p in gt])
    write_tum(tmp_path / "gt.tum", stamps, gt)
    write_tum(tmp_path / "est.tum", stamps, est)
    ref = file_interface.read_tum_trajectory_file(str(tmp_path / "gt.tum"))
    traj = file_interface.read_tum_trajectory_file(str(tmp_path / "est.tum"))
    ours = evaluate_rpe(ref.timestamps, ref.poses_se3, traj.timestamps, traj.poses_se3,
                        delta=delta)
    for relation, values in ((metrics.PoseRelation.translation_part, ours.trans),
                             (metrics.PoseRelation.rotation_angle_deg, ours.rot)):
        rpe = metrics.RPE(relation, delta=delta, delta_unit=metrics.Unit.frames,
                          all_pairs=True)  # every i -> i + delta, as ours
        rpe.process_data((ref, traj))
        np.testing.assert_allclose(values, rpe.error, atol=1e-6)
    assert ours.trans_mean > 0.003  # the noise is really there

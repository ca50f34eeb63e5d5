"""ATE: association, alignment, statistics, joint evaluation; cross-checked against evo."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cpslam.common.geometry import se3_exp, so3_exp
from cpslam.common.trajectory import read_tum, write_tum
from cpslam.tools.eval import (
    align,
    apply_alignment,
    associate,
    evaluate_ate,
    joint_ate,
    load_trajectory,
    locate_trajectory,
    umeyama,
)


def random_trajectory(n: int, seed: int, fps: float = 30.0) -> tuple[np.ndarray, np.ndarray]:
    """A smooth random camera path: stamps [n] and T_world_cam [n, 4, 4]."""
    rng = np.random.default_rng(seed)
    steps = se3_exp(np.concatenate([rng.normal(0, 0.02, (n, 3)), rng.normal(0, 0.02, (n, 3))], 1))
    poses = np.empty((n, 4, 4))
    poses[0] = se3_exp(rng.normal(0, 1.0, 6))
    for i in range(1, n):
        poses[i] = poses[i - 1] @ steps[i]
    return 1000.0 + np.arange(n) / fps, poses


def perturb(poses: np.ndarray, seed: int, sigma_t: float = 0.01, sigma_r: float = 0.01):
    rng = np.random.default_rng(seed)
    out = poses.copy()
    out[:, :3, :3] = poses[:, :3, :3] @ so3_exp(rng.normal(0, sigma_r, (len(poses), 3)))
    out[:, :3, 3] += rng.normal(0, sigma_t, (len(poses), 3))
    return out


def random_transform(seed: int) -> np.ndarray:
    return se3_exp(np.random.default_rng(seed).normal(0, 1.0, 6))


# ---------------------------------------------------------------------------------- association


def test_associate_one_to_one_closest_first() -> None:
    gt = np.array([0.0, 1.0, 2.0, 3.0])
    est = np.array([0.99, 1.005, 2.5, 3.01, -1.0])
    est_idx, gt_idx = associate(est, gt, max_dt=0.02)
    # 1.005 is closer to 1.0 than 0.99 is, so it wins; 2.5 and -1.0 match nothing.
    assert est_idx.tolist() == [1, 3]
    assert gt_idx.tolist() == [1, 3]


def test_associate_unsorted_stamps_and_empty() -> None:
    gt = np.array([3.0, 1.0, 2.0])
    est_idx, gt_idx = associate(np.array([2.001, 0.999]), gt, max_dt=0.01)
    assert est_idx.tolist() == [1, 0]  # ordered by estimate stamp
    assert gt_idx.tolist() == [1, 2]
    est_idx, gt_idx = associate(np.array([10.0]), gt, max_dt=0.01)
    assert len(est_idx) == 0 and len(gt_idx) == 0


def test_too_few_pairs_names_both_trajectories() -> None:
    stamps, poses = random_trajectory(5, seed=0)
    with pytest.raises(ValueError, match="est.tum.*gt.tum"):
        evaluate_ate(stamps, poses, stamps + 100.0, poses, gt_name="gt.tum", est_name="est.tum")


# ------------------------------------------------------------------------------------ alignment


def test_perfect_trajectory_has_zero_error() -> None:
    stamps, poses = random_trajectory(50, seed=1)
    for mode in ("origin", "se3", "sim3", "none"):
        result = evaluate_ate(stamps, poses, stamps, poses, align=mode)
        assert result.rmse < 1e-9 and result.max < 1e-9, mode
        assert result.rot_rmse_deg < 1e-5, mode
        assert result.n_pairs == 50


def test_rigid_copy_zero_with_se3_not_with_none() -> None:
    stamps, gt = random_trajectory(60, seed=2)
    T_est_gt = random_transform(3)
    est = T_est_gt @ gt
    for mode in ("se3", "origin", "sim3"):
        result = evaluate_ate(stamps, gt, stamps, est, align=mode)
        assert result.rmse < 1e-9, mode
        assert result.rot_rmse_deg < 1e-5, mode
        np.testing.assert_allclose(result.T_gt_est, np.linalg.inv(T_est_gt), atol=1e-9)
    assert evaluate_ate(stamps, gt, stamps, est, align="none").rmse > 0.1


def test_sim3_recovers_scale() -> None:
    stamps, gt = random_trajectory(80, seed=4)
    T = random_transform(5)
    est = apply_alignment(gt, T[:3, :3], T[:3, 3], s=0.4)
    result = evaluate_ate(stamps, gt, stamps, est, align="sim3")
    assert result.scale == pytest.approx(1.0 / 0.4, rel=1e-9)
    assert result.rmse < 1e-9
    assert evaluate_ate(stamps, gt, stamps, est, align="se3").rmse > 0.05


def test_umeyama_matches_known_similarity() -> None:
    rng = np.random.default_rng(6)
    src = rng.normal(size=(20, 3))
    R = so3_exp(rng.normal(size=3))
    dst = 2.5 * src @ R.T + np.array([1.0, -2.0, 0.5])
    R_hat, t_hat, s_hat = umeyama(src, dst, with_scale=True)
    np.testing.assert_allclose(R_hat, R, atol=1e-10)
    np.testing.assert_allclose(t_hat, [1.0, -2.0, 0.5], atol=1e-10)
    assert s_hat == pytest.approx(2.5)
    assert np.linalg.det(R_hat) == pytest.approx(1.0)


def test_align_rejects_bad_input() -> None:
    xyz = np.zeros((5, 3))
    with pytest.raises(ValueError, match="origin alignment needs poses"):
        align(xyz, xyz, "origin")
    with pytest.raises(ValueError, match="unknown alignment mode"):
        align(xyz, xyz, "affine")
    with pytest.raises(ValueError, match="coincide"):
        align(xyz, xyz + 1.0, "se3")
    with pytest.raises(ValueError, match="at least 3"):
        align(np.eye(3)[:2], np.eye(3)[:2], "se3")


# ---------------------------------------------------------------------------- evo cross-check


@pytest.mark.parametrize("mode", ["origin", "se3", "sim3"])
def test_matches_evo(tmp_path: Path, mode: str) -> None:
    from evo.core import metrics, sync
    from evo.tools import file_interface

    stamps, gt = random_trajectory(200, seed=7)
    est = perturb(gt, seed=8)
    if mode == "sim3":
        est[:, :3, 3] *= 0.7
    rng = np.random.default_rng(9)
    keep = np.sort(rng.choice(len(stamps), 150, replace=False))
    est_stamps = stamps[keep] + rng.uniform(-0.004, 0.004, len(keep))  # clock jitter
    write_tum(tmp_path / "gt.tum", stamps, gt)
    write_tum(tmp_path / "est.tum", est_stamps, est[keep])

    ref = file_interface.read_tum_trajectory_file(str(tmp_path / "gt.tum"))
    traj = file_interface.read_tum_trajectory_file(str(tmp_path / "est.tum"))
    ref, traj = sync.associate_trajectories(ref, traj, max_diff=0.01)
    if mode == "origin":
        traj.align_origin(ref)
    else:
        traj.align(ref, correct_scale=(mode == "sim3"))
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, traj))
    evo_stats = ape.get_all_statistics()
    ape_rot = metrics.APE(metrics.PoseRelation.rotation_angle_deg)
    ape_rot.process_data((ref, traj))

    gt_traj = load_trajectory(tmp_path / "gt.tum")
    est_traj = load_trajectory(tmp_path / "est.tum")
    result = evaluate_ate(
        gt_traj.stamps, gt_traj.poses, est_traj.stamps, est_traj.poses, align=mode, max_dt=0.01
    )
    assert result.n_pairs == ref.num_poses == 150
    for key in ("rmse", "mean", "median", "std", "min", "max"):
        assert getattr(result, key) == pytest.approx(evo_stats[key], abs=1e-6), key
    np.testing.assert_allclose(result.rot_err_deg, ape_rot.error, atol=1e-4)
    assert result.rmse > 0.005  # the noise is really there


# ----------------------------------------------------------------------------------- joint ATE


def test_joint_ate_uses_one_alignment() -> None:
    stamps, gt = random_trajectory(120, seed=10)
    a, b = slice(0, 60), slice(60, 120)
    T = random_transform(11)
    est = T @ perturb(gt, seed=12, sigma_t=0.002)
    pairs = [((stamps[a], gt[a]), (stamps[a], est[a])), ((stamps[b], gt[b]), (stamps[b], est[b]))]
    joint = joint_ate(pairs, align="se3")
    assert joint.overall.n_pairs == 120 and len(joint.parts) == 2
    assert joint.overall.rmse < 0.01
    np.testing.assert_allclose(joint.parts[0].T_gt_est, joint.parts[1].T_gt_est)
    pooled = np.sqrt(np.mean(np.concatenate([p.trans_err for p in joint.parts]) ** 2))
    assert joint.overall.rmse == pytest.approx(pooled)

    # The second agent in a frame of its own: fine on its own, wrong once held jointly.
    est_b = random_transform(13) @ est[b]
    pairs[1] = ((stamps[b], gt[b]), (stamps[b], est_b))
    assert evaluate_ate(stamps[b], gt[b], stamps[b], est_b, align="se3").rmse < 0.01
    assert joint_ate(pairs, align="se3").overall.rmse > 0.1

    d = joint.to_dict()
    assert set(d) == {"overall", "parts"} and d["parts"][1]["n_pairs"] == 60


def test_result_to_dict_numbers() -> None:
    stamps, gt = random_trajectory(30, seed=14)
    result = evaluate_ate(stamps, gt, stamps, perturb(gt, seed=15), align="se3")
    d = result.to_dict(series=True)
    assert d["align"] == "se3" and d["n_pairs"] == 30 and d["scale"] == 1.0
    assert d["rmse_m"] == pytest.approx(np.sqrt(np.mean(np.array(d["trans_err_m"]) ** 2)))
    assert d["min_m"] <= d["median_m"] <= d["max_m"]
    assert np.asarray(d["T_gt_est"]).shape == (4, 4)


# -------------------------------------------------------------------------------------- inputs


def test_locate_run_folders(tmp_path: Path) -> None:
    stamps, poses = random_trajectory(10, seed=16)
    with pytest.raises(FileNotFoundError, match="nowhere"):
        locate_trajectory(tmp_path / "nowhere")
    write_tum(tmp_path / "run" / "agent_0" / "trajectory.tum", stamps, poses)
    assert locate_trajectory(tmp_path / "run") == (
        "tum",
        tmp_path / "run" / "agent_0" / "trajectory.tum",
    )
    traj = load_trajectory(tmp_path / "run")
    np.testing.assert_allclose(traj.poses, read_tum(tmp_path / "run/agent_0/trajectory.tum")[1])
    write_tum(tmp_path / "run" / "agent_1" / "trajectory.tum", stamps, poses)
    with pytest.raises(ValueError, match="agent_0.*agent_1"):
        locate_trajectory(tmp_path / "run")
    write_tum(tmp_path / "run" / "trajectory.tum", stamps, poses)  # top level wins
    assert locate_trajectory(tmp_path / "run")[1] == tmp_path / "run" / "trajectory.tum"


@pytest.mark.data
def test_dataset_folder_as_ground_truth(kitchen_path: Path) -> None:
    gt = load_trajectory(kitchen_path)
    assert len(gt) == 300
    est = perturb(gt.poses, seed=17, sigma_t=0.005)
    result = evaluate_ate(gt.stamps, gt.poses, gt.stamps, est, align="se3")
    assert result.n_pairs == 300
    assert 0.005 < result.rmse < 0.015

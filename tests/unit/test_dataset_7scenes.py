"""The 7-Scenes loader on the real red-kitchen frames in ../shared/data (skips when absent)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import typer
from typer.testing import CliRunner

from cpslam.common.camera import Intrinsics
from cpslam.common.datasets import open_sequence
from cpslam.common.datasets.cli import info
from cpslam.common.geometry import is_rigid

pytestmark = pytest.mark.data


def test_kitchen_sequence(kitchen_path: Path) -> None:
    seq = open_sequence(kitchen_path)
    assert seq.format == "7scenes" and len(seq) == 300
    assert list(seq.indices[[0, -1]]) == [0, 299]
    assert seq.intrinsics == Intrinsics(585.0, 585.0, 320.0, 240.0, 640, 480)
    np.testing.assert_allclose(seq.timestamps[:3], [0.0, 1 / 30, 2 / 30])

    frame = seq[0]
    assert frame.rgb.shape == (480, 640, 3) and frame.rgb.dtype == np.uint8
    assert frame.depth.shape == (480, 640) and frame.depth.dtype == np.float32
    valid = frame.depth[frame.depth > 0]
    assert valid.size > 0.5 * frame.depth.size
    assert 0.3 < valid.min() and valid.max() < 5.0  # 65535 ("no reading") must be gone
    assert 1.0 < float(np.median(valid)) < 3.0
    # ground truth is snapped to the nearest rigid pose (the file is orthonormal to ~2e-4)
    np.testing.assert_allclose(
        frame.gt_pose, np.loadtxt(kitchen_path / "frame-000000.pose.txt"), atol=2e-4
    )
    assert is_rigid(frame.gt_pose, tol=1e-9)


def test_kitchen_ground_truth_is_rigid_and_smooth(kitchen_path: Path) -> None:
    poses = open_sequence(kitchen_path).gt_poses()
    assert poses.shape == (300, 4, 4)
    assert is_rigid(poses, tol=1e-3)
    steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    assert steps.max() < 0.05  # about 7 mm per frame at 30 Hz, never a jump


def test_kitchen_selection(kitchen_path: Path) -> None:
    seq = open_sequence(kitchen_path, frames="100:200:50")
    assert list(seq.indices) == [100, 150]
    assert seq[1].timestamp == pytest.approx(5.0)
    np.testing.assert_allclose(
        seq[1].gt_pose, np.loadtxt(kitchen_path / "frame-000150.pose.txt"), atol=2e-4
    )


def test_info_on_kitchen(kitchen_path: Path) -> None:
    app = typer.Typer()
    app.command()(info)

    @app.callback()
    def main() -> None:
        """Test app."""

    result = CliRunner().invoke(app, ["info", str(kitchen_path), "--json", "--samples", "3"])
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout)
    assert summary["format"] == "7scenes" and summary["frames"] == 300
    assert (summary["width"], summary["height"]) == (640, 480)
    assert 0.3 < summary["depth"]["min_m"] < summary["depth"]["max_m"] < 5.0
    assert 0.5 < summary["depth"]["valid_fraction"] <= 1.0
    assert summary["ground_truth"]["frames"] == 300
    assert 1.0 < summary["ground_truth"]["trajectory_length_m"] < 4.0
    text = CliRunner().invoke(app, ["info", str(kitchen_path)])
    assert text.exit_code == 0 and "7scenes" in text.output and "640x480" in text.output


def test_dataset_gt_writes_what_evo_scores_as_we_do(kitchen_path: Path, tmp_path: Path) -> None:
    """`cpslam dataset gt` writes the ground truth as TUM; evo's APE on it and an estimate
    equals `cpslam eval ate` on the sequence folder itself (the commands docs/evaluation.md
    gives)."""
    from evo.core import metrics, sync
    from evo.tools import file_interface

    from cpslam.common.datasets.cli import gt
    from cpslam.common.geometry import se3_exp
    from cpslam.common.trajectory import write_tum
    from cpslam.tools.eval import evaluate_ate

    app = typer.Typer()
    app.command()(gt)
    out = tmp_path / "gt.tum"
    result = CliRunner().invoke(app, [str(kitchen_path), "--frames", "0:60", "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert "60/60 frames" in result.output
    again = CliRunner().invoke(app, [str(kitchen_path), "--out", str(out)])
    assert again.exit_code == 2 and "--overwrite" in again.output

    seq = open_sequence(kitchen_path, frames="0:60")
    rng = np.random.default_rng(0)
    est = np.stack([T @ se3_exp(rng.normal(0, 0.01, 6)) for T in seq.gt_poses()])
    write_tum(tmp_path / "est.tum", seq.timestamps, est)
    ref = file_interface.read_tum_trajectory_file(str(out))
    traj = file_interface.read_tum_trajectory_file(str(tmp_path / "est.tum"))
    ref, traj = sync.associate_trajectories(ref, traj, max_diff=0.01)
    traj.align(ref)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, traj))
    ours = evaluate_ate(seq.timestamps, seq.gt_poses(), seq.timestamps, est, align="se3")
    assert ape.get_statistic(metrics.StatisticsType.rmse) == pytest.approx(ours.rmse, abs=1e-6)

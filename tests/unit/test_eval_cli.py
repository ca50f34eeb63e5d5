"""`cpslam eval ate` command and the ATE plot."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import typer
from typer.testing import CliRunner

from cpslam.common.geometry import se3_exp
from cpslam.common.trajectory import write_tum
from cpslam.tools.eval import evaluate_ate, joint_ate
from cpslam.tools.eval.cli import ate
from cpslam.tools.eval.plot import plot_ate, top_view_axes

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def make_pair(tmp_path: Path, n: int = 60, seed: int = 0) -> tuple[Path, Path]:
    """gt.tum and a noisy est.tum (in another frame) written to tmp_path."""
    rng = np.random.default_rng(seed)
    stamps = np.arange(n) / 30.0
    xi = np.zeros((n, 6))
    xi[:, 0] = np.linspace(0.0, 2.0, n)  # moving along x and z: the top view is x-z
    xi[:, 2] = np.sin(np.linspace(0.0, 3.0, n))
    xi[:, 4] = np.linspace(0.0, 1.0, n)
    gt = se3_exp(xi)
    est = se3_exp(np.array([0.3, -0.2, 0.1, 0.0, 0.5, 0.0])) @ gt
    est[:, :3, 3] += rng.normal(0.0, 0.01, (n, 3))
    write_tum(tmp_path / "gt.tum", stamps, gt)
    write_tum(tmp_path / "run" / "agent_0" / "trajectory.tum", stamps + 0.001, est)
    return tmp_path / "gt.tum", tmp_path / "run"


@pytest.fixture
def app() -> typer.Typer:
    app = typer.Typer()
    app.command()(ate)

    @app.command()
    def other() -> None:  # a second command keeps `ate` a named subcommand, as in cpslam
        pass

    return app


def test_cli_happy_path(tmp_path: Path, app: typer.Typer) -> None:
    gt, run = make_pair(tmp_path)
    out_json, out_png = tmp_path / "out" / "ate.json", tmp_path / "out" / "ate.png"
    args = ["ate", "--gt", str(gt), "--est", str(run), "--align", "se3"]
    result = CliRunner().invoke(app, [*args, "--out", str(out_json), "--plot", str(out_png)])
    assert result.exit_code == 0, result.output
    assert "RMSE" in result.output and "cm" in result.output and "se3" in result.output
    record = json.loads(out_json.read_text())
    assert record["n_pairs"] == 60 and record["align"] == "se3"
    assert record["est"].endswith("agent_0/trajectory.tum")
    assert 0.005 < record["rmse_m"] < 0.03
    assert out_png.read_bytes()[:8] == PNG_MAGIC


def test_cli_sim3_prints_scale(tmp_path: Path, app: typer.Typer) -> None:
    gt, run = make_pair(tmp_path)
    result = CliRunner().invoke(app, ["ate", "--gt", str(gt), "--est", str(run), "--align", "sim3"])
    assert result.exit_code == 0, result.output
    assert "scale" in result.output


def test_cli_missing_file_exits_2(tmp_path: Path, app: typer.Typer) -> None:
    gt, _ = make_pair(tmp_path)
    missing = tmp_path / "no_such_estimate.tum"
    result = CliRunner().invoke(app, ["ate", "--gt", str(gt), "--est", str(missing)])
    assert result.exit_code == 2
    assert "no_such_estimate.tum" in result.output


def test_cli_no_matching_stamps_exits_2(tmp_path: Path, app: typer.Typer) -> None:
    gt, run = make_pair(tmp_path)
    result = CliRunner().invoke(app, ["ate", "--gt", str(gt), "--est", str(run), "--max-dt", "0"])
    assert result.exit_code == 2
    assert "gt.tum" in result.output and "trajectory.tum" in result.output


def test_cli_bad_tum_line_exits_2(tmp_path: Path, app: typer.Typer) -> None:
    gt, _ = make_pair(tmp_path)
    bad = tmp_path / "bad.tum"
    bad.write_text("0.0 1 2 3\n")
    result = CliRunner().invoke(app, ["ate", "--gt", str(gt), "--est", str(bad)])
    assert result.exit_code == 2
    assert "bad.tum" in result.output


def make_replica(root: Path, n: int = 12) -> np.ndarray:
    """A tiny Replica-layout folder (8x6 images, 30 Hz) whose traj.txt holds the returned
    ground truth [n, 4, 4]."""
    import cv2

    xi = np.zeros((n, 6))
    xi[:, 0] = np.linspace(0.0, 1.0, n)
    xi[:, 2] = np.linspace(0.0, 0.5, n) ** 2
    xi[:, 4] = np.linspace(0.0, 0.8, n)
    poses = se3_exp(xi)
    (root / "results").mkdir(parents=True)
    for i in range(n):
        rgb, depth = np.zeros((6, 8, 3), np.uint8), np.full((6, 8), 6553, np.uint16)
        assert cv2.imwrite(str(root / "results" / f"frame{i:06d}.png"), rgb)
        assert cv2.imwrite(str(root / "results" / f"depth{i:06d}.png"), depth)
    (root / "traj.txt").write_text(
        "".join(" ".join(f"{v:.17g}" for v in T.ravel()) + "\n" for T in poses)
    )
    (root / "camera.yaml").write_text("fx: 6.4\nfy: 6.4\ncx: 3.5\ncy: 2.5\nwidth: 8\nheight: 6\n")
    return poses


def test_cli_dataset_folder_with_frames_and_format(tmp_path: Path, app: typer.Typer) -> None:
    gt = make_replica(tmp_path / "seq")
    est = gt.copy()
    est[:, :3, 3] += 0.01  # 1 cm off everywhere: the ATE with --align none is exactly 1 cm
    write_tum(tmp_path / "est.tum", np.arange(len(gt)) / 30.0, est)
    out = tmp_path / "ate.json"
    base = ["ate", "--gt", str(tmp_path / "seq"), "--est", str(tmp_path / "est.tum"),
            "--align", "none", "--out", str(out), "--overwrite"]
    result = CliRunner().invoke(app, base)
    assert result.exit_code == 0, result.output
    record = json.loads(out.read_text())
    assert record["n_gt"] == 12 and record["n_pairs"] == 12
    assert record["rmse_m"] == pytest.approx(0.01 * np.sqrt(3), abs=1e-9)
    # a selection keeps the sequence's own timestamps, so it pairs with the full estimate
    result = CliRunner().invoke(app, [*base, "--frames", "2:10:2", "--format", "replica"])
    assert result.exit_code == 0, result.output
    record = json.loads(out.read_text())
    assert record["n_gt"] == 4 and record["n_pairs"] == 4 and record["n_est"] == 12
    # the dataset may be the estimate's side as well
    swapped = ["ate", "--gt", str(tmp_path / "est.tum"), "--est", str(tmp_path / "seq"),
               "--align", "none", "--frames", ":5", "--out", str(out), "--overwrite"]
    result = CliRunner().invoke(app, swapped)
    assert result.exit_code == 0, result.output
    assert json.loads(out.read_text())["n_est"] == 5


def test_cli_frames_and_format_errors_exit_2(tmp_path: Path, app: typer.Typer) -> None:
    make_replica(tmp_path / "seq")
    gt, run = make_pair(tmp_path)
    seq = ["ate", "--gt", str(tmp_path / "seq"), "--est", str(run)]
    result = CliRunner().invoke(app, [*seq, "--format", "tum"])  # not a TUM RGB-D layout
    assert result.exit_code == 2 and "error" in result.output and "seq" in result.output
    result = CliRunner().invoke(app, [*seq, "--format", "kitti"])
    assert result.exit_code == 2 and "kitti" in result.output
    result = CliRunner().invoke(app, [*seq, "--frames", "3-9"])
    assert result.exit_code == 2 and "START:STOP" in result.output
    result = CliRunner().invoke(app, [*seq, "--frames", "50:"])
    assert result.exit_code == 2 and "select none" in result.output
    tum_only = ["ate", "--gt", str(gt), "--est", str(run), "--frames", "0:10"]
    result = CliRunner().invoke(app, tum_only)
    assert result.exit_code == 2 and "dataset folders" in result.output


def test_cli_help_names_inputs_and_units(app: typer.Typer) -> None:
    text = " ".join(CliRunner().invoke(app, ["ate", "--help"]).output.replace("│", " ").split())
    assert "dataset folder (its ground-truth poses)" in text
    assert "pose pair, in seconds" in text  # "[s]" would have been swallowed by rich markup
    assert "--frames" in text and "--format" in text
    assert "cpslam eval ate --gt" in text


def test_plot_single_and_joint(tmp_path: Path) -> None:
    import matplotlib.image

    stamps = np.arange(40) / 30.0
    xi = np.zeros((40, 6))
    xi[:, 1] = np.linspace(0.0, 1.0, 40)
    xi[:, 2] = np.linspace(0.0, 3.0, 40)
    gt = se3_exp(xi)
    est = gt.copy()
    est[:, :3, 3] += 0.01
    result = evaluate_ate(stamps, gt, stamps, est, align="none")
    path = plot_ate(result, tmp_path / "one.png", title="test")
    image = matplotlib.image.imread(path)
    assert image.ndim == 3 and image.shape[0] > 100 and image.shape[1] > 100

    joint = joint_ate([((stamps, gt), (stamps, est)), ((stamps, gt), (stamps, est))])
    path = plot_ate(joint.parts, tmp_path / "sub" / "joint.png", labels=["a", "b"])
    assert path.read_bytes()[:8] == PNG_MAGIC
    with pytest.raises(ValueError, match="labels"):
        plot_ate(joint.parts, tmp_path / "x.png", labels=["a"])


def test_top_view_axes_picks_largest_extent() -> None:
    xyz = np.zeros((10, 3))
    xyz[:, 0] = np.linspace(0, 1, 10)
    xyz[:, 1] = np.linspace(0, 0.1, 10)
    xyz[:, 2] = np.linspace(0, 5, 10)
    assert top_view_axes(xyz) == (0, 2)


def test_cli_rpe_rows_and_json(tmp_path: Path, app: typer.Typer) -> None:
    gt, run = make_pair(tmp_path)
    out_json = tmp_path / "ate.json"
    result = CliRunner().invoke(app, ["ate", "--gt", str(gt), "--est", str(run), "--rpe", "10",
                                      "--rpe", "1", "--out", str(out_json)])
    assert result.exit_code == 0, result.output
    assert "RPE over 1 frame" in result.output and "RPE over 10 frames" in result.output
    record = json.loads(out_json.read_text())
    assert [r["delta"] for r in record["rpe"]] == [1, 10]
    assert [r["pairs"] for r in record["rpe"]] == [59, 50]
    assert 0.005 < record["rpe"][0]["trans_mean_m"] < 0.05  # the 1 cm position noise
    too_long = CliRunner().invoke(app, ["ate", "--gt", str(gt), "--est", str(run),
                                        "--rpe", "60"])
    assert too_long.exit_code == 2 and "need more than delta = 60" in too_long.output


def test_cli_pieces_between_ground_truth_jumps(tmp_path: Path, app: typer.Typer) -> None:
    """--pieces scores the stretches between one-frame jumps of the ground truth apart: an
    estimate that follows the true motion pays for the jump over the whole run only."""
    n = 90
    stamps = np.arange(n) / 30.0
    step = se3_exp(np.array([0.007, 0.0, 0.002, 0.0, np.radians(0.3), 0.0]))
    est = np.stack([np.linalg.matrix_power(step, i) for i in range(n)])
    gt = est.copy()
    # From frame 50 on, the ground truth's world is shifted by 3 cm and turned by 1.5 deg.
    gt[50:] = se3_exp(np.array([0.03, 0.01, 0.0, 0.0, 0.0, np.radians(1.5)]))[None] @ gt[50:]
    write_tum(tmp_path / "gt.tum", stamps, gt)
    write_tum(tmp_path / "est.tum", stamps, est)
    out_json = tmp_path / "ate.json"
    result = CliRunner().invoke(app, ["ate", "--gt", str(tmp_path / "gt.tum"), "--est",
                                      str(tmp_path / "est.tum"), "--align", "se3", "--pieces",
                                      "--out", str(out_json)])
    assert result.exit_code == 0, result.output
    assert "RMSE over pieces" in result.output and "49->50" in result.output
    record = json.loads(out_json.read_text())
    assert record["rmse_m"] > 0.005 and record["pieces"]["rmse"] < 1e-6
    assert record["pieces"]["jumps_after_frame"] == [49]
    assert record["pieces"]["pieces"] == [[0, 49], [50, 89]]
    plain = CliRunner().invoke(app, ["ate", "--gt", str(tmp_path / "gt.tum"), "--est",
                                     str(tmp_path / "est.tum")])
    assert plain.exit_code == 0 and "RMSE over pieces" not in plain.output

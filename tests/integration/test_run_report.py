"""`cpslam report`, `cpslam mesh` and `cpslam eval render` on real run folders (tiny preset,
a small synthetic apartment): the report of a `cpslam run` folder prints the tables the run
printed when it ended (one code path), finds the ground truth the agents recorded, and agrees
with the run's own evaluation.json; the render metrics agree with scikit-image's PSNR and
SSIM of the very images they were computed from; a lone agent's folder is reported too."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from cpslam.cli import app

pytestmark = pytest.mark.slow
pytest.importorskip("open3d")  # the synthetic renderer, the mesh

ENV = {"COLUMNS": "160"}  # one width for every table, so the texts compare line by line


def _invoke(args: list[str]) -> str:
    result = CliRunner(env=ENV).invoke(app, args, catch_exceptions=False)
    assert result.exit_code == 0, result.output
    return result.output


def _tables(text: str) -> list[str]:
    """The report's lines from the results table's header to the traffic table's end: what
    every report of one run folder must print alike (the title and this process's memory
    differ)."""
    lines = text.splitlines()
    start = next(i for i, line in enumerate(lines) if line.split()[:3] == ["agent", "frames",
                                                                           "group"])
    stop = next(i for i, line in enumerate(lines) if line.startswith("peak memory"))
    return [line.rstrip() for line in lines[start:stop]]


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory):
    from cpslam.tools.synth import generate

    return generate(tmp_path_factory.mktemp("apt") / "apt", scene="apartment", agents=2,
                    frames=300, width=160, height=120, seed=0, show_progress=False)


@pytest.fixture(scope="module")
def collab(scene, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, str]:
    """A two-agent `cpslam run` of 30 frames each (2 cm apart), and what it printed."""
    out = tmp_path_factory.mktemp("runs") / "run"
    text = _invoke(["run", "--seq", str(scene.agent_dirs[0]), "--seq", str(scene.agent_dirs[1]),
                    "--preset", "tiny", "--frames", "0:60:2", "--set", "keyframes.every=5",
                    "--out", str(out), "--no-progress", "--no-mesh"])
    return out, text


def test_report_of_a_run_folder_prints_what_the_run_printed(collab, scene) -> None:
    run, at_the_end = collab
    first = json.loads((run / "report.json").read_text())
    again = _invoke(["report", str(run), "--no-mesh", "--no-progress", "--render-views", "0"])
    assert _tables(again) == _tables(at_the_end)
    assert "ATE glob" in again and "outputs in" in again
    report = json.loads((run / "report.json").read_text())
    assert report["schema_version"] == 1 and report["kind"] == "collaborative"
    # Found from agent_<id>/metrics.json, where each agent recorded its sequence.
    assert report["ground_truth"] == {str(a): str(d.resolve())
                                      for a, d in enumerate(scene.agent_dirs)}
    assert report["agents"] == first["agents"] and report["all"] == first["all"]
    # The run's own evaluation (cpslam.run.evaluate_run) computes the same joint figures.
    evaluation = json.loads((run / "evaluation.json").read_text())
    assert evaluation["schema_version"] == 1
    assert report["all"]["joint_ate_m"] == pytest.approx(
        evaluation["global_joint_se3_rmse_m"], rel=1e-9)
    assert report["all"]["odometry_joint_ate_m"] == pytest.approx(
        evaluation["odometry_joint_se3_rmse_m"], rel=1e-9)
    # The run's report rendered the map at ground-truth poses (RENDER_VIEWS per agent).
    assert first["render"]["lpips"] is None and "LPIPS omitted" in at_the_end
    assert all(len(r["frames"]) == 5 for r in first["render"]["agents"].values())


def test_explicit_ground_truth_replaces_the_recorded_one(collab, scene, tmp_path: Path) -> None:
    run, _ = collab
    from cpslam.common.trajectory import write_tum
    from cpslam.tools.eval import load_trajectory

    moved = load_trajectory(scene.agent_dirs[1])
    poses = moved.poses.copy()
    poses[:, 0, 3] += np.linspace(0, 0.5, len(poses))  # a drift: agent 1's ATE grows
    write_tum(tmp_path / "gt1.tum", moved.stamps, poses)
    _invoke(["report", str(run), "--gt", f"1={tmp_path / 'gt1.tum'}", "--no-mesh",
             "--no-progress", "--render-views", "0"])
    report = json.loads((run / "report.json").read_text())
    assert report["ground_truth"]["1"] == str(tmp_path / "gt1.tum")
    assert report["ground_truth"]["0"] == str(scene.agent_dirs[0].resolve())
    result = CliRunner(env=ENV).invoke(app, ["report", str(run), "--gt", "7=x", "--no-mesh"])
    assert result.exit_code == 2 and "agent '7' is not in this run" in result.output


def test_render_metrics_match_scikit_image(collab, tmp_path: Path) -> None:
    metrics = pytest.importorskip("skimage.metrics")
    import cv2

    run, _ = collab
    text = _invoke(["eval", "render", str(run), "--views", "3", "--json",
                    "--save-images", str(tmp_path / "img")])
    record = json.loads(text[text.index("{"):])
    assert record["schema_version"] == 1 and record["lpips"] is None
    psnrs, ssims = [], []
    for a, row in record["agents"].items():
        assert len(row["frames"]) == 3
        for i, index in enumerate(row["frames"]):
            render, gt = (cv2.imread(str(tmp_path / "img" / f"agent_{a}" /
                                         f"{index:06d}_{k}.png"))[..., ::-1] / 255.0
                          for k in ("render", "gt"))
            expect_psnr = metrics.peak_signal_noise_ratio(gt, render, data_range=1.0)
            expect_ssim = metrics.structural_similarity(
                gt, render, data_range=1.0, channel_axis=-1, gaussian_weights=True,
                sigma=1.5, use_sample_covariance=False)
            assert row["psnr_db"][i] == pytest.approx(expect_psnr, rel=1e-9)
            assert row["ssim"][i] == pytest.approx(expect_ssim, rel=1e-9, abs=1e-12)
            psnrs.append(expect_psnr)
            ssims.append(expect_ssim)
    assert record["psnr_db"] == pytest.approx(np.mean(psnrs), rel=1e-9)
    assert record["ssim"] == pytest.approx(np.mean(ssims), rel=1e-9)
    # Renders of a map, not copies of the frames: never perfect, never unrelated.
    assert 5.0 < record["psnr_db"] < 60.0 and 0.0 < record["ssim"] < 1.0
    assert 0.0 < record["depth_l1_m"] < 1.0


def test_lone_agent_folder_report_and_mesh(scene, tmp_path: Path) -> None:
    from cpslam.agent_cli import app as agent_app

    run = tmp_path / "alone"
    result = CliRunner(env=ENV).invoke(agent_app, [
        "--seq", str(scene.agent_dirs[0]), "--standalone", "--no-loops", "--preset", "tiny",
        "--frames", "0:30:2", "--out", str(run), "--no-progress"], catch_exceptions=False)
    assert result.exit_code == 0, result.output
    text = _invoke(["report", str(run), "--no-mesh", "--no-progress", "--render-views", "2"])
    report = json.loads((run / "report.json").read_text())
    assert report["kind"] == "agent" and list(report["agents"]) == ["0"]
    assert report["agents"]["0"]["frames"] == 15 and report["all"]["joint_ate_m"] is not None
    assert "memory_mb" in report and "server" not in report["memory_mb"]
    assert "one agent, no server" in text and report["render"]["map"] == "agent 0"
    mesh = json.loads(_invoke(["mesh", str(run), "--views", "3", "--json", "--no-progress"]))
    assert mesh["schema_version"] == 1 and mesh["frame"] == "agent 0"
    assert mesh["triangles"] > 0 and Path(mesh["path"]).is_file()
    refused = CliRunner(env=ENV).invoke(app, ["mesh", str(run), "--views", "3"])
    assert refused.exit_code == 2 and "--overwrite" in refused.output

"""A robot's bag straight into the agent: a ROS 2 bag written from 7-Scenes frames with
`rosbags`, run by `cpslam-agent --standalone` and `cpslam run`, scored by `cpslam eval ate`
against the bag's own pose topic."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from bag_writer import write_bag
from typer.testing import CliRunner

from cpslam.agent_cli import app as agent_app
from cpslam.cli import app as cpslam_app
from cpslam.common.datasets import open_sequence
from cpslam.common.trajectory import read_tum

pytest.importorskip("rosbags", reason="needs the bags extra: pip install 'cpslam[bags]'")
pytestmark = [pytest.mark.slow, pytest.mark.data]
runner = CliRunner()
FAST = ["--preset", "tiny", "--no-progress", "--frames", "0:3", "--set", "mapping.iters_first=30"]


@pytest.fixture(scope="module")
def bag(kitchen_path: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    source = open_sequence(kitchen_path, frames="0:6")
    return write_bag(tmp_path_factory.mktemp("bag") / "kitchen", source, "ros2", compressed=True)


def test_agent_runs_on_a_bag_and_is_scored_against_its_pose_topic(bag: Path,
                                                                  tmp_path: Path) -> None:
    run = tmp_path / "agent"
    result = runner.invoke(agent_app, ["--seq", str(bag), "--standalone", "--no-loops",
                                       "--topic-rgb", "/camera/color/image_raw/compressed",
                                       "--out", str(run), *FAST])
    assert result.exit_code == 0, result.output
    stamps, _ = read_tum(run / "agent_0" / "trajectory.tum")
    # the bag's header stamps, as written (TUM files keep microseconds)
    np.testing.assert_allclose(stamps, open_sequence(bag).timestamps[:3], rtol=0, atol=1e-6)
    result = runner.invoke(cpslam_app, ["eval", "ate", "--gt", str(bag), "--est", str(run),
                                        "--out", str(tmp_path / "ate.json")])
    assert result.exit_code == 0, result.output
    ate = json.loads((tmp_path / "ate.json").read_text())
    # over seeds 0-4 the RMSE was 0.35-1.9 cm; 5 cm leaves room for other CPUs
    assert ate["n_pairs"] == 3 and ate["rmse_m"] < 0.05


def test_run_takes_a_bag(bag: Path, tmp_path: Path) -> None:
    run = tmp_path / "run"
    result = runner.invoke(cpslam_app, ["run", "--seq", str(bag), "--out", str(run), *FAST])
    assert result.exit_code == 0, result.output
    assert len(read_tum(run / "agent_0" / "trajectory.tum")[0]) == 3
    assert (run / "evaluation.json").is_file()  # the bag's pose topic is ground truth


def test_bad_topic_is_a_usage_error(bag: Path, tmp_path: Path) -> None:
    result = runner.invoke(agent_app, ["--seq", str(bag), "--standalone", "--topic-depth",
                                       "/nope", "--out", str(tmp_path / "x"), *FAST])
    assert result.exit_code == 2
    assert "--topic-depth /nope: no such topic" in " ".join(result.output.split())

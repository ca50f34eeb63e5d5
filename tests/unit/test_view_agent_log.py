"""`run.rerun`: an agent logging itself to Rerun (`cpslam.tools.view.agent_log`); the unit
test feeds a recorder made-up frames on a fake clock and reads the .rrd back with Rerun's own
reader, the end-to-end test runs the real standalone agent with `run.rerun=save`."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import torch
from view_rrd import positions, read_rrd, strips

from cpslam.common.camera import Intrinsics
from cpslam.common.config import load_config
from tests.unit.spec_helpers import spec

pytest.importorskip("rerun")


@dataclass
class _Result:
    index: int
    timestamp: float
    T_world_cam: np.ndarray
    is_keyframe: bool
    kf_id: int | None
    track_loss: float = 0.1


@dataclass
class _Frame:
    rgb: np.ndarray


class _Odometry:
    def __init__(self) -> None:
        s = spec("tiny")
        self.intrinsics = Intrinsics(60.0, 60.0, 40.0, 30.0, 80, 60)
        self.point_map = s.point_map(0, "cpu")
        self.point_map.set_keyframe_poses(0, np.eye(4), 0)

    def grow(self, n: int) -> None:
        f = self.point_map.feature_dim
        self.point_map.add_points(torch.rand(n, 3) * 4.0, 0, torch.zeros(n, f),
                                  torch.full((n, 3), 200, dtype=torch.uint8))


def test_recorder_logs_every_pose_each_keyframe_and_the_map_at_its_rate(tmp_path: Path) -> None:
    from cpslam.tools.view.agent_log import LIVE_FILE, AgentRecorder

    now = [0.0]
    cfg = load_config("tiny", env={}).run.model_copy(update={"rerun": "save",
                                                             "rerun_every_s": 2.0})
    recorder = AgentRecorder.from_config(cfg, "robot-1", tmp_path)
    recorder._clock = lambda: now[0]
    odometry = _Odometry()
    frames, sizes = 10, []
    for i in range(frames):
        odometry.grow(50)
        sizes.append(len(odometry.point_map))
        T = np.eye(4)
        T[:3, 3] = [0.1 * i, 0.0, 0.0]
        recorder(_Frame(np.full((60, 80, 3), 20 * i, np.uint8)),
                 _Result(i, i / 30, T, i % 5 == 0, i // 5 if i % 5 == 0 else None), odometry)
        now[0] += 0.5  # full logs at frames 0, 4 and 8
    recorder.close()
    assert AgentRecorder.from_config(cfg.model_copy(update={"rerun": None}), "x",
                                     tmp_path) is None

    rows = read_rrd(tmp_path / LIVE_FILE)
    base = "world/agents/robot-1"
    assert len([r for r in rows[f"{base}/camera"] if r.get("Transform3D:translation")]) \
        == frames
    assert {f"{base}/keyframes/0", f"{base}/keyframes/1"} <= rows.keys()
    assert f"{base}/keyframes/0/image" in rows
    points = [r for r in rows[f"{base}/points"] if r.get("Points3D:positions")]
    assert len(points) == 3
    assert len(positions(points)) == sizes[8] > sizes[4]  # the map as it was at frame 8
    line = strips(rows[f"{base}/trajectory"])[0]
    np.testing.assert_allclose(line[:, 0], 0.1 * np.arange(9), atol=1e-6)


@pytest.mark.slow  # a real standalone run (~20 s on a shared 2-core machine)
def test_standalone_agent_saves_its_live_recording(tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from cpslam.agent_cli import app as agent_app
    from cpslam.cli import app as cpslam_app

    pytest.importorskip("open3d")  # the synthetic renderer
    runner = CliRunner()
    data = tmp_path / "room"
    result = runner.invoke(cpslam_app, ["dataset", "synth", "--scene", "room", "--loop",
                                        "--num-frames", "10", "--width", "96", "--height",
                                        "72", "--out", str(data)])
    assert result.exit_code == 0, result.output
    run = tmp_path / "run"
    result = runner.invoke(agent_app, [
        "--seq", str(data / "agent_0"), "--standalone", "--no-loops", "--preset", "tiny",
        "--set", "run.rerun=save", "--set", "mapping.iters_first=30", "--no-progress",
        "--out", str(run)])
    assert result.exit_code == 0, result.output
    rows = read_rrd(run / "agent_0" / "live.rrd")
    cameras = [r for r in rows["world/agents/0/camera"] if r.get("Transform3D:translation")]
    assert len(cameras) == 10
    assert any(k.startswith("world/agents/0/keyframes/") for k in rows)
    assert len(positions(rows["world/agents/0/points"])) > 0

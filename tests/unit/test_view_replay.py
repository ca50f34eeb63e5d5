"""`cpslam view RUN --save`: a real two-agent tiny run replayed to an .rrd and read back with
Rerun's own reader; every entity holds what the run folder holds."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import typer
from typer.testing import CliRunner
from view_rrd import last, positions, read_rrd, strips

from cpslam.common.trajectory import read_tum

FRAMES = 8


def _cli(args: list[str]):
    from cpslam.tools.view.cli import view

    app = typer.Typer()
    app.command()(view)
    return CliRunner().invoke(app, args, catch_exceptions=False)


@pytest.fixture(scope="module")
def run_folder(tmp_path_factory) -> tuple[Path, dict[str, Path]]:
    """Two agents × 12 frames of a 160×120 apartment with `cpslam run --preset tiny`."""
    pytest.importorskip("open3d")  # the synthetic renderer
    from cpslam.run import run
    from cpslam.tools.synth import generate

    tmp = tmp_path_factory.mktemp("view")
    data = generate(tmp / "apt", scene="apartment", agents=2, frames=FRAMES, width=160,
                    height=120, seed=0)
    out = tmp / "run"
    app = typer.Typer()
    app.command()(run)
    result = CliRunner().invoke(app, [
        "--seq", str(data.agent_dirs[0]), "--seq", str(data.agent_dirs[1]), "--preset",
        "tiny", "--set", "mapping.iters_first=30", "--out", str(out), "--no-progress"],
        catch_exceptions=False)
    assert result.exit_code == 0, result.output
    return out, {"0": data.agent_dirs[0], "1": data.agent_dirs[1]}


@pytest.mark.slow  # the run: ~25 s on a shared 2-core machine
def test_replay_holds_each_agents_trajectory_keyframes_and_points(run_folder, tmp_path):
    pytest.importorskip("rerun")
    import torch

    run, seqs = run_folder
    rrd = tmp_path / "run.rrd"
    result = _cli([str(run), "--save", str(rrd), "--gt", f"0={seqs['0']}", "--gt",
                   f"1={seqs['1']}"])
    assert result.exit_code == 0, result.output
    assert f"rerun {rrd}" in result.output
    data = read_rrd(rrd)
    metrics = json.loads((run / "metrics.json").read_text())
    total = 0
    for a in ("0", "1"):
        stamps, poses = read_tum(run / "trajectories" / f"agent_{a}_global.tum")
        (line,) = strips(data[f"world/agents/{a}/trajectory"])
        np.testing.assert_allclose(line, poses[:, :3, 3], atol=1e-5)
        (gt,) = strips(data[f"world/agents/{a}/ground_truth"])
        assert len(gt) == FRAMES
        assert len(data[f"world/agents/{a}/camera"]) == len(stamps) == FRAMES
        state = torch.load(run / f"agent_{a}" / "state.pt", weights_only=True)
        kf_ids = sorted(int(k["kf_id"]) for k in state["keyframes"]["keyframes"])
        logged = sorted(int(p.rsplit("/", 1)[1]) for p in data
                        if p.startswith(f"world/agents/{a}/keyframes/")
                        and not p.endswith("/image"))
        assert logged == kf_ids and kf_ids
        for kf in kf_ids:
            rows = data[f"world/agents/{a}/keyframes/{kf}"]
            assert last(rows, "Pinhole:resolution")
            assert last(data[f"world/agents/{a}/keyframes/{kf}/image"], "EncodedImage:blob")
        n = len(positions(data[f"world/agents/{a}/points"]))
        # Agent numbers in the fused map come from metrics.json.
        index = metrics["agents"][a]["index"]
        files = sorted(run.glob("fused_map_*.pt")) or [run / "fused_map.pt"]
        expected = sum(int((torch.load(f, weights_only=True)["agent_id"] == index).sum())
                       for f in files)
        assert n == expected > 0
        total += n
    assert len(positions(data["world/map/by_agent"])) == total
    edges = sum(line.startswith("EDGE") for line in
                (run / "pose_graph.g2o").read_text().splitlines())
    assert len(strips(data["world/pose_graph/edges"])) == edges > 0
    loops = metrics["loops"]["list"]
    for verdict, flag in (("accepted", True), ("rejected", False)):
        assert len(strips(data[f"world/loops/{verdict}"])) == sum(
            bool(lp["accepted"]) == flag for lp in loops)


@pytest.mark.slow
def test_replay_draws_loops_by_verdict_and_events_on_the_timeline(run_folder, tmp_path):
    """The run's metrics with two loop records and a merge added (the tiny run finds none)."""
    pytest.importorskip("rerun")
    from cpslam.tools.view.cli import save_replay

    run = tmp_path / "run"
    shutil.copytree(run_folder[0], run)
    metrics = json.loads((run / "metrics.json").read_text())
    metrics["loops"]["list"] = [
        {"agent_a": "0", "kf_a": 0, "agent_b": "1", "kf_b": 0, "score": 0.93,
         "accepted": True, "stamp": 4.0, "kind": "fine"},
        {"agent_a": "1", "kf_a": 0, "agent_b": "0", "kf_b": 0, "score": 0.71,
         "accepted": False, "reason": "fitness 0.1 < 0.3", "stamp": 2.0, "kind": "coarse"},
        {"agent_a": "0", "kf_a": 999, "agent_b": "1", "kf_b": 0, "score": 0.9,
         "accepted": True, "stamp": 5.0, "kind": "fine"}]
    metrics["merges"] = [{"time": 4.5, "group": "0", "members": ["0", "1"]}]
    metrics["rounds"]["list"] = [{"group": "0", "round": 1, "time": 6.0}]
    (run / "metrics.json").write_text(json.dumps(metrics))
    counts = save_replay(run, tmp_path / "loops.rrd")
    assert counts["loops"] == {"accepted": 1, "rejected": 1, "without_pose": 1}
    data = read_rrd(tmp_path / "loops.rrd")
    (accepted,) = strips(data["world/loops/accepted"])
    (rejected,) = strips(data["world/loops/rejected"])
    np.testing.assert_allclose(accepted, rejected[::-1], atol=1e-9)  # the same pair, reversed
    assert last(data["world/loops/accepted"], "LineStrips3D:labels") == ["0.93"]
    assert "fitness" in last(data["world/loops/rejected"], "LineStrips3D:labels")[0]
    assert len(data["events/loops"]) == 3 and len(data["events/merges"]) == 1
    assert len(data["events/rounds"]) == 1
    # Events sit on the server's clock in the order they happened.
    times = [row["run_time"] for row in data["events/loops"]]
    assert times == sorted(times)


@pytest.mark.slow
def test_replay_of_an_agent_alone_uses_its_own_folder(run_folder, tmp_path):
    """What `cpslam-agent --standalone --no-loops` leaves: agent_<id>/ and no server outputs."""
    pytest.importorskip("rerun")
    import torch

    from cpslam.tools.view.cli import save_replay

    run = tmp_path / "alone"
    shutil.copytree(run_folder[0] / "agent_1", run / "agent_1")
    counts = save_replay(run, tmp_path / "alone.rrd")
    data = read_rrd(tmp_path / "alone.rrd")
    _, poses = read_tum(run / "agent_1" / "trajectory.tum")
    (line,) = strips(data["world/agents/1/trajectory"])
    np.testing.assert_allclose(line, poses[:, :3, 3], atol=1e-5)
    state = torch.load(run / "agent_1" / "state.pt", weights_only=True)
    n = len(state["point_map"]["xyz_local"])
    assert counts["agents"]["1"]["points"] == len(positions(data["world/agents/1/points"])) == n
    assert counts["agents"]["1"]["keyframes"] == len(state["keyframes"]["keyframes"])
    assert counts["loops"] == {"accepted": 0, "rejected": 0, "without_pose": 0}


def test_view_refuses_a_folder_without_trajectories(tmp_path):
    (tmp_path / "empty").mkdir()
    result = _cli([str(tmp_path / "empty"), "--save", str(tmp_path / "x.rrd")])
    assert result.exit_code == 2 and "agent_<id>_global.tum" in result.output
    assert not (tmp_path / "x.rrd").exists()
    result = _cli([])
    assert result.exit_code == 2 and "--connect" in result.output


def test_without_rerun_view_says_how_to_install_it(tmp_path):
    """rerun hidden from the import system: the command exits 1 with the install line."""
    (tmp_path / "run" / "trajectories").mkdir(parents=True)
    (tmp_path / "run" / "trajectories" / "agent_0_global.tum").write_text("")
    code = ("import sys; sys.modules['rerun'] = None; from cpslam.cli import main; "
            f"sys.argv = ['cpslam', 'view', {str(tmp_path / 'run')!r}, '--save', "
            f"{str(tmp_path / 'x.rrd')!r}]; main()")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 1, done.stderr
    assert "pip install 'cpslam[viz]'" in done.stderr

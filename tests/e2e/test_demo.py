"""`cpslam demo --preset tiny` end to end: real server and agent processes over loopback TCP.

Small on purpose (two agents × 30 frames of a 160×120 apartment, tiny preset: about a minute
on two cores): it checks that the pieces run together and every output is written, not
accuracy (30 frames spread over the 300-frame walk move 10 cm per frame, too fast for tiny).
"""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import pytest

from cpslam.common.device import usable_cores

pytestmark = pytest.mark.slow
pytest.importorskip("open3d")


def test_demo_tiny_end_to_end(tmp_path: Path) -> None:
    out = tmp_path / "demo"
    cmd = [sys.executable, "-m", "cpslam", "demo", "--preset", "tiny", "--agents", "2",
           "--num-frames", "30", "--width", "160", "--height", "120", "--out", str(out),
           "--set", "run.num_threads=auto",
           "--data-dir", str(tmp_path / "data"), "--no-progress", "--timeout", "600"]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=900,
                          env={"COLUMNS": "120", **_env()})
    logs = "\n".join(f"--- {p.name}\n{p.read_text()[-3000:]}"
                     for p in sorted((out / "logs").glob("*.log")))
    assert done.returncode == 0, done.stdout + done.stderr + logs

    for name in ("trajectories/agent_0_global.tum", "trajectories/agent_1_global.tum",
                 "fused_map.ply", "mesh.ply", "pose_graph.g2o", "metrics.json", "report.json",
                 "plots/trajectories_global.png", "plots/trajectories_local.png",
                 "logs/server.log", "logs/agent_0.log", "logs/agent_1.log", "demo.json"):
        assert (out / name).is_file(), name
    report = json.loads((out / "report.json").read_text())
    assert sorted(report["agents"]) == ["0", "1"]
    for row in report["agents"].values():
        assert row["frames"] == 30
        assert row["sent_bytes"] > 10_000 and row["points"] > 0
        assert row["global_ate_m"] is not None
    assert report["all"]["joint_ate_m"] is not None
    assert report["mesh"]["triangles"] > 0
    assert report["schema_version"] == 1 and report["kind"] == "collaborative"
    assert report["recon"]["completion_ratio_pct"] > 0  # the synthetic scene's mesh
    assert report["render"]["psnr_db"] > 0 and report["render"]["lpips"] is None
    assert "ATE glob" in done.stdout and "outputs in" in done.stdout
    if importlib.util.find_spec("rerun") is not None:  # the viz extra: the 3-D view too
        assert (out / "demo.rrd").stat().st_size > 10_000
        assert f"rerun {out / 'demo.rrd'}" in done.stdout

    # `cpslam report` on the demo's folder (the daemons' shared --out, ground truth from what
    # the agents recorded) prints the tables the demo printed: one report code path.
    again = subprocess.run([sys.executable, "-m", "cpslam", "report", str(out), "--no-mesh",
                            "--no-progress", "--render-views", "0"], capture_output=True,
                           text=True, timeout=600, env={"COLUMNS": "120", **_env()})
    assert again.returncode == 0, again.stdout + again.stderr
    assert _tables(again.stdout) == _tables(done.stdout)
    assert json.loads((out / "report.json").read_text())["agents"] == report["agents"]
    info = json.loads((out / "demo.json").read_text())
    assert info["frame_slice"] == "0:300:10" and info["wall_s"] > 0
    # `auto` threads: the server and the two agents divide the cores between them.
    threads = max(1, usable_cores() // 3)
    assert f"run.num_threads={threads}" in info["sets"]
    assert f"({threads} CPU threads)" in (out / "logs" / "agent_0.log").read_text()

    # A second run refuses the earlier demo folder without --overwrite; with it, it reuses the
    # cached scene, replaces the folder, and gives up cleanly at its --timeout (every child
    # stopped).
    scene = next((tmp_path / "data").glob("*/scene.json"))
    stamp = scene.stat().st_mtime_ns
    (out / "stale.txt").write_text("from the first run")
    refused = subprocess.run([*cmd[:-2], "--timeout", "3"], capture_output=True, text=True,
                             timeout=300, env=_env())
    assert refused.returncode == 2 and "--overwrite" in refused.stderr, refused.stderr
    assert (out / "stale.txt").is_file()
    again = subprocess.run([*cmd[:-2], "--timeout", "3", "--overwrite"], capture_output=True,
                           text=True, timeout=300, env=_env())
    assert again.returncode == 1 and "--timeout reached" in again.stderr, again.stderr
    assert not (out / "stale.txt").exists() and scene.stat().st_mtime_ns == stamp


def _tables(text: str) -> list[str]:
    """From the results table's header to the traffic table's end (the title and the
    reporting process's memory differ between reports of one run)."""
    lines = text.splitlines()
    start = next(i for i, line in enumerate(lines) if line.split()[:2] == ["agent", "frames"])
    stop = next(i for i, line in enumerate(lines) if line.startswith("peak memory"))
    return [line.rstrip() for line in lines[start:stop]]


def _env() -> dict[str, str]:
    import os

    return {k: v for k, v in os.environ.items() if k != "COLUMNS"}

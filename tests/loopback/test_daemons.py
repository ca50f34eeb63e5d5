"""The daemons as separate OS processes over Zenoh TCP on 127.0.0.1 (tiny preset).

- two agents merge into one group, federated rounds close, the final pose graph runs, the
  outputs exist and the global trajectories agree with ground truth;
- faults: an agent that joins late, an agent killed with SIGKILL (the server keeps what it
  had delivered), a server killed and restarted on the same run folder (agents resend, nothing
  is lost), a server killed and restarted without its state (agents stream everything again).
"""

from __future__ import annotations

import importlib.util
import json
import signal
from pathlib import Path

import pytest
from daemons import (
    Daemon,
    agent_args,
    agent_field,
    finalise,
    server_args,
    status,
    tum_rows,
    wait_until,
)

pytestmark = [pytest.mark.loopback, pytest.mark.slow]
VIZ = importlib.util.find_spec("rerun") is not None
pytest.importorskip("open3d")  # the synthetic renderer


def test_two_agents_merge_over_tcp(tmp_path: Path, endpoint: str, apartment, daemons) -> None:
    from cpslam.common.datasets import open_sequence
    from cpslam.common.trajectory import read_tum
    from cpslam.tools.eval import joint_ate

    out, s = tmp_path / "run", "merge"
    server = Daemon("server", server_args(endpoint, s, out), tmp_path)
    daemons.append(server)
    # A live 3-D view of the session, when the viz extra is installed (it only listens).
    live = tmp_path / "live.rrd"
    viewer = Daemon("viewer", ["-m", "cpslam", "view", "--connect", endpoint, "--session", s,
                               "--save", str(live)], tmp_path) if VIZ else None
    daemons.extend([viewer] if viewer else [])
    agents = [Daemon(f"agent{a}", agent_args(apartment.agent_dirs[a], str(a), endpoint, s, out,
                                             "--frames", "0:300:3"), tmp_path)
              for a in (0, 1)]
    daemons.extend(agents)
    for agent in agents:
        assert agent.wait(600) == 0, agent.tail()
    summary = status(endpoint, s)
    assert summary is not None, server.tail()
    assert sorted(summary["agents"]) == ["0", "1"]
    finalise(endpoint, s)
    # Generous: after finalising, the server runs `cpslam report` (its mesh renders 40 views).
    assert server.wait(900) == 0, server.tail()
    if viewer is not None:
        viewer.signal(signal.SIGINT)
        assert viewer.wait(60) == 0, viewer.tail()
        _check_live_view(live)

    metrics = json.loads((out / "metrics.json").read_text())
    # The agents shared the server's folder and their sequences have ground truth: the
    # server reported, finding the ground truth the agents recorded.
    report = json.loads((out / "report.json").read_text())
    assert report["ground_truth"] == {a: str(apartment.agent_dirs[int(a)].resolve())
                                      for a in ("0", "1")}
    assert report["all"]["joint_ate_m"] is not None and (out / "mesh.ply").is_file()
    assert len(metrics["groups"]) == 1, metrics["groups"]
    assert sorted(metrics["groups"][0]["members"]) == ["0", "1"]
    assert metrics["merges"] and metrics["rounds"]["closed"] >= 1, (metrics["rounds"],
                                                                    server.tail())
    assert metrics["pose_graph"], "the final pose graph did not run"
    assert metrics["bus"]["traffic"]["received"], "no traffic recorded"
    for name in ("fused_map.ply", "pose_graph.g2o", "config.yaml", "server.log"):
        assert (out / name).is_file(), name
    pairs = []
    for a in ("0", "1"):
        agent_metrics = json.loads((out / f"agent_{a}" / "metrics.json").read_text())
        assert agent_metrics["unacknowledged"] == 0
        assert any(f"/agent/{a}/keyframe" in k for k in agent_metrics["bus"]["sent"])
        est = read_tum(out / "trajectories" / f"agent_{a}_global.tum")
        assert len(est[0]) == 100
        seq = open_sequence(apartment.agent_dirs[int(a)])
        pairs.append(((seq.timestamps, seq.gt_poses()), est))
    # The same bound as the in-process run (tests/integration/test_run.py): tiny is coarse.
    assert joint_ate(pairs, align="se3").overall.rmse < 0.8


def _check_live_view(path: Path) -> None:
    """Both agents' keyframes, trajectories and points, and their merge, reached the view."""
    from view_rrd import positions, read_rrd

    data = read_rrd(path)
    for a in ("0", "1"):
        assert any(p.startswith(f"world/agents/{a}/keyframes/") for p in data), sorted(data)
        assert data[f"world/agents/{a}/trajectory"] and data[f"world/agents/{a}/camera"]
        assert len(positions(data[f"world/agents/{a}/points"])) > 0
    assert data["events/merges"] and data["status/loops/found"]


def test_late_joiner_and_killed_agent(tmp_path: Path, endpoint: str, apartment,
                                      daemons) -> None:
    out, s = tmp_path / "run", "faults"
    server = Daemon("server", server_args(endpoint, s, out, "--no-report"), tmp_path)
    victim = Daemon("agent0", agent_args(apartment.agent_dirs[0], "0", endpoint, s, out,
                                         "--frames", "0:120"), tmp_path)
    daemons.extend([server, victim])

    def frames_of(agent: str) -> int:
        return agent_field(endpoint, s, agent, "frames", 0)

    wait_until("agent 0 to deliver frames", lambda: frames_of("0") >= 20, 300, server, victim)
    late = Daemon("agent1", agent_args(apartment.agent_dirs[1], "1", endpoint, s, out,
                                       "--frames", "0:60"), tmp_path)
    daemons.append(late)
    wait_until("the late agent to deliver frames", lambda: frames_of("1") >= 10, 300, server,
               late)
    victim.signal(signal.SIGKILL)
    victim.proc.wait(10)
    delivered = frames_of("0")
    wait_until("the server to see agent 0 leave",
               lambda: not agent_field(endpoint, s, "0", "alive", True), 30, server)
    assert late.wait(600) == 0, late.tail()
    finalise(endpoint, s)
    assert server.wait(120) == 0, server.tail()
    assert "agent 0 left" in server.text()
    assert tum_rows(out / "trajectories" / "agent_0_global.tum") >= delivered >= 20
    assert tum_rows(out / "trajectories" / "agent_1_global.tum") == 60


def _restart_server_mid_stream(tmp_path: Path, endpoint: str, apartment, daemons, s: str,
                               keep_state: bool) -> tuple[Daemon, Daemon, Path]:
    """Start a server and agent 0 (90 frames), SIGKILL the server once four keyframes reached
    it, start a second server (on the first one's run folder if `keep_state`, else on a fresh
    one), and run to the end: (agent, second server, the agent's and second server's run
    folder)."""
    out = tmp_path / "run"
    first_out = out if keep_state else tmp_path / "first"
    first = Daemon("server1", server_args(endpoint, s, first_out, "--no-report"), tmp_path)
    agent = Daemon("agent0", agent_args(apartment.agent_dirs[0], "0", endpoint, s, out,
                                        "--frames", "0:90"), tmp_path)
    daemons.extend([first, agent])

    # The server writes its state at most once per persist interval after a keyframe
    # arrives, so the kill waits for the first snapshot too (a server killed before it has
    # acknowledged nothing, and there is no state to resume from).
    wait_until("keyframes to reach the first server and its first snapshot",
               lambda: agent_field(endpoint, s, "0", "keyframes", 0) >= 4
               and (first_out / "server_state.pt").is_file(), 300, first, agent)
    first.signal(signal.SIGKILL)
    first.proc.wait(10)
    if keep_state:
        assert (out / "server_state.pt").is_file()
    second = Daemon("server2", server_args(endpoint, s, out, "--no-report"), tmp_path)
    daemons.append(second)
    assert agent.wait(600) == 0, agent.tail() + "\n" + second.tail()
    finalise(endpoint, s)
    assert second.wait(120) == 0, second.tail()
    return agent, second, out


def test_server_restart_loses_nothing(tmp_path: Path, endpoint: str, apartment,
                                      daemons) -> None:
    agent, second, out = _restart_server_mid_stream(tmp_path, endpoint, apartment, daemons,
                                                    "restart", keep_state=True)
    assert "restored server state" in second.text()
    assert "server is back; resent" in agent.text()
    assert tum_rows(out / "trajectories" / "agent_0_global.tum") == 90
    agent_metrics = json.loads((out / "agent_0" / "metrics.json").read_text())
    assert agent_metrics["unacknowledged"] == 0 and agent_metrics["server_rejoins"] >= 1
    assert agent_metrics["stream_restarts"] == 0  # the same state id came back


def test_server_restart_without_state_loses_nothing(tmp_path: Path, endpoint: str, apartment,
                                                    daemons) -> None:
    agent, second, out = _restart_server_mid_stream(tmp_path, endpoint, apartment, daemons,
                                                    "fresh", keep_state=False)
    assert "restored server state" not in second.text()
    assert "streaming everything again" in agent.text()
    assert tum_rows(out / "trajectories" / "agent_0_global.tum") == 90
    agent_metrics = json.loads((out / "agent_0" / "metrics.json").read_text())
    assert agent_metrics["unacknowledged"] == 0 and agent_metrics["stream_restarts"] == 1
    server_metrics = json.loads((out / "metrics.json").read_text())
    assert server_metrics["agents"]["0"]["frames"] == 90
    assert not server_metrics["agents"]["0"]["dropped"]

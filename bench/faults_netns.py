"""Fault (f) of bench/faults.py: a network partition between agent 0 and the server.

The server and each agent run as real processes (`cpslam.server.cli`, `cpslam.agent_cli`,
Zenoh over TCP), each in a Linux network namespace of its own joined to the server's by a veth
pair (`cpslam.tools.netns`, as in tests/loopback/test_netns.py). Two runs: fault-free, then
with agent 0's veth end down for `partition_s` once its first keyframe reached the server
(packets vanish as on a cut cable; longer than the Zenoh lease, so the session is torn down
and rebuilt). Needs root (CAP_NET_ADMIN) and iproute2; otherwise the result says why it was
skipped.

Lost, per agent, from what the processes left: the agent's state.pt (frames, keyframes, own
points) and metrics.json (unacknowledged, dropped by the server) against the server's durable
state (server_state.pt, its registry) and the final global trajectory.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from fault_run import LOSS_COUNTS, split_drops

from cpslam.tools import netns

PORT = 7447
AGENTS = ("0", "1")
# One torch thread per process: several share few cores.
ENV = {**os.environ, "OMP_NUM_THREADS": "1", "CPSLAM_RUN__NUM_THREADS": "1"}


def _proc(prefix: list[str], args: list[str], log: Path) -> subprocess.Popen:
    with log.open("w") as fh:
        return subprocess.Popen(
            [*prefix, sys.executable, *args],
            stdout=fh,
            stderr=subprocess.STDOUT,
            env=ENV,
        )


def _status(net: netns.Network, session: str) -> dict:
    done = subprocess.run(
        [
            *net.prefix("server"),
            sys.executable,
            "-m",
            "cpslam",
            "status",
            "--connect",
            f"tcp/127.0.0.1:{PORT}",
            "--session",
            session,
            "--json",
            "--timeout",
            "10",
        ],
        capture_output=True,
        text=True,
        env=ENV,
        timeout=60,
    )
    return json.loads(done.stdout) if done.returncode == 0 else {}


def _one_run(
    net: netns.Network,
    seq: Path,
    frames: list[str],
    preset: str,
    sets: list[str],
    out: Path,
    partition_s: float,
) -> dict:
    session = out.name
    out.mkdir(parents=True, exist_ok=True)
    over = [x for s in sets for x in ("--set", s)]
    server = _proc(
        net.prefix("server"),
        [
            "-m",
            "cpslam.server.cli",
            "--listen",
            f"tcp/0.0.0.0:{PORT}",
            "--session",
            session,
            "--preset",
            preset,
            "--out",
            str(out / "run"),
            "--no-report",
            *over,
        ],
        out / "server.log",
    )
    agents = [
        _proc(
            net.prefix(a),
            [
                "-m",
                "cpslam.agent_cli",
                "--seq",
                str(seq),
                "--frames",
                f,
                "--agent-id",
                a,
                "--connect",
                f"tcp/{net.links[a].server_ip}:{PORT}",
                "--session",
                session,
                "--preset",
                preset,
                "--out",
                str(out / "run"),
                "--no-progress",
                *over,
            ],
            out / f"agent{a}.log",
        )
        for a, f in zip(AGENTS, frames, strict=True)
    ]
    t0 = time.perf_counter()
    try:
        if partition_s > 0:
            deadline = time.monotonic() + 900
            while _status(net, session).get("agents", {}).get("0", {}).get("keyframes", 0) < 1:
                if time.monotonic() > deadline or any(
                    p.poll() not in (None, 0) for p in (server, *agents)
                ):
                    raise RuntimeError(f"agent 0 delivered no keyframe; see {out}/*.log")
                time.sleep(1.0)
            net.partition("0")
            time.sleep(partition_s)
            net.heal("0")
        codes = [p.wait(1800) for p in agents]
        server.send_signal(signal.SIGTERM)  # finalise and exit
        codes.append(server.wait(600))
    finally:
        for p in (server, *agents):
            if p.poll() is None:
                p.kill()
                p.wait(10)
    return {
        "exit_codes": dict(zip([*AGENTS, "server"], codes, strict=True)),
        "wall_s": round(time.perf_counter() - t0, 1),
    }


def _losses(run: Path, preset: str, sets: list[str]) -> dict:
    import io

    import torch

    from cpslam.common import durable
    from cpslam.common.config import load_config
    from cpslam.common.trajectory import read_tum
    from cpslam.server.backend import Backend

    cfg = load_config(preset, overrides=sets, env={})
    backend = Backend.from_config(cfg, lambda *_: None)
    state, _ = durable.load_generation(
        run / "server_state.pt", lambda b: torch.load(io.BytesIO(b), weights_only=True)
    )
    backend.load_state_dict(state)
    out = {}
    for a in AGENTS:
        rec = backend.registry.agents[a]
        odo = torch.load(run / f"agent_{a}" / "state.pt", weights_only=True)
        pm = odo["point_map"]
        own = set(pm["point_id"][pm["agent_id"] == 0].tolist())
        kfs = {int(k["kf_id"]) for k in odo["keyframes"]["keyframes"]}
        metrics = json.loads((run / f"agent_{a}" / "metrics.json").read_text())
        held = set(rec.points.ids.tolist())
        drops, decoders = split_drops(dict(rec.dropped))
        rows = len(read_tum(run / "trajectories" / f"agent_{a}_global.tum")[0])
        out[a] = {
            "frames": metrics["frames"],
            "frames_lost": metrics["frames"] - len(rec.frames),
            "trajectory_rows_lost": metrics["frames"] - rows,
            "keyframes": len(kfs),
            "keyframes_lost": len(kfs - set(rec.keyframes)),
            "points": len(own),
            "points_lost": len(own - held),
            "points_stale": len(held - own),
            "unacknowledged": metrics["unacknowledged"],
            "dropped_by_server": sum(drops.values()),
            "decoders_dropped": decoders,
            "server_rejoins": metrics.get("server_rejoins"),
            "resent": metrics["resent"],
        }
    return out


def _ate(run: Path, seq: Path, frames: list[str], preset: str) -> float | None:
    from cpslam.agent.standalone import open_for_config
    from cpslam.common.config import load_config
    from cpslam.common.trajectory import read_tum
    from cpslam.tools.eval import joint_ate

    cfg = load_config(preset, env={})
    pairs = []
    for a, f in zip(AGENTS, frames, strict=True):
        s = open_for_config(cfg, seq, frames=f)
        pairs.append(
            ((s.timestamps, s.gt_poses()), read_tum(run / "trajectories" / f"agent_{a}_global.tum"))
        )
    return float(joint_ate(pairs, align="se3").overall.rmse)


def partition(
    seq: Path,
    frames: list[str],
    preset: str,
    partition_s: float,
    out: Path,
    seed: int = 0,
    sets: list[str] | None = None,
) -> dict[str, Any]:
    """Fault-free and partitioned runs of real processes; {"skipped": reason} where network
    namespaces cannot be made."""
    if shutil.which("ip") is None:
        return {"skipped": "iproute2 (`ip`) is not installed"}
    sets = [*(sets or []), f"run.seed={seed}", "run.num_threads=1"]
    try:
        net = netns.create(f"cpf{os.getpid() % 100000}", AGENTS, subnet="10.78")
    except netns.NetnsError as err:
        return {
            "skipped": f"cannot set up network namespaces here ({err}); needs root / "
            "CAP_NET_ADMIN and veth support"
        }
    if out.exists():
        shutil.rmtree(out)
    report: dict[str, Any] = {"partition_s": partition_s}
    try:
        for name, down in (("fault_free", 0.0), ("partitioned", partition_s)):
            row = _one_run(net, seq, frames, preset, sets, out / name, down)
            run = out / name / "run"
            row["lost"] = _losses(run, preset, sets)
            row["joint_ate_m"] = _ate(run, seq, frames, preset)
            report[name] = row
    finally:
        net.remove()
    part, free = report["partitioned"], report["fault_free"]
    report["nothing_lost"] = all(v == 0 for v in part["exit_codes"].values()) and all(
        row[c] == 0 for row in part["lost"].values() for c in LOSS_COUNTS
    )
    report["joint_ate_m"] = part["joint_ate_m"]
    report["fault_free_joint_ate_m"] = free["joint_ate_m"]
    if free["joint_ate_m"]:
        report["ate_ratio"] = round(part["joint_ate_m"] / free["joint_ate_m"], 4)
    report["wall_s"] = round(part["wall_s"] + free["wall_s"], 1)
    return report

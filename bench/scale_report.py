"""bench/scale.py's figures of one N: the row it prints and stores (rates, poll figures,
merges and their stages, loops, joint ATE of the replicas, bytes per agent per key)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

__all__ = ["merge_stages", "print_row", "summarise"]


def summarise(
    n: int,
    metrics: dict,
    server_dir: Path,
    seqs: list[tuple[Path, str]],
    replicas: list,
    played: dict,
    wall: float,
    cpu: float,
    merged_at: list[float],
    skipped: int,
    resent: int,
) -> dict:
    from cpslam.common.datasets import open_sequence
    from cpslam.common.trajectory import read_tum
    from cpslam.tools.eval import joint_ate

    poll = metrics["process"]["poll"]
    gts = {}
    for seq in seqs:
        if seq not in gts:
            sequence = open_sequence(seq[0]).select(seq[1])
            gts[seq] = (np.asarray(sequence.timestamps, np.float64), sequence.gt_poses())
    pairs = []
    for r, seq in zip(replicas, seqs, strict=True):
        path = server_dir / "trajectories" / f"agent_{r.agent_id}_global.tum"
        if path.is_file():
            pairs.append((gts[seq], read_tum(path)))
    ate = float(joint_ate(pairs, align="se3").overall.rmse) if pairs else None
    groups = metrics["groups"]
    per_agent = metrics["bus"]["per_agent"]
    bytes_per_key: dict[str, dict[str, float]] = {}
    for direction in ("from_agent", "to_agent"):
        table: dict[str, float] = {}
        for r in replicas:
            for topic, cell in per_agent.get(r.agent_id, {}).get(direction, {}).items():
                table[topic] = table.get(topic, 0.0) + cell["bytes"] / n
        bytes_per_key[direction] = {k: round(v) for k, v in sorted(table.items())}
    return {
        "agents": n,
        "replay_wall_s": round(wall, 2),
        "streamed_s": played["streamed_s"] and round(played["streamed_s"], 2),
        "unacknowledged": sum(played["unacknowledged"].values()),
        "skipped": skipped,
        "resent": resent,
        "messages_handled": poll["messages"],
        "messages_per_s": round(poll["messages"] / wall, 1),
        "server_cpu_share": round(cpu / wall, 3),
        "poll_worst_s": round(poll["worst_s"], 3),
        "poll_p99_s": round(poll["p99_s"], 3),
        "max_queue_depth": poll["max_queue_depth"],
        "peak_rss_mb": round(metrics["process"]["peak_rss_mb"], 1),
        "merges": len(metrics["merges"]),
        "merged_at_s": [round(t, 1) for t in merged_at],
        **merge_stages(metrics["merges"]),
        "largest_group": max(len(g["members"]) for g in groups),
        "loop_verification_s": round(metrics.get("timings", {}).get("loop_verification_s", 0), 2),
        "loops_found": metrics["loops"]["found"],
        "loops_skipped": metrics["loops"].get("skipped", 0),
        "loops_accepted": metrics["loops"]["accepted"],
        "joint_ate_m": ate and round(ate, 4),
        "bytes_per_agent": bytes_per_key,
    }


def merge_stages(merges: list[dict]) -> dict:
    """The slowest merge (s, from its timed stages) and each stage's worst over the merges."""
    stages = [m.get("stages", {}) for m in merges]
    names = sorted({k for st in stages for k in st})
    return {"merge_worst_s": round(max((m.get("seconds", 0.0) for m in merges), default=0.0), 3),
            "merge_stage_worst_s": {k: round(max(st.get(k, 0.0) for st in stages), 3)
                                    for k in names}}


def print_row(row: dict) -> None:
    last = row["merged_at_s"][-1] if row["merged_at_s"] else "-"
    print(
        f"N={row['agents']:>2}  msgs/s {row['messages_per_s']:>7}  "
        f"cpu {row['server_cpu_share']:.2f}"
        f"  poll worst/p99 {row['poll_worst_s']:.3f}/{row['poll_p99_s']:.3f} s  queue "
        f"{row['max_queue_depth']}  rss {row['peak_rss_mb']} MB  merges {row['merges']} (last "
        f"{last} s, worst {row['merge_worst_s']} s, verify {row['loop_verification_s']} s)  loops "
        f"{row['loops_accepted']}/{row['loops_found']}  group {row['largest_group']}/"
        f"{row['agents']}  joint ATE {row['joint_ate_m']} m  resent {row['resent']}",
        flush=True,
    )
    print("      merge stages, worst s " + json.dumps(row["merge_stage_worst_s"]), flush=True)
    print(
        "      bytes/agent from agent "
        + json.dumps(row["bytes_per_agent"]["from_agent"])
        + "  to agent "
        + json.dumps(row["bytes_per_agent"]["to_agent"]),
        flush=True,
    )

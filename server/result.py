"""What a finished run hands to `cpslam.server.export.export_run`: every agent's trajectory in
its own and its group's frame, the groups' refined maps and decoders, the final pose graph and
the metrics."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from cpslam.common.field import NeuralPointMap
from cpslam.common.geometry import compose, invert
from cpslam.server.pose_graph import PoseGraph, PoseGraphResult
from cpslam.server.tracks import trajectory_poses

if TYPE_CHECKING:
    from cpslam.server.groups import Group
    from cpslam.server.loops import LoopRecord
    from cpslam.server.registry import Registry

__all__ = ["AgentResult", "FinalResult", "agent_results", "pose_graph_figures", "run_metrics"]


@dataclass
class AgentResult:
    """One agent's final trajectory in its own frame and in its group's frame."""

    agent_id: str
    group_id: str
    merged: bool
    """False when the agent never joined another: its global frame is its own."""
    stamps: np.ndarray
    T_own_cam: np.ndarray
    T_group_cam: np.ndarray
    T_group_agent: np.ndarray


@dataclass
class FinalResult:
    """What `export_run` writes."""

    agents: list[AgentResult]
    maps: dict[str, NeuralPointMap]
    """Refined fused map of every group (group frame)."""
    decoders: dict[str, dict[str, np.ndarray]]
    """Final decoder weights of every group that has some."""
    main_group: str | None
    """The group written as fused_map.* (most members, then most points)."""
    pose_graph: PoseGraph | None
    metrics: dict[str, Any] = field(default_factory=dict)


def agent_results(groups: list[Group], registry: Registry,
                  kf_poses: Callable[[str], dict[int, np.ndarray]],
                  frame_fix: dict[str, dict[int, np.ndarray]]) -> list[AgentResult]:
    """Every member's trajectory (members without keyframes have none).

    Args:
        kf_poses: ``agent -> {kf_id: T_group_kf}``, the final keyframe poses.
        frame_fix: ``agent -> {frame index: T_group_cam}`` of the frames the final pose graph
            corrected.
    """
    out = []
    for group in groups:
        for m in group.members:
            rec = registry.agents[m]
            if not rec.keyframes:
                continue
            stamps, T_group = trajectory_poses(rec, kf_poses(m), frame_fix.get(m))
            T_ga = group.T_group_agent[m]
            out.append(AgentResult(m, group.group_id, len(group.members) > 1, stamps,
                                   compose(invert(T_ga), T_group), T_group, T_ga))
    return out


def pose_graph_figures(graph: PoseGraph, result: PoseGraphResult | None, loops: list[Any]
                       ) -> dict[str, Any]:
    """The final pose graph's size and, once optimised, errors, iterations and outliers."""
    pg: dict[str, Any] = {"nodes": graph.num_nodes, "edges": graph.num_edges,
                          "loops": len(loops)}
    if result is not None:
        pg.update(error_before=result.error_before, error_after=result.error_after,
                  iterations=result.iterations, outliers=len(result.outlier_loops))
    return pg


def run_metrics(groups: list[Group], registry: Registry, agents: list[AgentResult],
                loop_records: list[LoopRecord], loops_found: int, loops_skipped: int,
                merges: list[dict], rounds_closed: list[dict], pose_graph_runs: list[dict],
                pg: dict, refine: list[dict], timings: dict[str, float]) -> dict[str, Any]:
    """The metrics.json of a run (``pg``: the final pose graph's figures, ``refine``: each
    group's map refinement)."""
    loops = [asdict(lp) for lp in loop_records]
    for lp in loops:
        lp.pop("T_a_b")
    return {
        "groups": [{"group_id": g.group_id, "members": g.members, "epoch": g.epoch,
                    "rounds": g.round} for g in groups],
        "agents": {a.agent_id: {"group": a.group_id, "merged": a.merged, "frames": len(a.stamps),
                                "global_frame": "group" if a.merged else "own (never merged)",
                                # the agent's number in fused_map.pt's agent_id column
                                "index": registry.agents[a.agent_id].index,
                                "bytes": registry.agents[a.agent_id].bytes,
                                "messages": registry.agents[a.agent_id].messages,
                                "dropped": dict(registry.agents[a.agent_id].dropped)}
                   for a in agents},
        "loops": {"found": loops_found,
                  "skipped": loops_skipped,  # near a verified pair: loop.spacing
                  "accepted": sum(lp["accepted"] for lp in loops),
                  "rejected": sum(not lp["accepted"] for lp in loops),
                  "list": loops},
        "merges": merges,
        "rounds": {"closed": len(rounds_closed), "list": rounds_closed},
        "pose_graph": {"final": pg, "runs": len(pose_graph_runs),
                       "seconds_total": sum(r["seconds"] for r in pose_graph_runs)},
        "refinement": refine,
        "dropped": dict(registry.dropped),
        "timings": {**timings, "loop_verification_s": sum(lp["seconds"] for lp in loops)},
    }


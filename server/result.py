"""Finalisation: the last pose graph over everything, refined group maps, trajectories and
metrics, gathered in a `FinalResult` that `cpslam.server.export.export_run` writes out."""

from __future__ import annotations

import logging
import time
from dataclasses import asdict, dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from cpslam.common.field import NeuralPointMap
from cpslam.common.geometry import compose, invert
from cpslam.server.fusion import fuse
from cpslam.server.pose_graph import PoseGraph
from cpslam.server.tracks import trajectory_poses

if TYPE_CHECKING:
    from cpslam.server.backend import Backend

__all__ = ["AgentResult", "FinalResult", "finalise_backend"]

logger = logging.getLogger(__name__)


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


def finalise_backend(backend: Backend) -> FinalResult:
    """Run the final optimisation and refinement of a back end (see `Backend.finalise`)."""
    t0 = time.perf_counter()
    reg, groups = backend.registry, backend.groups
    graph, loops, trajectories = backend.pose_graph(list(groups.groups.values()))
    pg_metrics: dict[str, Any] = {"nodes": graph.num_nodes, "edges": graph.num_edges,
                                  "loops": len(loops)}
    frame_fix: dict[str, dict[int, np.ndarray]] = {}
    if graph.num_nodes:
        result = graph.optimize()
        backend.corrected.update(result.poses)
        for lp in loops:
            lp.outlier = lp.loop_id in result.outlier_loops
        for m, traj in trajectories.items():
            fixed = graph.corrected_frames(result, m)
            frame_fix[m] = dict(zip(traj.frame_indices.tolist(), fixed, strict=True))
        pg_metrics.update(error_before=result.error_before, error_after=result.error_after,
                          iterations=result.iterations, outliers=len(result.outlier_loops))
    t_graph = time.perf_counter() - t0

    agents = []
    for group in groups.groups.values():
        for m in group.members:
            rec = reg.agents[m]
            if not rec.keyframes:
                continue
            stamps, T_group = trajectory_poses(rec, backend.kf_poses(m), frame_fix.get(m))
            T_ga = group.T_group_agent[m]
            agents.append(AgentResult(m, group.group_id, len(group.members) > 1, stamps,
                                      compose(invert(T_ga), T_group), T_group, T_ga))

    t1 = time.perf_counter()
    maps, decoders, refine = {}, {}, []
    for group in groups.groups.values():
        fused = fuse(backend.member_maps(group), backend.feature_dim, backend.cell_size,
                     grid_filter=backend.refine_cfg.grid_filter)
        maps[group.group_id] = fused
        state = group.decoder
        if state is None and len(group.members) == 1:
            state = reg.agents[group.members[0]].decoder
        if state is not None:
            state = backend.federator.finetune(group, state, backend.refine_cfg.finetune_iters,
                                               backend.finetune_lr_features, point_map=fused)
            decoders[group.group_id] = state
        refine.append({"group": group.group_id, "points": len(fused)})
    t_refine = time.perf_counter() - t1
    main = max(maps, key=lambda g: (len(groups.groups[g].members), len(maps[g])), default=None)
    metrics = _metrics(backend, agents, pg_metrics, refine,
                       {"final_pose_graph_s": t_graph, "refinement_s": t_refine})
    metrics["main_group"] = main  # the group written as fused_map.* / decoders_<g>.pt
    return FinalResult(agents, maps, decoders, main, graph if graph.num_nodes else None, metrics)


def _metrics(backend: Backend, agents: list[AgentResult], pg: dict, refine: list[dict],
             timings: dict[str, float]) -> dict[str, Any]:
    loops = [asdict(lp) for lp in backend.loops]
    for lp in loops:
        lp.pop("T_a_b")
    reg = backend.registry
    pg_runs = backend.pose_graph_runs
    return {
        "groups": [{"group_id": g.group_id, "members": g.members, "epoch": g.epoch,
                    "rounds": g.round} for g in backend.groups.groups.values()],
        "agents": {a.agent_id: {"group": a.group_id, "merged": a.merged, "frames": len(a.stamps),
                                "global_frame": "group" if a.merged else "own (never merged)",
                                "bytes": reg.agents[a.agent_id].bytes,
                                "messages": reg.agents[a.agent_id].messages,
                                "dropped": dict(reg.agents[a.agent_id].dropped)}
                   for a in agents},
        "loops": {"found": backend.loops_found,
                  "accepted": sum(lp["accepted"] for lp in loops),
                  "rejected": sum(not lp["accepted"] for lp in loops),
                  "list": loops},
        "merges": backend.merges,
        "rounds": {"closed": len(backend.rounds_closed), "list": backend.rounds_closed},
        "pose_graph": {"final": pg, "runs": len(pg_runs),
                       "seconds_total": sum(r["seconds"] for r in pg_runs)},
        "refinement": refine,
        "dropped": dict(reg.dropped),
        "timings": {**timings, "loop_verification_s": sum(lp["seconds"] for lp in loops)},
    }

"""The end of a run: the back end's final pose graph over every group, the refined fused maps,
every agent's trajectories and the metrics, as a `FinalResult` (`Backend.finalise` calls it
once every loop candidate is verified). A part of the back end split out for size: it reads
the back end whole.
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

from cpslam.server.refinement import refine_maps
from cpslam.server.result import FinalResult, agent_results, pose_graph_figures, run_metrics
from cpslam.server.tracks import corrected_frame_poses

if TYPE_CHECKING:
    from cpslam.server.backend import Backend

__all__ = ["final_result"]


def final_result(be: Backend) -> FinalResult:
    """The final pose graph over everything, refined fused maps, trajectories and metrics."""
    t0 = time.perf_counter()
    groups = list(be.groups.groups.values())
    graph, result, loops, trajectories = be.optimise(groups)
    frame_fix = {} if result is None else corrected_frame_poses(graph, result, trajectories)
    pg = pose_graph_figures(graph, result, loops)
    t_graph = time.perf_counter() - t0
    agents = agent_results(groups, be.registry, be.kf_poses, frame_fix)
    t1 = time.perf_counter()
    maps, decoders, refined = refine_maps(
        groups, be.member_maps, lambda a: be.registry.agents[a].decoder, be.federator.finetune,
        be.spec.feature_dim, be.spec.grid_size, grid_filter=be.refine_cfg.grid_filter,
        finetune_iters=be.refine_cfg.finetune_iters, lr_features=be.finetune_lr_features)
    timings = {"final_pose_graph_s": t_graph, "refinement_s": time.perf_counter() - t1}
    main = max(maps, key=lambda g: (len(be.groups.groups[g].members), len(maps[g])),
               default=None)
    metrics = run_metrics(groups, be.registry, agents, be.loops, be.loops_found,
                          be.pipeline.skipped, be.merges, be.rounds_closed, be.pose_graph_runs,
                          pg, refined, timings)
    metrics["main_group"] = main  # the group written as fused_map.* / decoders_<g>.pt
    return FinalResult(agents, maps, decoders, main, graph if graph.num_nodes else None,
                       metrics)

"""Agent tracks for the pose graph and the exported trajectories.

The sequential edges of the pose graph are the agent's odometry (``T_prev_kf_kf`` chained, see
`AgentRecord.odometry`) and its frames' poses relative to their keyframes; the pose graph
re-anchors them in the group frame with the member's alignment; `add_group_tracks` puts a
set of groups' members and their loops into one graph, `optimise_groups` optimises it and
keeps the corrections.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING

import numpy as np

from cpslam.common.geometry import compose, invert
from cpslam.server.pose_graph import AgentTrajectory, PoseGraph, PoseGraphResult, loop_sigmas
from cpslam.server.records import AgentRecord
from cpslam.server.registry import Registry

if TYPE_CHECKING:
    from cpslam.common.config.collab import PoseGraphConfig
    from cpslam.server.groups import Group
    from cpslam.server.loops import LoopRecord

__all__ = ["add_group_tracks", "agent_trajectory", "corrected_frame_poses", "group_kf_poses",
           "optimise_groups", "trajectory_poses"]


def agent_trajectory(rec: AgentRecord) -> AgentTrajectory | None:
    """The record's keyframes (odometry poses, own world) and frames; None without keyframes."""
    kf_ids = rec.kf_ids
    if not kf_ids:
        return None
    odo = rec.odometry()
    frames = sorted(rec.frames)
    return AgentTrajectory(
        kf_ids=np.asarray(kf_ids, np.int64),
        kf_frame_indices=np.asarray([rec.keyframes[k].frame_index for k in kf_ids], np.int64),
        T_world_kf=np.stack([odo[k] for k in kf_ids]),
        frame_indices=np.asarray(frames, np.int64),
        frame_kf_ids=np.asarray([rec.frames[f][0] for f in frames], np.int64),
        T_kf_frame=np.stack([rec.frames[f][1] for f in frames]) if frames
        else np.zeros((0, 4, 4)),
    )


def group_kf_poses(rec: AgentRecord, T_group_agent: np.ndarray,
                   corrected: Mapping[int, np.ndarray]) -> dict[int, np.ndarray]:
    """Best current ``T_group_kf`` of every keyframe of an agent.

    Corrected poses (pose graph) where there are; a later keyframe follows the last earlier
    one by odometry; keyframes before any correction use the alignment and the reported pose.
    """
    odo = rec.odometry()
    out: dict[int, np.ndarray] = {}
    prev: int | None = None
    for kf in rec.kf_ids:
        if kf in corrected:
            out[kf] = np.asarray(corrected[kf], np.float64)
        elif prev is not None:
            out[kf] = compose(out[prev], invert(odo[prev]), odo[kf])
        else:
            out[kf] = compose(T_group_agent, rec.keyframes[kf].T_own_kf)
        prev = kf
    return out


def trajectory_poses(rec: AgentRecord, kf_poses: Mapping[int, np.ndarray],
                     frame_poses: Mapping[int, np.ndarray] | None = None
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Stamps [N] and camera poses [N, 4, 4] of every known frame (keyframes included) in
    stream order: a frame is ``kf_poses[its kf] @ T_kf_frame`` unless `frame_poses` (by
    frame index) has it."""
    entries: dict[int, tuple[float, np.ndarray]] = {}
    for kf, k in rec.keyframes.items():
        entries[k.frame_index] = (k.stamp, kf_poses[kf])
    for frame, (kf, T_kf_frame, stamp) in rec.frames.items():
        if frame in entries:
            continue
        if frame_poses is not None and frame in frame_poses:
            entries[frame] = (stamp, frame_poses[frame])
        else:
            entries[frame] = (stamp, compose(kf_poses[kf], T_kf_frame))
    order = sorted(entries)
    if not order:
        return np.zeros(0), np.zeros((0, 4, 4))
    return (np.asarray([entries[f][0] for f in order], np.float64),
            np.stack([entries[f][1] for f in order]))


def add_group_tracks(graph: PoseGraph, registry: Registry, groups: list[Group],
                     loops: list[LoopRecord], loop_sigma_t: float, loop_sigma_r: float
                     ) -> tuple[list[LoopRecord], dict[str, AgentTrajectory]]:
    """Add every member's odometry (in its group frame) and the accepted `loops` between
    members of one group to `graph`. Returns those loops and the members' trajectories.

    A loop weighs by its registration's information when it has one, else by sigmas from
    its overlap and residual (`loop_sigmas`).
    """
    trajectories, group_of = {}, {}
    for group in groups:
        for m in group.members:
            group_of[m] = group.group_id
            traj = agent_trajectory(registry.agents[m])
            if traj is not None:
                graph.add_trajectory(m, traj, group.T_group_agent[m])
                trajectories[m] = traj
    used = [lp for lp in loops if lp.accepted and lp.agent_a in trajectories
            and lp.agent_b in trajectories and group_of[lp.agent_a] == group_of[lp.agent_b]]
    for lp in used:
        if lp.information is not None:
            graph.add_loop(lp.agent_a, lp.kf_a, lp.agent_b, lp.kf_b, np.asarray(lp.T_a_b),
                           information=np.asarray(lp.information), loop_id=lp.loop_id)
            continue
        sig_t, sig_r = loop_sigmas(loop_sigma_t, loop_sigma_r, max(lp.rmse, 0.0),
                                   min(max(lp.fitness, 1e-3), 1.0))
        graph.add_loop(lp.agent_a, lp.kf_a, lp.agent_b, lp.kf_b, np.asarray(lp.T_a_b),
                       sigma_t=sig_t, sigma_r=sig_r, loop_id=lp.loop_id)
    return used, trajectories


def optimise_groups(cfg: PoseGraphConfig, registry: Registry, groups: list[Group],
                    loops: list[LoopRecord], corrected: dict[tuple[str, int], np.ndarray]
                    ) -> tuple[PoseGraph, PoseGraphResult | None, list[LoopRecord],
                               dict[str, AgentTrajectory]]:
    """One pose graph over these groups (`add_group_tracks`), optimised. Each keyframe's
    corrected pose goes into `corrected` by ``(agent, kf)`` and each of the graph's loops is
    marked an outlier or not. Returns the graph, its result (None for an empty graph), its
    loops and the members' trajectories."""
    graph = PoseGraph.from_config(cfg)
    used, trajectories = add_group_tracks(graph, registry, groups, loops, cfg.loop_sigma_t,
                                          cfg.loop_sigma_r)
    if graph.num_nodes == 0:
        return graph, None, used, trajectories
    result = graph.optimize()
    for (agent, kf), T in result.poses.items():
        corrected[(agent, kf)] = T
    for lp in used:
        lp.outlier = lp.loop_id in result.outlier_loops
    return graph, result, used, trajectories


def corrected_frame_poses(graph: PoseGraph, result: PoseGraphResult,
                          trajectories: Mapping[str, AgentTrajectory]
                          ) -> dict[str, dict[int, np.ndarray]]:
    """``agent -> {frame index: T_group_frame}`` of every frame an optimised graph holds."""
    return {m: dict(zip(traj.frame_indices.tolist(), graph.corrected_frames(result, m),
                        strict=True))
            for m, traj in trajectories.items()}

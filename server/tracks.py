"""Agent tracks for the pose graph and the exported trajectories.

The sequential edges of the pose graph are the agent's odometry (``T_prev_kf_kf`` chained, see
`AgentRecord.odometry`) and its frames' poses relative to their keyframes; the pose graph
re-anchors them in the group frame with the member's alignment.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from cpslam.common.geometry import compose, invert
from cpslam.server.pose_graph import AgentTrajectory
from cpslam.server.registry import AgentRecord

__all__ = ["agent_trajectory", "group_kf_poses", "trajectory_poses"]


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

"""Pose corrections a server update applies to an agent's odometry (`AgentLink.apply_update`).

Every product is projected back onto SO(3) (`rigid`): repeated corrections must not let
rounding drift build up in poses that are sent on (receivers check rigidity).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from cpslam.common.geometry import compose, invert

if TYPE_CHECKING:
    from cpslam.agent.odometry import Odometry

__all__ = ["correct_keyframes", "move_world", "rigid"]


def move_world(odometry: Odometry, T_new_old: np.ndarray) -> None:
    """Every pose the agent holds, left-multiplied by T_new_old: the keyframe poses of the
    map's pose table (own and foreign, so every point moves with its keyframe), the keyframe
    store and the trajectory."""
    pm = odometry.point_map
    keys = pm.kf_keys.cpu().numpy()
    poses = pm.kf_poses.cpu().numpy()
    for agent in np.unique(keys[:, 0]) if len(keys) else []:
        sel = keys[:, 0] == agent
        moved = np.stack([rigid(T_new_old @ T) for T in poses[sel]])
        pm.set_keyframe_poses(keys[sel, 1], moved, int(agent))
    for kf in odometry.keyframes:
        odometry.keyframes.set_pose(kf.kf_id, rigid(T_new_old @ kf.T_world_cam))
    odometry.set_frame_poses([rigid(T_new_old @ T) for T in odometry.trajectory()[1]])


def correct_keyframes(odometry: Odometry, own: int, frame_kf: list[int],
                      corrected: dict[int, np.ndarray]) -> None:
    """Own keyframes (map agent key `own`) take the corrected poses; a keyframe the server has
    not seen yet follows the correction of the one before it, and every frame that of its
    keyframe (`frame_kf`: the keyframe of each trajectory entry)."""
    delta: dict[int, np.ndarray] = {}
    last = np.eye(4)
    store = odometry.keyframes
    for kf in store:
        if kf.kf_id in corrected:
            last = compose(corrected[kf.kf_id], invert(kf.T_world_cam))
        delta[kf.kf_id] = last
    if not delta:
        return
    ids = list(delta)
    for kf_id in ids:
        store.set_pose(kf_id, rigid(delta[kf_id] @ store.get(kf_id).T_world_cam))
    odometry.point_map.set_keyframe_poses(
        ids, np.stack([store.get(k).T_world_cam for k in ids]), own)
    poses = odometry.trajectory()[1]
    odometry.set_frame_poses([rigid(delta[k] @ T)
                              for k, T in zip(frame_kf, poses, strict=True)])


def rigid(T: np.ndarray) -> np.ndarray:
    """T with its rotation projected back onto SO(3) and its last row reset."""
    T = np.array(T, np.float64)
    u, _, vt = np.linalg.svd(T[:3, :3])
    T[:3, :3] = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    T[3] = (0.0, 0.0, 0.0, 1.0)
    return T

"""An agent's track as the pose graph takes it (`AgentTrajectory`: keyframe poses and frames
relative to their keyframes), and the frames that follow corrected keyframes
(`correct_frames`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cpslam.common.geometry import compose

__all__ = ["AgentTrajectory", "correct_frames"]


@dataclass(frozen=True)
class AgentTrajectory:
    """What the server knows of one agent's track, in the group frame.

    ``T_world_kf`` and ``T_kf_frame`` come from tracking: the relative poses between
    consecutive keyframes/frames are the odometry the sequential edges encode.
    """

    kf_ids: np.ndarray
    """Keyframe ids (int [K], increasing)."""
    kf_frame_indices: np.ndarray
    """Stream index of each keyframe's frame (int [K], increasing)."""
    T_world_kf: np.ndarray
    """Keyframe poses (float64 [K, 4, 4])."""
    frame_indices: np.ndarray
    """Stream indices of the ordinary frames (int [N]); may include keyframe frames."""
    frame_kf_ids: np.ndarray
    """Keyframe each frame is expressed against (int [N])."""
    T_kf_frame: np.ndarray
    """Frame poses in their keyframe's camera frame (float64 [N, 4, 4])."""

    def __post_init__(self) -> None:
        k, n = len(self.kf_ids), len(self.frame_indices)
        check_shape(self.kf_frame_indices, (k,), "kf_frame_indices")
        check_shape(self.T_world_kf, (k, 4, 4), "T_world_kf")
        check_shape(self.frame_kf_ids, (n,), "frame_kf_ids")
        check_shape(self.T_kf_frame, (n, 4, 4), "T_kf_frame")
        if k == 0:
            raise ValueError("AgentTrajectory: needs at least one keyframe")
        if np.any(np.diff(self.kf_ids) <= 0) or np.any(np.diff(self.kf_frame_indices) <= 0):
            raise ValueError("AgentTrajectory: kf_ids and kf_frame_indices must increase")
        unknown = set(np.asarray(self.frame_kf_ids).tolist()) - set(self.kf_ids.tolist())
        if unknown:
            raise ValueError(f"AgentTrajectory.frame_kf_ids: unknown keyframes {sorted(unknown)}")


def correct_frames(
    kf_poses_new: dict[int, np.ndarray], frame_kf_ids: np.ndarray, T_kf_frame: np.ndarray
) -> np.ndarray:
    """Corrected frame poses ``T_world_frame [N, 4, 4] = T_world_kf_new @ T_kf_frame``.

    ``kf_poses_new`` maps keyframe id to its corrected ``T_world_kf``; every id in
    ``frame_kf_ids [N]`` must be present.
    """
    frame_kf_ids = np.asarray(frame_kf_ids)
    check_shape(T_kf_frame, (len(frame_kf_ids), 4, 4), "T_kf_frame")
    missing = sorted(set(frame_kf_ids.tolist()) - set(kf_poses_new))
    if missing:
        raise ValueError(f"correct_frames: no corrected pose for keyframes {missing}")
    if len(frame_kf_ids) == 0:
        return np.zeros((0, 4, 4))
    T_world_kf = np.stack([kf_poses_new[int(k)] for k in frame_kf_ids])
    return compose(T_world_kf, np.asarray(T_kf_frame, dtype=np.float64))


def frame_chain(
    traj: AgentTrajectory, kf_pose: dict[int, np.ndarray]
) -> list[tuple[tuple[str, int], int, np.ndarray]]:
    """Keyframes and frames in stream order: ``((kind, id), frame_index, T_world)``."""
    chain = {
        int(f): (("kf", int(k)), int(f), kf_pose[int(k)])
        for k, f in zip(traj.kf_ids, traj.kf_frame_indices, strict=True)
    }
    frames = zip(traj.frame_indices, traj.frame_kf_ids, traj.T_kf_frame, strict=True)
    for frame, kf, T_kf_frame in frames:
        if int(frame) not in chain:  # a keyframe's own frame is the keyframe node
            chain[int(frame)] = (
                ("frame", int(frame)),
                int(frame),
                compose(kf_pose[int(kf)], T_kf_frame),
            )
    return [chain[f] for f in sorted(chain)]


def check_shape(a: np.ndarray, shape: tuple[int, ...], name: str) -> None:
    if np.shape(a) != shape:
        raise ValueError(f"{name}: expected shape {shape}, got {np.shape(a)}")

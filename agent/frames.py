"""What the odometry takes, keeps and reports per frame: `checked_rgbd` (a frame's images as
tracking and mapping take them), `FrameResult` (one frame's outcome) and `FrameLog` (every
frame's stamp, index, pose and whether it tracked, in order)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch

if TYPE_CHECKING:
    from cpslam.common.camera import Intrinsics
    from cpslam.common.datasets import RGBDFrame

__all__ = ["FrameLog", "FrameResult", "checked_rgbd"]


def checked_rgbd(frame: RGBDFrame, intrinsics: Intrinsics, depth_min: float,
                 depth_max: float) -> tuple[np.ndarray, np.ndarray]:
    """rgb uint8 and depth float32 clipped to [depth_min, depth_max] (0 outside), after
    checking the frame has the size of `intrinsics` (`Odometry.step` never resizes)."""
    shape = intrinsics.shape
    if frame.depth.shape != shape or frame.rgb.shape != (*shape, 3):
        raise ValueError(
            f"Odometry.step: frame {frame.index} has rgb {frame.rgb.shape} / depth "
            f"{frame.depth.shape}, expected {shape} (resize frames by camera.downscale "
            f"before step)")
    if frame.rgb.dtype != np.uint8:
        raise ValueError(f"Odometry.step: frame {frame.index} rgb must be uint8, "
                         f"got {frame.rgb.dtype}")
    depth = np.asarray(frame.depth, dtype=np.float32)
    ok = np.isfinite(depth) & (depth >= depth_min) & (depth <= depth_max)
    return np.ascontiguousarray(frame.rgb), np.where(ok, depth, 0.0).astype(np.float32)


@dataclass
class FrameResult:
    """What happened to one frame. Times in seconds; map_steps is 0 when it did not map.

    map_time_s is the whole mapping call (adding points, co-visibility, optimisation);
    map_optimise_time_s only its `map_steps` optimisation steps, so a per-step time is
    map_optimise_time_s / map_steps; with the concurrent schedule they sum the calls that
    finished while this frame was processed (on the mapping thread). track_event is ""
    (tracked and healthy, or recovery off), "recovered" or "lost" (see
    `cpslam.agent.recovery`); track_time_s includes the recovery.
    """

    index: int
    timestamp: float
    T_world_cam: np.ndarray  # [4, 4] float64
    track_time_s: float
    track_iters: int
    track_loss: float
    map_time_s: float
    map_steps: int
    map_optimise_time_s: float
    n_points: int
    is_keyframe: bool
    kf_id: int | None
    track_event: str = ""
    track_inlier_ratio: float = float("nan")
    track_residual_m: float = float("nan")


class FrameLog:
    """Every processed frame in order: timestamp, dataset index, T_world_cam and whether its
    tracking held (False: lost, neither mapped nor keyframed)."""

    def __init__(self) -> None:
        self.stamps: list[float] = []
        self.indices: list[int] = []
        self.poses: list[np.ndarray] = []  # T_world_cam [4, 4] float64 each
        self.tracked: list[bool] = []

    def __len__(self) -> int:
        return len(self.poses)

    def append(self, timestamp: float, index: int, T_world_cam: np.ndarray,
               tracked: bool) -> None:
        self.stamps.append(float(timestamp))
        self.indices.append(int(index))
        self.poses.append(np.asarray(T_world_cam, dtype=np.float64))
        self.tracked.append(bool(tracked))

    def trajectory(self) -> tuple[np.ndarray, np.ndarray]:
        """Stamps [N] float64 and T_world_cam [N, 4, 4]."""
        poses = np.stack(self.poses) if self.poses else np.zeros((0, 4, 4))
        return np.asarray(self.stamps, dtype=np.float64), poses

    def set_poses(self, T_world_cam: np.ndarray | list[np.ndarray]) -> None:
        """Replace every pose (a correction from the server); the count must match."""
        poses = [np.array(T, dtype=np.float64) for T in T_world_cam]
        if len(poses) != len(self.poses) or any(T.shape != (4, 4) for T in poses):
            raise ValueError(f"set_frame_poses: expected {len(self.poses)} poses [4, 4], got "
                             f"{[T.shape for T in poses]}")
        self.poses = poses

    def state_dict(self) -> dict:
        """Plain tensors (torch.load(weights_only=True) reads them)."""
        _, poses = self.trajectory()
        return {"stamps": torch.tensor(self.stamps, dtype=torch.float64),
                "frame_indices": torch.tensor(self.indices, dtype=torch.int64),
                "poses": torch.from_numpy(poses.copy()),
                "tracked": torch.tensor(self.tracked, dtype=torch.bool)}

    def load_state_dict(self, state: dict, n_frames: int) -> None:
        """Restore `state_dict`'s entries, checking they all hold `n_frames` frames."""
        self.stamps = [float(s) for s in state["stamps"].tolist()]
        self.indices = [int(i) for i in state["frame_indices"].tolist()]
        self.poses = [p.cpu().numpy().astype(np.float64) for p in state["poses"]]
        tracked = state.get("tracked")  # absent in states written before the recovery
        self.tracked = [True] * len(self.poses) if tracked is None else \
            [bool(b) for b in tracked.tolist()]
        if len(self.tracked) != len(self.poses):
            raise ValueError("odometry state: tracked and poses differ in length")
        if not len(self.stamps) == len(self.indices) == len(self.poses) == n_frames:
            raise ValueError("odometry state: stamps, frame_indices and poses differ in length")

"""ATE over the pieces of a ground truth that jumps: find single-frame jumps in a reference
trajectory and score an estimate on the pieces between them, each aligned on its own.

Ground truth from another SLAM system can hold a jump that the camera never made: the
7-Scenes kitchen's KinectFusion poses step 36 mm / 1.4 deg from frame 121 to 122, between
steps of 5-7 mm, while Open3D and cpslam both measure 4-8 mm there and agree with each other
to 4.5 mm. Over the whole sequence that one step enters every later frame's error, so the
ATE of two good estimators then mostly says how each one's drift happens to line up with
the jump. Scoring the pieces separately (pooled RMSE over every frame of every piece) leaves
the jump out and keeps everything else. Only the reference is read, so every estimator is
cut in the same places.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cpslam.tools.eval.ate import DEFAULT_MAX_DT, AteResult, evaluate_ate, rotation_angle_deg

__all__ = ["SegmentedAte", "reference_jumps", "segmented_ate"]


def reference_jumps(
    T_world_cam: np.ndarray, factor: float = 3.0, min_trans_m: float = 0.02,
    min_rot_deg: float = 1.0,
) -> np.ndarray:
    """Indices i [J] (int64) where the step from pose i to i + 1 is a jump.

    A step is a jump when its translation exceeds both min_trans_m and factor times the
    median step and factor times each neighbouring step (or the same holds for its rotation
    with min_rot_deg): a spike of one frame, not fast motion, which builds up over several.
    T_world_cam: [N, 4, 4] consecutive poses of the reference.
    """
    poses = np.asarray(T_world_cam, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise ValueError(f"reference_jumps: poses must be [N, 4, 4], got {poses.shape}")
    if len(poses) < 4:
        return np.zeros(0, dtype=np.int64)
    rel = np.linalg.inv(poses[:-1]) @ poses[1:]
    trans = np.linalg.norm(rel[:, :3, 3], axis=1)
    rot = rotation_angle_deg(poses[:-1, :3, :3], poses[1:, :3, :3])
    jump = _spikes(trans, factor, min_trans_m) | _spikes(rot, factor, min_rot_deg)
    return np.flatnonzero(jump).astype(np.int64)


@dataclass
class SegmentedAte:
    """ATE per piece and pooled: rmse over every paired frame of every scored piece (metres).

    pieces: (first, last) frame index of each scored piece; results: their AteResults.
    """

    jumps: np.ndarray
    pieces: list[tuple[int, int]]
    results: list[AteResult]

    @property
    def rmse(self) -> float:
        err = np.concatenate([r.trans_err for r in self.results])
        return float(np.sqrt(np.mean(err**2)))

    def to_dict(self) -> dict:
        """Plain numbers for JSON: pooled RMSE (m), jumps, pieces and each piece's RMSE."""
        return {"rmse": self.rmse, "jumps_after_frame": [int(j) for j in self.jumps],
                "pieces": [list(p) for p in self.pieces],
                "piece_rmse": [r.rmse for r in self.results]}


def segmented_ate(
    gt_stamps: np.ndarray, gt_poses: np.ndarray, est_stamps: np.ndarray,
    est_poses: np.ndarray, jumps: np.ndarray, align: str = "se3", min_frames: int = 10,
    max_dt: float = DEFAULT_MAX_DT,
) -> SegmentedAte:
    """ATE of the estimate on the pieces of the reference between `jumps` (from
    `reference_jumps`), each piece associated and aligned on its own; pieces with fewer than
    `min_frames` reference poses are left out."""
    gt_stamps = np.asarray(gt_stamps, dtype=np.float64)
    est_stamps = np.asarray(est_stamps, dtype=np.float64)
    bounds = [0, *(int(j) + 1 for j in np.sort(jumps)), len(gt_stamps)]
    pieces, results = [], []
    for first, stop in zip(bounds[:-1], bounds[1:], strict=True):
        if stop - first < min_frames:
            continue
        lo, hi = gt_stamps[first], gt_stamps[stop - 1]
        inside = (est_stamps >= lo - max_dt) & (est_stamps <= hi + max_dt)
        results.append(evaluate_ate(gt_stamps[first:stop], gt_poses[first:stop],
                                    est_stamps[inside], est_poses[inside], align=align,
                                    max_dt=max_dt))
        pieces.append((first, stop - 1))
    if not results:
        raise ValueError(f"segmented_ate: no piece of at least {min_frames} frames between "
                         f"the jumps {list(map(int, jumps))}")
    return SegmentedAte(np.asarray(jumps, dtype=np.int64), pieces, results)


def _spikes(step: np.ndarray, factor: float, minimum: float) -> np.ndarray:
    """bool [N]: steps above `minimum`, factor x their median and factor x each neighbour."""
    before = np.r_[0.0, step[:-1]]
    after = np.r_[step[1:], 0.0]
    return (step > minimum) & (step > factor * np.median(step)) & \
        (step > factor * before) & (step > factor * after)

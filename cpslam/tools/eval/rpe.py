"""Relative pose error (RPE): how well an estimate reproduces the ground truth's motion over a
fixed number of frames, independent of drift accumulated before.

For every associated pair i and i + delta (in associated order),
``E = (G_i^-1 G_{i+delta})^-1 (P_i^-1 P_{i+delta})`` and the error is E's translation (m) and
rotation angle (degrees). No alignment is needed: relative motions do not depend on the world
frame. Frame-to-frame RPE (delta 1) measures a tracker's jitter; longer deltas measure local
drift. ATE, by contrast, mixes both with one alignment over the whole run.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cpslam.tools.eval.ate import (
    DEFAULT_MAX_DT,
    _check_trajectory,
    associate,
    rotation_angle_deg,
)

__all__ = ["RpeResult", "evaluate_rpe"]


@dataclass(frozen=True)
class RpeResult:
    """RPE over `pairs` pose pairs `delta` frames apart; translation in metres, rotation in
    degrees; `trans` and `rot` hold every pair's errors."""

    delta: int
    pairs: int
    trans_mean: float
    trans_rmse: float
    rot_mean_deg: float
    rot_rmse_deg: float
    trans: np.ndarray
    rot: np.ndarray

    def to_dict(self) -> dict:
        """Plain numbers (no per-pair series)."""
        return {"delta": self.delta, "pairs": self.pairs, "trans_mean_m": self.trans_mean,
                "trans_rmse_m": self.trans_rmse, "rot_mean_deg": self.rot_mean_deg,
                "rot_rmse_deg": self.rot_rmse_deg}


def evaluate_rpe(
    gt_stamps: np.ndarray,
    gt_poses: np.ndarray,
    est_stamps: np.ndarray,
    est_poses: np.ndarray,
    delta: int = 1,
    max_dt: float = DEFAULT_MAX_DT,
) -> RpeResult:
    """RPE of ``est_poses`` against ``gt_poses`` (both ``T_world_cam [N, 4, 4]``) over
    ``delta`` associated frames. Inputs are checked as for ATE (shapes, finite values); raises
    ValueError when fewer than delta + 1 poses associate."""
    if delta < 1:
        raise ValueError(f"evaluate_rpe: delta must be >= 1, got {delta}")
    gt_stamps, gt_poses = _check_trajectory((gt_stamps, gt_poses), "ground truth")
    est_stamps, est_poses = _check_trajectory((est_stamps, est_poses), "estimate")
    est_idx, gt_idx = associate(est_stamps, gt_stamps, max_dt)
    if len(est_idx) <= delta:
        raise ValueError(f"evaluate_rpe: {len(est_idx)} poses associate within {max_dt} s, "
                         f"need more than delta = {delta}")
    P, G = est_poses[est_idx], gt_poses[gt_idx]
    P_rel = np.linalg.inv(P[:-delta]) @ P[delta:]
    G_rel = np.linalg.inv(G[:-delta]) @ G[delta:]
    E = np.linalg.inv(G_rel) @ P_rel
    trans = np.linalg.norm(E[:, :3, 3], axis=1)
    rot = rotation_angle_deg(G_rel[:, :3, :3], P_rel[:, :3, :3])
    return RpeResult(
        delta=delta, pairs=len(trans), trans_mean=float(trans.mean()),
        trans_rmse=float(np.sqrt(np.mean(trans**2))), rot_mean_deg=float(rot.mean()),
        rot_rmse_deg=float(np.sqrt(np.mean(rot**2))), trans=trans, rot=rot,
    )

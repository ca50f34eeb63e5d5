"""Absolute trajectory error (ATE): association by timestamp, alignment, statistics.

``evaluate_ate`` scores one estimated trajectory against its ground truth;
``joint_ate`` scores several (one per agent) under a single shared alignment, which is what a
collaborative system has to get right: the agents' trajectories must agree with each other,
not only each with its own ground truth.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from cpslam.common.geometry import so3_log
from cpslam.common.trajectory import Trajectory
from cpslam.tools.eval.align import ALIGN_MODES, MIN_PAIRS, apply_alignment, similarity_matrix
from cpslam.tools.eval.align import align as fit_alignment

logger = logging.getLogger(__name__)

DEFAULT_MAX_DT = 0.02
"""Seconds. Tolerates clocks that differ by up to 20 ms (evo's default is 0.01 s). Below half
the frame spacing (0.0167 s at 30 Hz) every pair is unambiguous; above it the one-to-one rule
still keeps the closest pairs."""

TrajectoryLike = Trajectory | tuple[np.ndarray, np.ndarray]
"""A ``cpslam.common.trajectory.Trajectory`` or ``(stamps [N] s, T_world_cam [N, 4, 4])``."""


def evaluate_ate(
    gt_stamps: np.ndarray,
    gt_poses: np.ndarray,
    est_stamps: np.ndarray,
    est_poses: np.ndarray,
    align: str = "origin",
    max_dt: float = DEFAULT_MAX_DT,
    gt_name: str = "ground truth",
    est_name: str = "estimate",
) -> AteResult:
    """ATE of ``est_poses`` against ``gt_poses`` (both ``T_world_cam [N, 4, 4]``).

    Poses are associated by nearest timestamp within ``max_dt`` seconds (one-to-one), the
    estimate is aligned with ``align`` (see ``cpslam.tools.eval.align``), and the position
    errors of the pairs are summarised. ``gt_name``/``est_name`` (for example file paths)
    appear in error messages.
    """
    return joint_ate(
        [((gt_stamps, gt_poses), (est_stamps, est_poses))],
        align=align,
        max_dt=max_dt,
        names=[(gt_name, est_name)],
    ).overall


def joint_ate(
    pairs: Sequence[tuple[TrajectoryLike, TrajectoryLike]],
    align: str = "se3",
    max_dt: float = DEFAULT_MAX_DT,
    names: Sequence[tuple[str, str]] | None = None,
) -> JointAteResult:
    """ATE of several ``(gt, est)`` trajectory pairs under ONE alignment fitted to all of them.

    Each element of ``pairs`` is ``(gt, est)``, each a ``Trajectory`` or a
    ``(stamps, T_world_cam)`` tuple, for example one pair per agent. Each pair is associated
    on its own, then a single ``(R, t, s)`` is fitted on all associated poses together;
    ``origin`` uses the first associated pose of the first pair. ``names`` gives
    ``(gt_name, est_name)`` per pair for error messages.
    """
    if align not in ALIGN_MODES:
        raise ValueError(f"unknown alignment {align!r}; expected one of {ALIGN_MODES}")
    if max_dt < 0:
        raise ValueError(f"max_dt must be >= 0 seconds, got {max_dt}")
    if not pairs:
        raise ValueError("joint_ate needs at least one (gt, est) pair")
    if names is None:
        names = [(f"ground truth #{i}", f"estimate #{i}") for i in range(len(pairs))]
    if len(names) != len(pairs):
        raise ValueError(f"got {len(names)} names for {len(pairs)} trajectory pairs")

    need = MIN_PAIRS[align]
    matched = []  # per pair: (stamps [M], gt poses [M], est poses [M], n_gt, n_est)
    for (gt, est), (gt_name, est_name) in zip(pairs, names, strict=True):
        gt_stamps, gt_poses = _check_trajectory(gt, gt_name)
        est_stamps, est_poses = _check_trajectory(est, est_name)
        est_idx, gt_idx = associate(est_stamps, gt_stamps, max_dt)
        n_est, n_gt, n = len(est_stamps), len(gt_stamps), len(est_idx)
        if n < need:
            raise ValueError(
                f"only {n} poses of {est_name} ({n_est} poses) matched {gt_name} ({n_gt} poses) "
                f"within max_dt={max_dt} s; {align} evaluation needs at least {need}. "
                "Check that both use the same clock."
            )
        logger.info("%s: %d of %d poses matched %s", est_name, n, n_est, gt_name)
        matched.append((est_stamps[est_idx], gt_poses[gt_idx], est_poses[est_idx], n_gt, n_est))

    stamps, gt_poses, est_poses, n_gt, n_est = zip(*matched, strict=True)
    all_gt, all_est = np.concatenate(gt_poses), np.concatenate(est_poses)
    R, t, s = fit_alignment(all_est, all_gt, align)
    parts = [_score(*m, R, t, s, align, max_dt) for m in matched]
    overall = _score(
        np.concatenate(stamps), all_gt, all_est, sum(n_gt), sum(n_est), R, t, s, align, max_dt
    )
    return JointAteResult(overall=overall, parts=parts)


@dataclass
class AteResult:
    """Errors of associated, aligned pose pairs. Lengths in metres, angles in degrees."""

    align: str
    max_dt: float
    n_gt: int
    n_est: int
    scale: float
    T_gt_est: np.ndarray  # [4, 4] the alignment, s·R in the rotation block for sim3
    stamps: np.ndarray  # [M] stamps of the estimated poses of the pairs
    gt_xyz: np.ndarray  # [M, 3]
    est_xyz: np.ndarray  # [M, 3] aligned
    trans_err: np.ndarray  # [M] metres
    rot_err_deg: np.ndarray  # [M]

    @property
    def n_pairs(self) -> int:
        return len(self.trans_err)

    @property
    def rmse(self) -> float:
        return float(np.sqrt(np.mean(self.trans_err**2)))

    @property
    def mean(self) -> float:
        return float(np.mean(self.trans_err))

    @property
    def median(self) -> float:
        return float(np.median(self.trans_err))

    @property
    def std(self) -> float:
        return float(np.std(self.trans_err))

    @property
    def min(self) -> float:
        return float(np.min(self.trans_err))

    @property
    def max(self) -> float:
        return float(np.max(self.trans_err))

    @property
    def rot_rmse_deg(self) -> float:
        return float(np.sqrt(np.mean(self.rot_err_deg**2)))

    def to_dict(self, series: bool = False) -> dict:
        """JSON-ready numbers; ``series=True`` adds the per-pair stamps and errors."""
        rot = self.rot_err_deg
        out = {
            "align": self.align,
            "max_dt_s": self.max_dt,
            "n_pairs": self.n_pairs,
            "n_est": self.n_est,
            "n_gt": self.n_gt,
            "scale": self.scale,
            "rmse_m": self.rmse,
            "mean_m": self.mean,
            "median_m": self.median,
            "std_m": self.std,
            "min_m": self.min,
            "max_m": self.max,
            "rot_rmse_deg": self.rot_rmse_deg,
            "rot_mean_deg": float(np.mean(rot)),
            "rot_median_deg": float(np.median(rot)),
            "rot_max_deg": float(np.max(rot)),
            "T_gt_est": self.T_gt_est.tolist(),
        }
        if series:
            out["stamps"] = self.stamps.tolist()
            out["trans_err_m"] = self.trans_err.tolist()
            out["rot_err_deg"] = rot.tolist()
        return out


@dataclass
class JointAteResult:
    """``overall``: all pairs pooled; ``parts``: one result per input pair, same alignment."""

    overall: AteResult
    parts: list[AteResult] = field(default_factory=list)

    def to_dict(self, series: bool = False) -> dict:
        return {
            "overall": self.overall.to_dict(series),
            "parts": [p.to_dict(series) for p in self.parts],
        }


def associate(
    est_stamps: np.ndarray, gt_stamps: np.ndarray, max_dt: float = DEFAULT_MAX_DT
) -> tuple[np.ndarray, np.ndarray]:
    """One-to-one pairs ``(est_idx [M], gt_idx [M])`` with ``|Δt| <= max_dt``, by est stamp.

    Candidate pairs are accepted closest-first, so each pose is used at most once and a
    pose loses its partner only to a strictly closer (or, on ties, earlier) one.
    """
    est_stamps = np.asarray(est_stamps, dtype=np.float64)
    gt_stamps = np.asarray(gt_stamps, dtype=np.float64)
    gt_order = np.argsort(gt_stamps, kind="stable")
    gt_sorted = gt_stamps[gt_order]
    lo = np.searchsorted(gt_sorted, est_stamps - max_dt, side="left")
    hi = np.searchsorted(gt_sorted, est_stamps + max_dt, side="right")
    counts = np.maximum(hi - lo, 0)
    cand_est = np.repeat(np.arange(len(est_stamps)), counts)
    starts = np.repeat(lo - np.cumsum(counts) + counts, counts)
    cand_gt = gt_order[starts + np.arange(len(cand_est))]
    dt = np.abs(est_stamps[cand_est] - gt_stamps[cand_gt])
    keep = dt <= max_dt  # searchsorted bounds can be off by rounding of stamp ± max_dt
    cand_est, cand_gt, dt = cand_est[keep], cand_gt[keep], dt[keep]

    used_est = np.zeros(len(est_stamps), dtype=bool)
    used_gt = np.zeros(len(gt_stamps), dtype=bool)
    pairs = []
    for k in np.lexsort((cand_gt, cand_est, dt)):
        i, j = cand_est[k], cand_gt[k]
        if not used_est[i] and not used_gt[j]:
            used_est[i] = used_gt[j] = True
            pairs.append((i, j))
    if not pairs:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    est_idx, gt_idx = np.array(pairs, dtype=np.int64).T
    order = np.argsort(est_stamps[est_idx], kind="stable")
    return est_idx[order], gt_idx[order]


def rotation_angle_deg(R_a: np.ndarray, R_b: np.ndarray) -> np.ndarray:
    """Angle in degrees of ``R_a[i]ᵀ R_b[i]`` for ``[N, 3, 3]`` stacks."""
    R_rel = np.swapaxes(R_a, -1, -2) @ R_b
    return np.degrees(np.linalg.norm(so3_log(R_rel), axis=-1))


def _score(
    stamps: np.ndarray,
    gt_poses: np.ndarray,
    est_poses: np.ndarray,
    n_gt: int,
    n_est: int,
    R: np.ndarray,
    t: np.ndarray,
    s: float,
    mode: str,
    max_dt: float,
) -> AteResult:
    aligned = apply_alignment(est_poses, R, t, s)
    gt_xyz = gt_poses[:, :3, 3]
    est_xyz = aligned[:, :3, 3]
    return AteResult(
        align=mode,
        max_dt=max_dt,
        n_gt=n_gt,
        n_est=n_est,
        scale=s,
        T_gt_est=similarity_matrix(R, t, s),
        stamps=stamps,
        gt_xyz=gt_xyz,
        est_xyz=est_xyz,
        trans_err=np.linalg.norm(est_xyz - gt_xyz, axis=1),
        rot_err_deg=rotation_angle_deg(gt_poses[:, :3, :3], aligned[:, :3, :3]),
    )


def _check_trajectory(traj: TrajectoryLike, name: str) -> tuple[np.ndarray, np.ndarray]:
    stamps, poses = (traj.stamps, traj.poses) if isinstance(traj, Trajectory) else traj
    stamps = np.asarray(stamps, dtype=np.float64)
    poses = np.asarray(poses, dtype=np.float64)
    if stamps.ndim != 1:
        raise ValueError(f"{name}: stamps must be [N], got shape {stamps.shape}")
    if poses.shape != (len(stamps), 4, 4):
        raise ValueError(
            f"{name}: poses must be [N, 4, 4] with N = {len(stamps)} stamps, got {poses.shape}"
        )
    if not (np.isfinite(stamps).all() and np.isfinite(poses).all()):
        raise ValueError(f"{name}: stamps and poses must be finite")
    return stamps, poses

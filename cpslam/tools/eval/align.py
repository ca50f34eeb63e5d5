"""Aligning an estimated trajectory to ground truth before measuring its error.

An estimated trajectory lives in its own world frame (for cpslam, the agent's first camera),
so it has to be brought into the ground-truth frame first. Four modes:

- ``origin``: the rigid motion that makes the first associated poses coincide,
  ``T_gt_est = T_world_gt[0] · T_world_est[0]⁻¹`` (the CP-SLAM paper's protocol).
- ``se3``: the rigid motion minimising the summed squared position error (Umeyama 1991).
- ``sim3``: as ``se3`` plus one global scale (for monocular-like scale drift).
- ``none``: identity; the trajectories are assumed to share a frame already.

Every mode returns ``(R, t, s)`` with the convention ``p_gt ≈ s · R · p_est + t``.
"""

from __future__ import annotations

import logging

import numpy as np

from cpslam.common.geometry import invert

logger = logging.getLogger(__name__)

ALIGN_MODES = ("origin", "se3", "sim3", "none")

# Fewest associated poses each mode needs to be determined at all.
MIN_PAIRS = {"origin": 2, "none": 2, "se3": 3, "sim3": 3}


def align(
    est: np.ndarray, gt: np.ndarray, mode: str = "se3"
) -> tuple[np.ndarray, np.ndarray, float]:
    """Alignment ``(R [3,3], t [3], s)`` taking ``est`` onto ``gt`` (``p_gt ≈ s R p_est + t``).

    ``est`` and ``gt`` are associated, equally long arrays of either positions ``[N, 3]`` or
    poses ``[N, 4, 4]`` (``T_world_cam``). ``origin`` needs poses, because it also matches the
    first orientation; the other modes use positions only.
    """
    if mode not in ALIGN_MODES:
        raise ValueError(f"unknown alignment mode {mode!r}; expected one of {ALIGN_MODES}")
    est = np.asarray(est, dtype=np.float64)
    gt = np.asarray(gt, dtype=np.float64)
    if est.shape != gt.shape:
        raise ValueError(f"est and gt must have the same shape, got {est.shape} and {gt.shape}")
    if est.ndim == 3 and est.shape[1:] == (4, 4):
        est_xyz, gt_xyz = est[:, :3, 3], gt[:, :3, 3]
    elif est.ndim == 2 and est.shape[1] == 3:
        if mode == "origin":
            raise ValueError("origin alignment needs poses [N, 4, 4], not positions [N, 3]")
        est_xyz, gt_xyz = est, gt
    else:
        raise ValueError(f"expected positions [N, 3] or poses [N, 4, 4], got shape {est.shape}")
    if len(est_xyz) < MIN_PAIRS[mode]:
        raise ValueError(
            f"{mode} alignment needs at least {MIN_PAIRS[mode]} poses, got {len(est_xyz)}"
        )

    if mode == "none":
        return np.eye(3), np.zeros(3), 1.0
    if mode == "origin":
        T_gt_est = gt[0] @ invert(est[0])
        return T_gt_est[:3, :3].copy(), T_gt_est[:3, 3].copy(), 1.0
    return umeyama(est_xyz, gt_xyz, with_scale=(mode == "sim3"))


def umeyama(
    src_xyz: np.ndarray, dst_xyz: np.ndarray, with_scale: bool = False
) -> tuple[np.ndarray, np.ndarray, float]:
    """Least-squares similarity ``(R, t, s)`` with ``dst ≈ s R src + t`` (Umeyama, PAMI 1991).

    ``src_xyz`` and ``dst_xyz`` are ``[N, 3]`` corresponding points. Without ``with_scale``
    ``s`` is 1. Points on a line leave the rotation about that line free: one minimiser is
    returned and a warning logged.
    """
    src = np.asarray(src_xyz, dtype=np.float64)
    dst = np.asarray(dst_xyz, dtype=np.float64)
    if src.ndim != 2 or src.shape[1] != 3 or src.shape != dst.shape:
        raise ValueError(f"expected two [N, 3] arrays, got {src.shape} and {dst.shape}")
    n = len(src)
    if n < 3:
        raise ValueError(f"Umeyama alignment needs at least 3 points, got {n}")
    mu_src, mu_dst = src.mean(axis=0), dst.mean(axis=0)
    src_c, dst_c = src - mu_src, dst - mu_dst
    var_src = float((src_c**2).sum() / n)
    if var_src <= 1e-18:
        raise ValueError("Umeyama alignment is undefined: all estimated positions coincide")
    cov = dst_c.T @ src_c / n
    U, d, Vt = np.linalg.svd(cov)
    if np.count_nonzero(d > 1e-12 * max(d[0], 1e-300)) < 2:
        logger.warning("positions are (nearly) collinear: rotation about their line is unknown")
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0.0:
        S[2, 2] = -1.0  # reflection -> closest proper rotation
    R = U @ S @ Vt
    s = float(np.trace(np.diag(d) @ S) / var_src) if with_scale else 1.0
    t = mu_dst - s * R @ mu_src
    return R, t, s


def apply_alignment(
    T_world_cam: np.ndarray, R: np.ndarray, t: np.ndarray, s: float = 1.0
) -> np.ndarray:
    """Poses ``[N, 4, 4]`` mapped by the alignment: positions ``s R p + t``, rotations ``R · R_i``.

    The result stays a proper rigid pose per frame (scale only acts on positions).
    """
    poses = np.asarray(T_world_cam, dtype=np.float64)
    out = np.empty_like(poses)
    out[:] = np.eye(4)
    out[:, :3, :3] = R @ poses[:, :3, :3]
    out[:, :3, 3] = s * poses[:, :3, 3] @ R.T + t
    return out


def similarity_matrix(R: np.ndarray, t: np.ndarray, s: float = 1.0) -> np.ndarray:
    """The 4x4 matrix ``[[s R, t], [0, 1]]`` of an alignment (``T_gt_est`` when s = 1)."""
    T = np.eye(4)
    T[:3, :3] = s * np.asarray(R)
    T[:3, 3] = t
    return T

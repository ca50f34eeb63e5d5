"""Verification of a registered loop candidate: the checks that accept or reject it, and the
verdict as a `LoopRecord`.

A pair is accepted when its (coarse or refined) registration succeeded, its RMS residual is at
most ``loop.verify_max_residual`` and its overlap at least ``loop.verify_min_overlap``. The
registration's information matrix, scaled by ``loop.information_scale``, weighs the loop edge
in the pose graph when it is positive definite.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from cpslam.common.config.collab import LoopConfig
    from cpslam.server.loops.candidates import Candidate

__all__ = ["LoopRecord", "judge", "loop_information", "loop_record"]


@dataclass
class LoopRecord:
    """One verified candidate, accepted or rejected."""

    loop_id: int
    agent_a: str
    kf_a: int
    agent_b: str
    kf_b: int
    score: float
    kind: str
    accepted: bool
    reason: str
    T_a_b: list | None
    fitness: float
    rmse: float
    stamp: float
    seconds: float
    merged: bool = False
    outlier: bool = False
    method: str = ""  # how T_a_b was found: "ransac+icp", "render" (refined), "coarse" (kept)
    refinement: dict | None = None  # what `PoseRefiner` did (JSON-able)
    # Information [6, 6] of T_a_b (right perturbation, translation first): the registration's
    # times loop.information_scale; None when the registration gave none (sigmas from
    # overlap and residual then).
    information: list | None = None


def judge(reg: Any, cfg: LoopConfig) -> str:
    """Empty when the registration passes the thresholds, else why not (``loop.verify`` off:
    only a failed registration is rejected)."""
    if not reg.success:
        return reg.reason or "registration failed"
    if not cfg.verify:
        return ""
    if not reg.inlier_rmse <= cfg.verify_max_residual:
        return f"residual {reg.inlier_rmse:.4f} m > {cfg.verify_max_residual}"
    if not reg.fitness >= cfg.verify_min_overlap:
        return f"overlap {reg.fitness:.3f} < {cfg.verify_min_overlap}"
    return ""


def loop_information(reg: Any, scale: float) -> list | None:
    """The registration's information matrix times `scale`, when it is positive definite."""
    info = getattr(reg, "information", None)
    if info is None or not getattr(reg, "success", False):
        return None
    info = scale * np.asarray(info, dtype=np.float64)
    info = 0.5 * (info + info.T)
    if not np.all(np.isfinite(info)) or np.linalg.eigvalsh(info).min() <= 0:
        return None
    return info.tolist()


def loop_record(loop_id: int, cand: Candidate, reg: Any, reason: str, stamp: float,
                seconds: float, information_scale: float) -> LoopRecord:
    """The verdict on `cand`: accepted when `reason` is empty; `reg` is the registration used
    (None when none ran)."""
    return LoopRecord(
        loop_id=loop_id, agent_a=cand.agent_a, kf_a=int(cand.kf_a),
        agent_b=cand.agent_b, kf_b=int(cand.kf_b), score=float(cand.score),
        kind=str(cand.kind), accepted=not reason, reason=reason,
        T_a_b=None if reg is None else np.asarray(reg.T_dst_src, np.float64).tolist(),
        fitness=float(reg.fitness) if reg is not None else 0.0,
        rmse=float(reg.inlier_rmse) if reg is not None and np.isfinite(reg.inlier_rmse)
        else -1.0,
        stamp=stamp, seconds=seconds,
        method=getattr(reg, "method", ""),
        refinement=(getattr(reg, "details", None) or {}).get("refinement"),
        information=loop_information(reg, information_scale),
    )

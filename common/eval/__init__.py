"""Trajectory evaluation: association, alignment, absolute trajectory error (ATE) and relative
pose error (RPE).

Plots live in ``cpslam.common.eval.plot`` and the ``cpslam eval ate`` command in
``cpslam.common.eval.cli``; both are left out here so importing this package stays light.
"""

from cpslam.common.eval.align import ALIGN_MODES, align, apply_alignment, umeyama
from cpslam.common.eval.ate import (
    DEFAULT_MAX_DT,
    AteResult,
    JointAteResult,
    associate,
    evaluate_ate,
    joint_ate,
)
from cpslam.common.eval.rpe import RpeResult, evaluate_rpe
from cpslam.common.eval.segments import SegmentedAte, reference_jumps, segmented_ate
from cpslam.common.eval.source import load_trajectory, locate_trajectory

__all__ = [
    "ALIGN_MODES",
    "DEFAULT_MAX_DT",
    "AteResult",
    "JointAteResult",
    "RpeResult",
    "SegmentedAte",
    "align",
    "apply_alignment",
    "associate",
    "evaluate_ate",
    "evaluate_rpe",
    "joint_ate",
    "load_trajectory",
    "locate_trajectory",
    "reference_jumps",
    "segmented_ate",
    "umeyama",
]

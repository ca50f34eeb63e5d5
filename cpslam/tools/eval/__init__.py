"""Trajectory evaluation: association, alignment, absolute trajectory error (ATE) and relative
pose error (RPE).

Plots live in ``cpslam.tools.eval.plot`` and the ``cpslam eval ate`` command in
``cpslam.tools.eval.cli``; both are left out here so importing this package stays light.
"""

from cpslam.tools.eval.align import ALIGN_MODES, align, apply_alignment, umeyama
from cpslam.tools.eval.ate import (
    DEFAULT_MAX_DT,
    AteResult,
    JointAteResult,
    associate,
    evaluate_ate,
    joint_ate,
)
from cpslam.tools.eval.rpe import RpeResult, evaluate_rpe
from cpslam.tools.eval.segments import SegmentedAte, reference_jumps, segmented_ate
from cpslam.tools.eval.source import load_trajectory, locate_trajectory

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

"""How wrong is the ground truth? Errors of three trajectories of the same frames, estimated
from their pairwise differences alone (the three-cornered hat of clock metrology).

When the reference is itself an estimate (7-Scenes' poses come from KinectFusion), an error
measured against it is the method's error plus the reference's. Given three trajectories
a, b, c of the same frames whose errors are independent, the mean squared difference of
each pair is the sum of their two variances, so

    var_a = (d_ab^2 + d_ac^2 - d_bc^2) / 2    (and the same for b and c)

where d is an RMS difference: the ATE of one trajectory against the other (se3 alignment)
or the RMS relative pose error over a span of frames. What two sources share (the same
depth sensor's bias, say) cancels from every difference, so the estimates are of each
source's own part. With a few hundred frames they are noisy: a variance estimate below 0 is
reported as such (not clipped), the sign that the independence assumption or the sample
size does not hold for that metric.
"""

from __future__ import annotations

import itertools
import math

import numpy as np

from cpslam.tools.eval.ate import evaluate_ate
from cpslam.tools.eval.rpe import evaluate_rpe

__all__ = ["pairwise_differences", "three_cornered_hat", "hat_table"]


def pairwise_differences(trajectories: dict[str, np.ndarray],
                         deltas: tuple[int, ...] = (1, 10, 50)) -> dict[str, dict[str, float]]:
    """For every pair of T_world_cam [N, 4, 4] trajectories of the same N frames: "ate_m"
    (RMS position difference after the se3 alignment of the second onto the first) and
    "rpe{delta}_m" (RMS translation difference of their motions over delta frames).
    Keys "a|b" in the order of the dict."""
    names = list(trajectories)
    lengths = {name: len(poses) for name, poses in trajectories.items()}
    if len(set(lengths.values())) != 1:
        raise ValueError(f"pairwise_differences: the trajectories differ in length: {lengths}")
    stamps = np.arange(next(iter(lengths.values())), dtype=np.float64)
    out: dict[str, dict[str, float]] = {}
    for a, b in itertools.combinations(names, 2):
        ref, est = np.asarray(trajectories[a]), np.asarray(trajectories[b])
        entry = {"ate_m": evaluate_ate(stamps, ref, stamps, est, align="se3").rmse}
        for delta in (d for d in deltas if d < len(stamps)):
            entry[f"rpe{delta}_m"] = evaluate_rpe(stamps, ref, stamps, est, delta).trans_rmse
        out[f"{a}|{b}"] = entry
    return out


def three_cornered_hat(d_ab: float, d_ac: float, d_bc: float) -> tuple[float, float, float]:
    """Signed RMS errors of a, b, c from their pairwise RMS differences: sqrt(var) for a
    variance estimate >= 0, -sqrt(-var) for one below 0 (see the module docstring)."""
    if min(d_ab, d_ac, d_bc) < 0:
        raise ValueError("three_cornered_hat: a difference below 0")
    sq = (d_ab**2, d_ac**2, d_bc**2)
    variances = ((sq[0] + sq[1] - sq[2]) / 2, (sq[0] + sq[2] - sq[1]) / 2,
                 (sq[1] + sq[2] - sq[0]) / 2)
    a, b, c = (math.copysign(math.sqrt(abs(v)), v) for v in variances)
    return a, b, c


def hat_table(pairs: dict[str, dict[str, float]], a: str, b: str, c: str
              ) -> dict[str, dict[str, float]]:
    """Per metric of `pairwise_differences`' output, the hat's signed estimate for a, b, c."""
    def diff(x: str, y: str) -> dict[str, float]:
        return pairs.get(f"{x}|{y}") or pairs[f"{y}|{x}"]

    ab, ac, bc = diff(a, b), diff(a, c), diff(b, c)
    return {metric: dict(zip((a, b, c), three_cornered_hat(ab[metric], ac[metric], bc[metric]),
                             strict=True))
            for metric in ab if metric in ac and metric in bc}

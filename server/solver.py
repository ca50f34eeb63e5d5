"""The pose graph's optimisation in gtsam: gauge priors, Gaussian sequential factors and
robust loop factors, Levenberg-Marquardt (or graduated non-convexity around it), then the
chi-square test that classifies every loop inlier or outlier.

Information matrices arrive in our order (translation first, as g2o); gtsam's Pose3 tangent
is rotation first, and the conversion happens here (`_noise`).
"""

from __future__ import annotations

from collections.abc import Hashable, Sequence
from dataclasses import dataclass, field
from typing import Literal

import gtsam
import numpy as np

__all__ = ["CHI2_6DOF_95", "Edge", "PoseGraphResult", "RobustKernel", "solve"]

CHI2_6DOF_95 = 12.591587243743977
"""95% quantile of the chi-square distribution with 6 degrees of freedom: a loop whose squared
whitened residual exceeds it after optimisation is an outlier."""

# The gauge prior pins a component's first node; 1e-6 keeps the system well conditioned
# while moving the anchor by nothing measurable.
_PRIOR_SIGMA = 1e-6

RobustKernel = Literal["cauchy", "huber", "gnc", "none"]
Node = tuple[str, int]
"""A keyframe: ``(agent id, keyframe id)``; a frame node in all-frames mode:
``(agent id, frame index)``."""


@dataclass
class PoseGraphResult:
    """Outcome of ``PoseGraph.optimize``. Errors are gtsam graph errors (0.5 sum of squared
    whitened residuals, robust-weighted on loop edges)."""

    poses: dict[Node, np.ndarray]
    """Optimised keyframe poses ``T_world_kf [4, 4]`` by ``(agent, kf_id)``."""
    frame_poses: dict[Node, np.ndarray]
    """Optimised frame-node poses by ``(agent, frame_index)`` (all-frames mode; else empty)."""
    error_before: float
    error_after: float
    iterations: int | None
    """Levenberg-Marquardt iterations; None for GNC, which does not report them."""
    inlier_loops: list[Hashable]
    outlier_loops: list[Hashable]
    loop_chi2: dict[Hashable, float] = field(default_factory=dict)
    """Squared whitened residual of each loop (Gaussian noise, no kernel) after optimisation."""


@dataclass
class Edge:
    """One edge of the pose graph between the nodes of gtsam keys ``key_a`` and ``key_b``."""

    key_a: int
    key_b: int
    T_a_b: np.ndarray
    information: np.ndarray  # [6, 6], translation first (g2o order)
    loop_id: Hashable | None  # None for sequential edges


def solve(
    names: Sequence[tuple[str, str, int]],
    estimate: Sequence[np.ndarray],
    edges: Sequence[Edge],
    anchors: Sequence[int],
    *,
    robust_kernel: RobustKernel,
    kernel_scale: float,
    max_iters: int,
    rel_tol: float,
) -> tuple[PoseGraphResult, list[np.ndarray]]:
    """Optimise the nodes (key ``i`` is ``names[i]``, ``(agent, "kf" | "frame", id)``, starting
    at ``estimate[i]``) with a gauge prior on each of ``anchors``; the result and the optimised
    pose of every key."""
    # 1. Factor graph: gauge priors, sequential edges (Gaussian), loops (robust).
    graph = gtsam.NonlinearFactorGraph()
    prior_noise = gtsam.noiseModel.Isotropic.Sigma(6, _PRIOR_SIGMA)
    for key in anchors:
        graph.add(gtsam.PriorFactorPose3(key, _pose3(estimate[key]), prior_noise))
    # Loops go last so that the trusted factors are the indices 0 .. n_trusted - 1.
    loops: list[tuple[Edge, gtsam.BetweenFactorPose3]] = []
    for edge in sorted(edges, key=lambda e: e.loop_id is not None):
        base = _noise(edge.information)
        graph.add(_factor(edge, base, robust_kernel, kernel_scale))
        if edge.loop_id is not None:
            loops.append(
                (
                    edge,
                    gtsam.BetweenFactorPose3(edge.key_a, edge.key_b, _pose3(edge.T_a_b), base),
                )
            )
    n_trusted = graph.size() - len(loops)
    # 2. Initial values: the current estimate (an anchor never moves, being the smallest
    # key of every component it was ever in).
    initial = gtsam.Values()
    for key, T in enumerate(estimate):
        initial.insert(key, _pose3(T))
    # 3. Optimiser: Levenberg-Marquardt, or GNC around it with the trusted factors fixed.
    lm_params = gtsam.LevenbergMarquardtParams()
    lm_params.setMaxIterations(max_iters)
    lm_params.setRelativeErrorTol(rel_tol)
    if robust_kernel == "gnc":
        gnc_params = gtsam.GncLMParams(lm_params)
        gnc_params.setKnownInliers(list(range(n_trusted)))
        optimizer = gtsam.GncLMOptimizer(graph, initial, gnc_params)
        # Inlier threshold at the same 95% chi-square point as the classification.
        optimizer.setInlierCostThresholdsAtProbability(0.95)
        values, iterations = optimizer.optimize(), None
    else:
        optimizer = gtsam.LevenbergMarquardtOptimizer(graph, initial, lm_params)
        values = optimizer.optimize()
        iterations = optimizer.iterations()
    # 4. Results and loop classification by the chi-square test.
    poses = [values.atPose3(key).matrix() for key in range(len(names))]
    result = PoseGraphResult(
        poses={},
        frame_poses={},
        error_before=graph.error(initial),
        error_after=graph.error(values),
        iterations=iterations,
        inlier_loops=[],
        outlier_loops=[],
    )
    for (agent, kind, node_id), T in zip(names, poses, strict=True):
        (result.poses if kind == "kf" else result.frame_poses)[(agent, node_id)] = T
    for edge, factor in loops:
        chi2 = 2.0 * factor.error(values)
        result.loop_chi2[edge.loop_id] = chi2
        inlier = chi2 <= CHI2_6DOF_95
        (result.inlier_loops if inlier else result.outlier_loops).append(edge.loop_id)
    return result, poses


def _factor(
    edge: Edge, base: gtsam.noiseModel.Base, robust_kernel: RobustKernel, kernel_scale: float
) -> gtsam.BetweenFactorPose3:
    noise = base
    if edge.loop_id is not None and robust_kernel in ("cauchy", "huber"):
        make = {
            "cauchy": gtsam.noiseModel.mEstimator.Cauchy,
            "huber": gtsam.noiseModel.mEstimator.Huber,
        }[robust_kernel]
        noise = gtsam.noiseModel.Robust.Create(make.Create(kernel_scale), base)
    return gtsam.BetweenFactorPose3(edge.key_a, edge.key_b, _pose3(edge.T_a_b), noise)


def _noise(information: np.ndarray) -> gtsam.noiseModel.Base:
    """gtsam noise model from an information matrix in our (translation first) order."""
    perm = [3, 4, 5, 0, 1, 2]  # gtsam's Pose3 tangent is (rotation, translation)
    info = information[np.ix_(perm, perm)]
    if np.count_nonzero(info - np.diag(np.diag(info))) == 0:
        return gtsam.noiseModel.Diagonal.Precisions(np.diag(info).copy())
    return gtsam.noiseModel.Gaussian.Information(info)


def _pose3(T: np.ndarray) -> gtsam.Pose3:
    return gtsam.Pose3(np.asarray(T, dtype=np.float64))

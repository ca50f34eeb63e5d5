"""Coarse relative pose between two keyframes' RGB-D images, and its verification.

The server pulls the RGB-D images of a loop candidate's two keyframes from the agents and
estimates ``T_dst_src`` (maps points from the src camera frame into the dst camera frame)
before the rendering-based refinement against the sub-map. The paper starts that refinement
from the loop frame's own pose and so fails under large viewpoint changes; a global estimate
from features does not depend on where it starts:

1. each depth image is back-projected (valid depth in ``[min_depth, max_depth]``) into a
   coarse cloud (``voxel_size``; normals, FPFH features) and a fine cloud (half the voxel);
2. matches: mutual nearest neighbours in the joint space [FPFH, ``color_weight`` x RGB] —
   FPFH alone cannot tell the points of one wall from another, colour can;
3. RANSAC, vectorised in numpy with a seeded generator: 3-match samples that pass an
   edge-length check, Kabsch, scored by the matches they explain; the best few distinct
   hypotheses that explain at least ``min_support`` matches are kept (false alignments of
   look-alike surfaces explain a handful);
4. each hypothesis in turn is refined by symmetric point-to-plane ICP with a Tukey kernel
   (coarse clouds at ``max_distance``, then fine clouds) and verified; the first that passes
   wins;
5. verification (also `verify`) on the fine clouds, from the smaller view into the other:
   overlap = fraction of points with a neighbour within ``inlier_distance``; residual = RMS
   point-to-plane distance of those; colour consistency = fraction of those whose colours
   agree after a global gain; free-space conflict = fraction of points that land in front of
   a surface the other camera saw (it would have seen them). Accepted when overlap >=
   ``min_overlap``, residual <= ``max_residual``, conflict <= ``max_free_space_conflict`` and
   colour consistency >= ``min_color_consistency``.

Everything after the (per-point, deterministic) open3d normals and FPFH is numpy and scipy, so
the same inputs give bit-identical poses. docs/loops.md has the measured figures.

An ``initial`` guess (e.g. from the pose graph) is refined and verified first; RANSAC runs
only when that fails. open3d is imported inside the functions: importing this module is cheap.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
from scipy.spatial import cKDTree

from cpslam.common.camera import Intrinsics
from cpslam.common.geometry import invert
from cpslam.common.icp import icp, icp_information

if TYPE_CHECKING:
    from cpslam.common.config.collab import LoopConfig

__all__ = ["RGBDView", "Registration", "RegistrationParams", "register_rgbd", "verify"]

logger = logging.getLogger(__name__)

_MIN_POINTS = 30  # fewer coarse points than this cannot be registered meaningfully
_RANSAC_BATCH = 500  # samples drawn (and scored at once) between stopping checks


class RGBDView(Protocol):
    """Anything with ``rgb`` uint8 [H, W, 3] and ``depth`` float32 [H, W] metres (0 = invalid),
    such as `cpslam.common.datasets.RGBDFrame`; a plain ``(rgb, depth)`` tuple works too."""

    rgb: np.ndarray
    depth: np.ndarray


@dataclass(frozen=True)
class RegistrationParams:
    """Settings of `register_rgbd` and `verify`; `from_config` maps the ``loop`` section."""

    voxel_size: float = 0.05
    """Voxel size (m) of the coarse clouds (features, RANSAC, first ICP); fine clouds use half."""
    max_distance: float = 0.2
    """Largest correspondence distance (m) of the first ICP stage."""
    min_overlap: float = 0.3
    """Accept only when at least this fraction of the smaller view overlaps the other."""
    max_residual: float = 0.05
    """Accept only when the RMS point-to-plane distance (m) of the overlap is at most this."""
    min_color_consistency: float = 0.3
    """Accept only when at least this fraction of the overlap agrees in colour."""
    max_free_space_conflict: float = 0.1
    """Accept only when at most this fraction of one view's points, where the other camera
    looks, lies in front of the surface that camera saw (it would have seen them)."""
    color_tolerance: float = 0.1
    """Two colours agree when their mean absolute difference (0..1 scale) after a global gain
    is below this."""
    color_weight: float = 100.0
    """Weight of RGB (0..1) against FPFH (bins sum to 300) when matching features; 0 = FPFH."""
    inlier_distance: float | None = None
    """A point overlaps the other view when its neighbour there is this close (m);
    None = 2 x ``voxel_size``."""
    min_depth: float = 0.1
    """Depth below this (m) is ignored."""
    max_depth: float = 6.0
    """Depth beyond this (m) is ignored: far depth is the noisiest and sparsest."""
    ransac_samples: int = 20_000
    """Most 3-match samples RANSAC draws; it stops earlier once 99.9 % sure it has drawn an
    all-inlier sample (the usual rule, from the best inlier ratio so far)."""
    max_hypotheses: int = 3
    """At most this many distinct RANSAC hypotheses are refined and verified."""
    min_support: int = 15
    """Only hypotheses that explain at least this many feature matches are refined: false
    alignments of look-alike surfaces (a wall on the opposite wall) explain a handful."""
    seed: int = 0
    """Seed of the RANSAC sampling."""

    def __post_init__(self) -> None:
        for name in ("voxel_size", "max_distance", "max_residual", "max_depth",
                     "color_tolerance"):
            if not getattr(self, name) > 0.0:
                raise ValueError(
                    f"RegistrationParams.{name} must be > 0, got {getattr(self, name)}"
                )
        for name in ("min_overlap", "min_color_consistency", "max_free_space_conflict"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(
                    f"RegistrationParams.{name} must be in [0, 1], got {getattr(self, name)}"
                )
        if self.inlier_distance is not None and not self.inlier_distance > 0.0:
            raise ValueError(
                f"RegistrationParams.inlier_distance must be > 0, got {self.inlier_distance}"
            )
        if not 0.0 <= self.min_depth < self.max_depth:
            raise ValueError(
                "RegistrationParams: need 0 <= min_depth < max_depth, got "
                f"{self.min_depth}, {self.max_depth}"
            )
        if (self.color_weight < 0.0 or self.ransac_samples < 1 or self.max_hypotheses < 1
                or self.min_support < 3):
            raise ValueError(
                "RegistrationParams: color_weight must be >= 0, ransac_samples and "
                "max_hypotheses >= 1, min_support >= 3"
            )

    @property
    def inlier_radius(self) -> float:
        """The effective `inlier_distance` (m)."""
        return self.inlier_distance if self.inlier_distance is not None else 2.0 * self.voxel_size

    @classmethod
    def from_config(cls, cfg: LoopConfig, seed: int = 0) -> RegistrationParams:
        """Settings from the ``loop`` config section (the other fields keep their defaults).
        With ``loop.verify`` off (the paper) no check rejects a pose: only a failed estimate
        does."""
        checks: dict[str, float] = dict(min_overlap=cfg.verify_min_overlap,
                                        max_residual=cfg.verify_max_residual)
        if not cfg.verify:
            checks = dict(min_overlap=0.0, max_residual=math.inf, min_color_consistency=0.0,
                          max_free_space_conflict=1.0)
        return cls(voxel_size=cfg.icp_voxel_size, max_distance=cfg.icp_max_distance, seed=seed,
                   **checks)


@dataclass
class Registration:
    """Outcome of `register_rgbd` or `verify`."""

    T_dst_src: np.ndarray
    """Relative pose [4, 4] float64: maps src camera-frame points into the dst camera frame."""
    fitness: float
    """Overlap: fraction of the smaller view's points with a neighbour in the other view."""
    inlier_rmse: float
    """RMS point-to-plane distance (m) of the overlapping points (inf when there are none)."""
    n_correspondences: int
    """Number of overlapping points (of the smaller view's fine cloud)."""
    method: str
    """How T was found: "initial+icp", "ransac+icp", "verify", or "none" (nothing to try)."""
    success: bool
    """Whether every verification test passed its threshold."""
    reason: str
    """Why it failed ("" on success)."""
    color_consistency: float = 0.0
    """Fraction of the overlapping points whose colours agree."""
    free_space_conflict: float = 0.0
    """Fraction of one view's points, seen by the other camera, that lie in front of what
    that camera observed (the larger of both directions); near 0 when aligned."""
    seconds: float = 0.0
    """Wall time of the call."""
    details: dict[str, Any] = field(default_factory=dict)
    """Diagnostics of `register_rgbd`: coarse point counts, feature matches, the support of
    each RANSAC hypothesis, the reasons the tried ones failed."""
    information: np.ndarray | None = None
    """Gauss-Newton information [6, 6] of T_dst_src (right perturbation, translation first)
    as if the fine correspondences were independent (`cpslam.common.icp.icp_information`);
    set by `register_rgbd` on success, else None."""


def register_rgbd(
    src: RGBDView | tuple[np.ndarray, np.ndarray],
    dst: RGBDView | tuple[np.ndarray, np.ndarray],
    intrinsics: Intrinsics,
    params: RegistrationParams | None = None,
    initial: np.ndarray | None = None,
    dst_intrinsics: Intrinsics | None = None,
) -> Registration:
    """Estimate ``T_dst_src`` between two RGB-D views and verify it.

    Args:
        src, dst: the two views (``.rgb``/``.depth`` or ``(rgb, depth)``).
        intrinsics: camera of ``src`` (and of ``dst`` unless ``dst_intrinsics`` is given).
        params: thresholds and sizes (default `RegistrationParams()`).
        initial: optional guess of ``T_dst_src`` [4, 4]; when ICP from it passes
            verification, RANSAC is skipped.
        dst_intrinsics: camera of ``dst`` when it differs.

    Returns:
        A `Registration`; ``success`` False with a ``reason`` when the views do not overlap or
        do not align well enough (the best ``T_dst_src`` tried is still returned).

    Raises:
        ValueError: for images of the wrong shape or dtype, or an ``initial`` that is not 4x4.
    """
    start = time.perf_counter()
    params = params or RegistrationParams()
    dst_intrinsics = dst_intrinsics or intrinsics
    if initial is not None:
        initial = np.asarray(initial, dtype=np.float64)
        if initial.shape != (4, 4):
            raise ValueError(f"register_rgbd: initial must be 4x4, got {initial.shape}")
    a = _View(*_unpack(src, intrinsics, "src"), intrinsics, params)
    b = _View(*_unpack(dst, dst_intrinsics, "dst"), dst_intrinsics, params)
    if min(a.size, b.size) < _MIN_POINTS:
        result = _failed(f"too few valid depth points (src {a.size}, dst {b.size} after "
                         f"downsampling; need {_MIN_POINTS})")
    else:
        result = _search(a, b, params, initial)
        if result.success:
            result.information, pairs = icp_information(
                a, b, result.T_dst_src, params.voxel_size, 0.4 * params.voxel_size)
            result.details["information_pairs"] = pairs
    result.details.update(points_src=a.size, points_dst=b.size)
    result.seconds = time.perf_counter() - start
    logger.debug(
        "register_rgbd: %s overlap %.3f residual %.4f colour %.2f conflict %.3f (%s) in %.2f s",
        result.method, result.fitness, result.inlier_rmse, result.color_consistency,
        result.free_space_conflict, result.reason or "accepted", result.seconds,
    )
    return result


def verify(
    src: RGBDView | tuple[np.ndarray, np.ndarray],
    dst: RGBDView | tuple[np.ndarray, np.ndarray],
    intrinsics: Intrinsics,
    T_dst_src: np.ndarray,
    params: RegistrationParams | None = None,
    dst_intrinsics: Intrinsics | None = None,
) -> Registration:
    """Verification tests of two views under a given ``T_dst_src``.

    No optimisation: used after the rendering-based refinement has moved the pose found by
    `register_rgbd`. Arguments as in `register_rgbd`; ``method`` is "verify".
    """
    start = time.perf_counter()
    params = params or RegistrationParams()
    dst_intrinsics = dst_intrinsics or intrinsics
    T_dst_src = np.asarray(T_dst_src, dtype=np.float64)
    if T_dst_src.shape != (4, 4):
        raise ValueError(f"verify: T_dst_src must be 4x4, got {T_dst_src.shape}")
    a = _View(*_unpack(src, intrinsics, "src"), intrinsics, params, features=False)
    b = _View(*_unpack(dst, dst_intrinsics, "dst"), dst_intrinsics, params, features=False)
    if min(a.size, b.size) < _MIN_POINTS:
        result = _failed(f"too few valid depth points (src {a.size}, dst {b.size})")
        result.T_dst_src = T_dst_src
    else:
        result = _evaluate(a, b, T_dst_src, params, "verify")
    result.seconds = time.perf_counter() - start
    return result


# --------------------------------------------------------------------------------------------
# implementation


def _search(a: _View, b: _View, params: RegistrationParams, initial: np.ndarray | None
            ) -> Registration:
    """The initial guess, then RANSAC hypotheses, each refined and verified, until one
    passes; otherwise the best failure, its reason saying why."""
    tried: list[Registration] = []
    details: dict[str, Any] = {}
    if initial is not None:
        tried.append(_evaluate(a, b, _refine(a, b, initial, params), params, "initial+icp"))
    if not (tried and tried[0].success):
        matches = _match_features(a, b)
        hypotheses = _ransac(a.xyz, b.xyz, *matches, params)
        details.update(matches=len(matches[0]), support=[n for _, n in hypotheses])
        for T, support in hypotheses:
            if support < params.min_support:
                break
            tried.append(_evaluate(a, b, _refine(a, b, T, params), params, "ransac+icp"))
            if tried[-1].success:
                break
        if not any(r.method == "ransac+icp" for r in tried):
            best_support = hypotheses[0][1] if hypotheses else 0
            unsupported = _failed(f"no alignment explains {params.min_support} feature "
                                  f"matches (best {best_support} of {len(matches[0])})")
            if hypotheses:  # unverified, but better than the identity
                unsupported.T_dst_src = hypotheses[0][0]
            if tried:  # the initial guess failed as well: say why both failed
                tried[0].reason = f"{tried[0].reason}; {unsupported.reason}"
            else:
                tried.append(unsupported)
    best = next((r for r in tried if r.success), None) or max(tried, key=_score)
    details["rejected"] = [r.reason for r in tried if not r.success]
    best.details.update(details)
    return best


class _View:
    """One RGB-D view as clouds: coarse (voxel_size; normals, features) and fine (half)."""

    def __init__(self, rgb: np.ndarray, depth: np.ndarray, intrinsics: Intrinsics,
                 params: RegistrationParams, features: bool = True) -> None:
        import open3d as o3d

        valid = np.isfinite(depth) & (depth > params.min_depth) & (depth < params.max_depth)
        xyz = intrinsics.backproject(np.where(valid, depth, 0.0).astype(np.float32))[valid]
        full = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz.astype(np.float64)))
        full.colors = o3d.utility.Vector3dVector(rgb[valid].astype(np.float64) / 255.0)
        self.fine = _with_normals(full.voxel_down_sample(0.5 * params.voxel_size),
                                  params.voxel_size)
        self.coarse = _with_normals(full.voxel_down_sample(params.voxel_size),
                                    2.0 * params.voxel_size)
        self.size = len(self.coarse.points)
        self.xyz = np.asarray(self.coarse.points)
        self.normals = np.asarray(self.coarse.normals)
        self.fine_xyz = np.asarray(self.fine.points)
        self.fine_rgb = np.asarray(self.fine.colors)
        self.fine_normals = np.asarray(self.fine.normals)
        self.depth = np.where(valid, depth, 0.0).astype(np.float32)
        self.intrinsics = intrinsics
        self._tree: cKDTree | None = None
        self._coarse_tree: cKDTree | None = None
        self._gradient: np.ndarray | None = None
        self._voxel_size = params.voxel_size
        self.fine_intensity = self.fine_rgb.mean(axis=1)
        self.features: np.ndarray | None = None
        if features and self.size >= _MIN_POINTS:
            fpfh = o3d.pipelines.registration.compute_fpfh_feature(
                self.coarse,
                o3d.geometry.KDTreeSearchParamHybrid(radius=5.0 * params.voxel_size, max_nn=100),
            )
            rgb_coarse = np.asarray(self.coarse.colors) * params.color_weight
            self.features = np.hstack([np.asarray(fpfh.data).T, rgb_coarse])

    @property
    def tree(self) -> cKDTree:
        """KD-tree over the fine cloud (built on first use)."""
        if self._tree is None:
            self._tree = cKDTree(self.fine_xyz)
        return self._tree

    @property
    def gradient(self) -> np.ndarray:
        """Intensity gradient [N, 3] of the fine cloud in each point's tangent plane, by least
        squares over its neighbours (computed on first use)."""
        if self._gradient is None:
            xyz, normals = self.fine_xyz, self.fine_normals
            dist, idx = self.tree.query(xyz, k=9, distance_upper_bound=2.0 * self._voxel_size)
            found = np.isfinite(dist)
            idx = np.where(found, idx, 0)
            offset = xyz[idx] - xyz[:, None]  # [N, 9, 3]
            offset -= np.einsum("nki,ni->nk", offset, normals)[..., None] * normals[:, None]
            offset *= found[..., None]
            d_int = (self.fine_intensity[idx] - self.fine_intensity[:, None]) * found
            # The n n^T term keeps the system regular and the gradient in the tangent plane.
            A = np.einsum("nki,nkj->nij", offset, offset) + np.einsum("ni,nj->nij",
                                                                      normals, normals)
            b = np.einsum("nki,nk->ni", offset, d_int)
            self._gradient = np.linalg.solve(A + 1e-9 * np.eye(3), b[..., None])[..., 0]
        return self._gradient

    @property
    def coarse_tree(self) -> cKDTree:
        """KD-tree over the coarse cloud (built on first use)."""
        if self._coarse_tree is None:
            self._coarse_tree = cKDTree(self.xyz)
        return self._coarse_tree


def _with_normals(cloud: Any, radius: float) -> Any:
    import open3d as o3d

    if len(cloud.points) >= 3:
        cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=30))
        # Normals facing the camera (at the origin) keep FPFH and the ICP terms consistent.
        cloud.orient_normals_towards_camera_location(np.zeros(3))
    return cloud


def _match_features(a: _View, b: _View) -> tuple[np.ndarray, np.ndarray]:
    """Mutual nearest neighbours in feature space: indices into a.xyz and b.xyz."""
    assert a.features is not None and b.features is not None
    _, a_to_b = cKDTree(b.features).query(a.features)
    _, b_to_a = cKDTree(a.features).query(b.features)
    src = np.flatnonzero(b_to_a[a_to_b] == np.arange(len(a_to_b)))
    return src, a_to_b[src]


def _ransac(xyz_a: np.ndarray, xyz_b: np.ndarray, idx_a: np.ndarray, idx_b: np.ndarray,
            params: RegistrationParams) -> list[tuple[np.ndarray, int]]:
    """Best distinct rigid hypotheses ``(T_b_a, matches explained)``, best first."""
    n = len(idx_a)
    if n < 3:
        return []
    P, Q = xyz_a[idx_a], xyz_b[idx_b]
    rng = np.random.default_rng(params.seed)
    threshold2 = (1.5 * params.voxel_size) ** 2
    Rs, ts, scores = [], [], []
    drawn, needed = 0, params.ransac_samples
    while drawn < min(needed, params.ransac_samples):
        batch = min(_RANSAC_BATCH, params.ransac_samples - drawn)
        drawn += batch
        R, t = _sample_motions(P, Q, rng.integers(0, n, size=(batch, 3)), params.voxel_size)
        if len(R) == 0:
            continue
        moved = np.matmul(P[None], np.swapaxes(R, 1, 2)) + t[:, None]  # [M, n, 3]
        Rs.append(R)
        ts.append(t)
        scores.append(np.sum(np.sum((moved - Q) ** 2, axis=2) < threshold2, axis=1))
        # Standard RANSAC stopping rule: enough samples to have drawn an all-inlier triple
        # with probability 0.999, given the best inlier ratio so far.
        ratio = max(int(c.max()) for c in scores) / n
        if ratio > 0.0:
            miss = 1.0 - ratio**3
            needed = int(np.ceil(np.log(1e-3) / np.log(miss))) if miss > 0 else 0
    if not scores:
        return []
    R, t, counts = np.concatenate(Rs), np.concatenate(ts), np.concatenate(scores)
    hypotheses: list[tuple[np.ndarray, int]] = []
    kept: list[int] = []
    # Most good samples find the same pose: look for distinct ones among the best few hundred.
    for m in np.argsort(-counts, kind="stable")[:500]:
        if counts[m] < 3 or len(kept) == params.max_hypotheses:
            break
        if any(_similar(R[m], t[m], R[k], t[k], params.voxel_size) for k in kept):
            continue
        kept.append(m)
        # Re-fit on every match the sample explains: less noise than three points.
        inliers = np.sum((P @ R[m].T + t[m] - Q) ** 2, axis=1) < threshold2
        R_all, t_all = _kabsch(P[inliers][None], Q[inliers][None])
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R_all[0], t_all[0]
        hypotheses.append((T, int(counts[m])))
    return hypotheses


def _sample_motions(P: np.ndarray, Q: np.ndarray, tri: np.ndarray, voxel_size: float
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Rigid motions [M, 3, 3], [M, 3] of the 3-match samples ``tri`` [S, 3] that pass the
    checks: three distinct matches, edge lengths kept within 10 %, no edge under 2 voxels."""
    tri = tri[(tri[:, 0] != tri[:, 1]) & (tri[:, 1] != tri[:, 2]) & (tri[:, 0] != tri[:, 2])]
    p, q = P[tri], Q[tri]  # [S, 3, 3]
    # A rigid motion keeps edge lengths; small triangles pin the rotation poorly.
    lp = np.linalg.norm(p - np.roll(p, 1, axis=1), axis=2)
    lq = np.linalg.norm(q - np.roll(q, 1, axis=1), axis=2)
    ok = np.all(np.minimum(lp, lq) >= 0.9 * np.maximum(lp, lq), axis=1)
    ok &= np.all(lp > 2.0 * voxel_size, axis=1)
    return _kabsch(p[ok], q[ok]) if ok.any() else (np.zeros((0, 3, 3)), np.zeros((0, 3)))


def _kabsch(p: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares rotations [M, 3, 3] and translations [M, 3] with R p + t ~ q, for point
    sets p, q [M, K, 3]."""
    mp, mq = p.mean(axis=1), q.mean(axis=1)
    H = np.einsum("mki,mkj->mij", p - mp[:, None], q - mq[:, None])
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(np.swapaxes(Vt, 1, 2) @ np.swapaxes(U, 1, 2)))
    D = np.broadcast_to(np.eye(3), H.shape).copy()
    D[:, 2, 2] = d
    R = np.swapaxes(Vt, 1, 2) @ D @ np.swapaxes(U, 1, 2)
    return R, mq - np.einsum("mij,mj->mi", R, mp)


def _similar(R1: np.ndarray, t1: np.ndarray, R2: np.ndarray, t2: np.ndarray,
             voxel_size: float) -> bool:
    """Whether two rigid motions differ by less than 2 voxels and 5 degrees."""
    cos_angle = 0.5 * (float(np.sum(R1 * R2)) - 1.0)  # trace(R1^T R2) = sum of products
    return (float(np.linalg.norm(t1 - t2)) < 2.0 * voxel_size
            and cos_angle > np.cos(np.radians(5.0)))


def _refine(a: _View, b: _View, T_init: np.ndarray, params: RegistrationParams) -> np.ndarray:
    """ICP: symmetric point-to-plane on the coarse clouds at max_distance, then on the fine
    clouds at voxel_size with a photometric term (Park et al., "Colored point cloud
    registration revisited", ICCV 2017), both with Tukey kernels.

    The robust kernel matters at large viewpoint changes: without it the points of one view
    that the other does not see pull the pose by centimetres. The photometric term pins what
    geometry leaves free, such as sliding along a wall. Written in numpy rather than with
    open3d's ICP, whose multi-threaded sums differ in the last bits from run to run.
    """
    T = icp(a, b, T_init, False, params.max_distance, params.voxel_size)
    return icp(a, b, T, True, params.voxel_size, 0.4 * params.voxel_size)


def _evaluate(a: _View, b: _View, T_dst_src: np.ndarray, params: RegistrationParams,
              method: str) -> Registration:
    # The smaller view decides: a close-up seen again from afar covers all of the close-up
    # but only part of the wide view, and that is still a full overlap.
    if len(a.fine_xyz) <= len(b.fine_xyz):
        small, large, T = a, b, T_dst_src
    else:
        small, large, T = b, a, invert(T_dst_src)
    xyz = small.fine_xyz @ T[:3, :3].T + T[:3, 3]
    dist, nearest = large.tree.query(xyz, distance_upper_bound=params.inlier_radius)
    hit = np.isfinite(dist)
    n_hit = int(hit.sum())
    fitness = n_hit / max(len(xyz), 1)
    rmse, color = float("inf"), 0.0
    if n_hit:
        j = nearest[hit]
        offset = xyz[hit] - large.fine_xyz[j]
        rmse = float(np.sqrt(np.mean(np.einsum("ni,ni->n", offset, large.fine_normals[j]) ** 2)))
        color = _color_agreement(small.fine_rgb[hit], large.fine_rgb[j], params.color_tolerance)
    conflict = max(_free_space_conflict(a, b, T_dst_src, params),
                   _free_space_conflict(b, a, invert(T_dst_src), params))
    reason = ""
    if fitness < params.min_overlap:
        reason = f"overlap {fitness:.3f} below {params.min_overlap}"
    elif rmse > params.max_residual:
        reason = f"residual {rmse:.4f} m above {params.max_residual} m"
    elif conflict > params.max_free_space_conflict:
        reason = (f"free-space conflict {conflict:.3f} above {params.max_free_space_conflict} "
                  "(surfaces where the other view sees through)")
    elif color < params.min_color_consistency:
        reason = f"colour consistency {color:.3f} below {params.min_color_consistency}"
    return Registration(
        T_dst_src=np.asarray(T_dst_src, dtype=np.float64), fitness=fitness, inlier_rmse=rmse,
        n_correspondences=n_hit, method=method, success=not reason, reason=reason,
        color_consistency=color, free_space_conflict=conflict,
    )


def _free_space_conflict(a: _View, b: _View, T_b_a: np.ndarray, params: RegistrationParams
                         ) -> float:
    """Fraction of a's points seen by b (inside b's image, valid depth there) that lie in
    front of b's surface by more than max(inlier radius, 5 % of depth): b saw through them."""
    xyz = a.fine_xyz @ T_b_a[:3, :3].T + T_b_a[:3, 3]
    uv, z = b.intrinsics.project(xyz)
    u, v = np.round(uv[:, 0]), np.round(uv[:, 1])
    inside = (u >= 0) & (u < b.intrinsics.width) & (v >= 0) & (v < b.intrinsics.height)
    z_b = b.depth[v[inside].astype(np.int64), u[inside].astype(np.int64)]
    z = z[inside][z_b > 0]
    z_b = z_b[z_b > 0]
    if len(z) == 0:
        return 0.0
    return float(np.mean(z < z_b - np.maximum(params.inlier_radius, 0.05 * z_b)))


def _color_agreement(rgb_a: np.ndarray, rgb_b: np.ndarray, tolerance: float) -> float:
    """Fraction of colour pairs [N, 3] (0..1) that agree after one global gain (exposure)."""
    ia, ib = rgb_a.mean(axis=1), rgb_b.mean(axis=1)
    lit = (ia > 0.05) & (ib > 0.05)
    gain = float(np.clip(np.median(ib[lit] / ia[lit]), 0.67, 1.5)) if lit.any() else 1.0
    return float(np.mean(np.abs(gain * rgb_a - rgb_b).mean(axis=1) < tolerance))


def _score(r: Registration) -> float:
    return r.fitness * r.color_consistency


def _failed(reason: str) -> Registration:
    return Registration(np.eye(4), 0.0, float("inf"), 0, "none", False, reason)


def _unpack(view: Any, intrinsics: Intrinsics, name: str) -> tuple[np.ndarray, np.ndarray]:
    if isinstance(view, tuple):
        if len(view) != 2:
            raise ValueError(f"{name}: expected an (rgb, depth) tuple, got {len(view)} items")
        rgb, depth = view
    else:
        rgb, depth = getattr(view, "rgb", None), getattr(view, "depth", None)
        if rgb is None or depth is None:
            raise ValueError(f"{name}: expected an object with .rgb and .depth, or a tuple")
    rgb, depth = np.asarray(rgb), np.asarray(depth)
    shape = intrinsics.shape
    if rgb.dtype != np.uint8 or rgb.shape != (*shape, 3):
        raise ValueError(f"{name}.rgb: expected uint8 {(*shape, 3)}, got {rgb.dtype} {rgb.shape}")
    if depth.shape != shape or not np.issubdtype(depth.dtype, np.floating):
        raise ValueError(
            f"{name}.depth: expected float metres of shape {shape}, got {depth.dtype} {depth.shape}"
        )
    return rgb, depth.astype(np.float32, copy=False)

"""Reconstruction metrics: accuracy, completion and completion ratio of a mesh; depth L1.

The protocol of the dense-SLAM papers (NICE-SLAM, Point-SLAM, CP-SLAM): draw ``samples``
points uniformly by area on the reconstructed and on the ground-truth mesh, then

- **accuracy**: mean distance from reconstructed samples to the ground truth (how far what
  was built lies from the true surface);
- **completion**: mean distance from ground-truth samples to the reconstruction (how much of
  the true surface was built);
- **completion ratio**: fraction of ground-truth samples within ``threshold`` (5 cm) of the
  reconstruction; **precision** is the same the other way, F-score their harmonic mean.

``method="points"`` measures to the other mesh's samples with a k-d tree, exactly as the
papers' scripts; it has a floor from the sample spacing (a mesh against itself scores a few
millimetres). ``method="surface"`` measures to the other mesh's triangles (open3d ray-casting
scene), which has no floor. ``Frustum`` restricts the scored samples to what the cameras saw.
Lengths are metres in code and JSON; tables show centimetres.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree

from cpslam.common.camera import Intrinsics
from cpslam.common.geometry import invert
from cpslam.tools.mesh import sample_surface

logger = logging.getLogger(__name__)

__all__ = [
    "DEFAULT_SAMPLES",
    "DEFAULT_THRESHOLD",
    "METHODS",
    "Frustum",
    "ReconResult",
    "cull_to_frustum",
    "depth_l1",
    "evaluate_recon",
]

DEFAULT_SAMPLES = 200_000
DEFAULT_THRESHOLD = 0.05  # metres, the completion-ratio radius of the papers
METHODS = ("points", "surface")


@dataclass
class ReconResult:
    """Mesh reconstruction scores. Lengths in metres, ratios as fractions in [0, 1]."""

    accuracy: float
    completion: float
    completion_ratio: float
    precision: float
    threshold: float
    method: str
    samples: int  # drawn on each mesh
    seed: int
    n_est: int  # reconstructed samples scored (after culling)
    n_gt: int  # ground-truth samples scored (after culling)
    culled: bool
    seconds: float
    # "points" only (0 for "surface"): what a perfect reconstruction would score, the mean
    # nearest-neighbour distance of `samples` uniform points on the target mesh,
    # 0.5 / sqrt(samples / area); accuracy measures to gt samples, completion to est samples
    accuracy_floor: float = 0.0
    completion_floor: float = 0.0

    @property
    def f_score(self) -> float:
        """Harmonic mean of precision and completion ratio (recall)."""
        total = self.precision + self.completion_ratio
        return 0.0 if total == 0 else 2 * self.precision * self.completion_ratio / total

    def to_dict(self) -> dict:
        """JSON-ready numbers, lengths in metres (``_m``) and centimetres (``_cm``)."""
        out = asdict(self)
        for key in ("accuracy", "completion", "threshold", "accuracy_floor", "completion_floor"):
            value = out.pop(key)
            out[f"{key}_m"] = value
            out[f"{key}_cm"] = 100.0 * value
        out["completion_ratio_pct"] = 100.0 * self.completion_ratio
        out["f_score"] = self.f_score
        return out


@dataclass
class Frustum:
    """The region a set of cameras saw: in front of some camera, inside its image, nearer
    than ``depth_max`` and, when ``depths`` are given, not behind the observed surface.

    Args:
        T_world_cam: camera poses ``[N, 4, 4]``; non-finite poses (frames without ground
            truth) are skipped.
        intrinsics: the cameras' intrinsics.
        depth_max: farthest seen distance (z, metres).
        depths: optional depth images ``[H, W]`` (metres, 0 = invalid) at those poses; a point
            then counts as seen only where its pixel has a reading and the point is at most
            ``depth_tolerance`` behind it (occlusion-aware culling).
        depth_tolerance: metres.
    """

    T_world_cam: np.ndarray
    intrinsics: Intrinsics
    depth_max: float = 6.0
    depths: Sequence[np.ndarray] | None = None
    depth_tolerance: float = 0.05

    def __post_init__(self) -> None:
        poses = np.asarray(self.T_world_cam, dtype=np.float64)
        if poses.ndim == 2:
            poses = poses[None]
        if poses.ndim != 3 or poses.shape[1:] != (4, 4):
            raise ValueError(f"Frustum: T_world_cam must be [N, 4, 4], got {poses.shape}")
        if self.depths is not None and len(self.depths) != len(poses):
            raise ValueError(f"Frustum: {len(self.depths)} depth images for {len(poses)} poses")
        if self.depth_max <= 0 or self.depth_tolerance < 0:
            raise ValueError("Frustum: depth_max must be > 0 and depth_tolerance >= 0")
        self.T_world_cam = poses

    def visible(self, xyz: np.ndarray) -> np.ndarray:
        """Boolean mask ``[M]``: which points ``xyz [M, 3]`` some camera saw."""
        xyz = np.asarray(xyz, dtype=np.float64)
        if xyz.ndim != 2 or xyz.shape[1] != 3:
            raise ValueError(f"Frustum.visible: expected xyz [M, 3], got {xyz.shape}")
        intr = self.intrinsics
        seen = np.zeros(len(xyz), dtype=bool)
        todo = np.arange(len(xyz))  # only points no camera has seen yet are tested again
        finite = np.isfinite(self.T_world_cam).all(axis=(1, 2))
        for i in np.flatnonzero(finite):
            if todo.size == 0:
                break
            T_cam_world = invert(self.T_world_cam[i])
            p = xyz[todo] @ T_cam_world[:3, :3].T + T_cam_world[:3, 3]
            z = p[:, 2]
            front = (z > 0) & (z <= self.depth_max)
            z_safe = np.where(front, z, 1.0)
            u = intr.fx * p[:, 0] / z_safe + intr.cx
            v = intr.fy * p[:, 1] / z_safe + intr.cy
            # integer pixel coordinates are centres, so the image spans [-0.5, size - 0.5)
            ok = front & (u >= -0.5) & (u < intr.width - 0.5) & (v >= -0.5)
            ok &= v < intr.height - 0.5
            if self.depths is not None:
                depth = np.asarray(self.depths[i])
                if depth.shape != intr.shape:
                    raise ValueError(
                        f"Frustum: depth image {i} has shape {depth.shape}, expected {intr.shape}"
                    )
                col = np.clip(np.round(u[ok]).astype(np.int64), 0, intr.width - 1)
                row = np.clip(np.round(v[ok]).astype(np.int64), 0, intr.height - 1)
                observed = depth[row, col]
                hit = (observed > 0) & (z[ok] <= observed + self.depth_tolerance)
                ok[np.flatnonzero(ok)[~hit]] = False
            seen[todo[ok]] = True
            todo = todo[~ok]
        return seen


def cull_to_frustum(
    mesh_or_points: o3d.geometry.TriangleMesh | np.ndarray,
    poses: np.ndarray,
    intrinsics: Intrinsics,
    depth_max: float = 6.0,
    depths: Sequence[np.ndarray] | None = None,
    depth_tolerance: float = 0.05,
) -> o3d.geometry.TriangleMesh | np.ndarray:
    """Keep what the cameras at ``poses`` (``T_world_cam [N, 4, 4]``) saw; see `Frustum`.

    Points ``[M, 3]`` give the seen points; a mesh gives a copy holding the triangles whose
    three vertices were all seen (for writing or viewing a culled mesh; `evaluate_recon`
    culls its samples instead, which is finer than whole triangles).
    """
    frustum = Frustum(poses, intrinsics, depth_max, depths, depth_tolerance)
    if isinstance(mesh_or_points, o3d.geometry.TriangleMesh):
        mesh = o3d.geometry.TriangleMesh(mesh_or_points)
        seen = frustum.visible(np.asarray(mesh.vertices))
        keep = seen[np.asarray(mesh.triangles)].all(axis=1)
        mesh.remove_triangles_by_mask(~keep)
        mesh.remove_unreferenced_vertices()
        return mesh
    xyz = np.asarray(mesh_or_points, dtype=np.float64)
    return xyz[frustum.visible(xyz)]


def evaluate_recon(
    est_mesh: o3d.geometry.TriangleMesh,
    gt_mesh: o3d.geometry.TriangleMesh,
    samples: int = DEFAULT_SAMPLES,
    seed: int = 0,
    threshold: float = DEFAULT_THRESHOLD,
    method: str = "points",
    frustum: Frustum | None = None,
) -> ReconResult:
    """Accuracy, completion and completion ratio of ``est_mesh`` against ``gt_mesh``.

    Args:
        samples: points drawn on each mesh (independent seeded streams for the two meshes).
        threshold: radius of completion ratio and precision, metres.
        method: ``points`` (distance to the other mesh's samples, the papers' protocol) or
            ``surface`` (distance to the other mesh's triangles, no sampling floor).
        frustum: when given, only samples inside it are scored; distances are still taken
            to the whole other mesh (or its whole sample set), so culling never creates
            false errors at the border of the seen region.

    Raises:
        ValueError: bad arguments, a mesh without area, or no sample left after culling.
    """
    if method not in METHODS:
        raise ValueError(f"evaluate_recon: method {method!r}: expected one of {METHODS}")
    if samples <= 0 or not math.isfinite(threshold) or threshold <= 0:
        raise ValueError(
            f"evaluate_recon: samples and threshold must be > 0, got {samples}, {threshold}"
        )
    t_start = time.perf_counter()
    est_xyz = sample_surface(est_mesh, samples, seed=_substream(seed, 0))
    gt_xyz = sample_surface(gt_mesh, samples, seed=_substream(seed, 1))
    est_query, gt_query = est_xyz, gt_xyz
    if frustum is not None:
        seen = frustum.visible(np.concatenate([est_xyz, gt_xyz]))  # one pass over the views
        est_query, gt_query = est_xyz[seen[:samples]], gt_xyz[seen[samples:]]
        for name, kept in (("reconstructed", est_query), ("ground-truth", gt_query)):
            if len(kept) == 0:
                raise ValueError(
                    f"evaluate_recon: no {name} sample lies inside the camera frustums; "
                    "are the poses and the mesh in the same frame?"
                )
    if method == "points":
        est_to_gt = _nearest_distance(gt_xyz, est_query)
        gt_to_est = _nearest_distance(est_xyz, gt_query)
    else:
        est_to_gt = _surface_distance(gt_mesh, est_query)
        gt_to_est = _surface_distance(est_mesh, gt_query)
    result = ReconResult(
        accuracy=float(est_to_gt.mean()),
        completion=float(gt_to_est.mean()),
        completion_ratio=float(np.mean(gt_to_est < threshold)),
        precision=float(np.mean(est_to_gt < threshold)),
        threshold=float(threshold),
        method=method,
        samples=int(samples),
        seed=int(seed),
        n_est=len(est_query),
        n_gt=len(gt_query),
        culled=frustum is not None,
        seconds=time.perf_counter() - t_start,
    )
    if method == "points":
        result.accuracy_floor = _sampling_floor(gt_mesh, samples)
        result.completion_floor = _sampling_floor(est_mesh, samples)
    logger.info(
        "recon (%s): accuracy %.2f cm, completion %.2f cm, completion ratio %.1f %% in %.2f s",
        method,
        100 * result.accuracy,
        100 * result.completion,
        100 * result.completion_ratio,
        result.seconds,
    )
    return result


def depth_l1(rendered_depths: Sequence[np.ndarray], gt_depths: Sequence[np.ndarray]) -> float:
    """Depth L1 (metres): per frame, the mean ``|rendered - gt|`` over pixels valid (finite
    and > 0) in both; then the mean over frames (each frame weighs the same, as in NICE-SLAM).

    A single ``[H, W]`` pair or stacks ``[N, H, W]`` work too. Frames without a common valid
    pixel are skipped (and logged).

    Raises:
        ValueError: different numbers of frames, a shape mismatch (naming the frame), or no
            valid pixel in any frame.
    """
    rendered = _as_depth_list(rendered_depths)
    gt = _as_depth_list(gt_depths)
    if len(rendered) != len(gt):
        raise ValueError(f"depth_l1: {len(rendered)} rendered depth images but {len(gt)} gt")
    means = []
    for i, (d_r, d_gt) in enumerate(zip(rendered, gt, strict=True)):
        d_r = np.asarray(d_r, dtype=np.float64)
        d_gt = np.asarray(d_gt, dtype=np.float64)
        if d_r.shape != d_gt.shape or d_r.ndim != 2:
            raise ValueError(
                f"depth_l1: frame {i}: rendered {d_r.shape} and gt {d_gt.shape} must be the "
                "same [H, W]"
            )
        with np.errstate(invalid="ignore"):
            valid = np.isfinite(d_r) & np.isfinite(d_gt) & (d_r > 0) & (d_gt > 0)
        if not valid.any():
            logger.debug("depth_l1: frame %d has no pixel valid in both; skipped", i)
            continue
        means.append(np.abs(d_r[valid] - d_gt[valid]).mean())
    if not means:
        raise ValueError(f"depth_l1: no pixel is valid in both images in any of {len(gt)} frames")
    if len(means) < len(gt):
        logger.info(
            "depth_l1: %d of %d frames had no common valid pixel", len(gt) - len(means), len(gt)
        )
    return float(np.mean(means))


def _as_depth_list(depths: Sequence[np.ndarray] | np.ndarray) -> list[np.ndarray]:
    if isinstance(depths, np.ndarray) and depths.ndim == 2:
        return [depths]
    return list(depths)


def _substream(seed: int, k: int) -> np.random.SeedSequence:
    return np.random.SeedSequence([int(seed), k])


def _sampling_floor(mesh: o3d.geometry.TriangleMesh, samples: int) -> float:
    # the mean nearest-neighbour distance of a uniform planar scatter of density lambda is
    # 0.5 / sqrt(lambda); curvature and edges change it little
    return 0.5 / math.sqrt(samples / mesh.get_surface_area())


def _nearest_distance(target_xyz: np.ndarray, query_xyz: np.ndarray) -> np.ndarray:
    distances, _ = cKDTree(target_xyz).query(query_xyz, k=1, workers=-1)
    return distances


def _surface_distance(mesh: o3d.geometry.TriangleMesh, query_xyz: np.ndarray) -> np.ndarray:
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(np.asarray(mesh.vertices, dtype=np.float32)),
        o3d.core.Tensor(np.asarray(mesh.triangles, dtype=np.uint32)),
    )
    query = o3d.core.Tensor(query_xyz.astype(np.float32))
    return scene.compute_distance(query).numpy().astype(np.float64)

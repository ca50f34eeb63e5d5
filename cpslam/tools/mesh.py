"""Triangle meshes from depth images by TSDF fusion, mesh files and surface sampling.

    mesh = tsdf_mesh(((rgb, depth, T_world_cam) for ...), intrinsics, voxel_size=0.02)
    write_mesh("runs/x/mesh.ply", mesh)

Fusion uses open3d's tensor `VoxelBlockGrid` (a hashed grid of 8^3-voxel blocks holding a
truncated signed distance, a weight and a colour); open3d 0.20's legacy `ScalableTSDFVolume`
returns empty meshes, so it is not used. Meshes are returned as legacy
`open3d.geometry.TriangleMesh` (what `open3d.io` reads and writes, and what viewers expect),
vertex colours in [0, 1].

Two folder helpers: `mesh_from_renders` fuses images written in the Replica layout at the
poses of their `traj.txt` (what `cpslam render` writes: depth rendered from a map at the
estimated poses), and `reference_mesh_from_ground_truth` fuses a dataset's own depth at its
ground-truth poses, a reference surface for evaluation only.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterable
from pathlib import Path

import numpy as np
import open3d as o3d

from cpslam.common.camera import Intrinsics
from cpslam.common.geometry import invert, is_rigid, project_to_rigid
from cpslam.common.logs import progress

logger = logging.getLogger(__name__)

__all__ = [
    "mesh_from_renders",
    "read_mesh",
    "reference_mesh_from_ground_truth",
    "sample_surface",
    "tsdf_mesh",
    "write_mesh",
]

Frame = tuple[np.ndarray | None, np.ndarray, np.ndarray]


def tsdf_mesh(
    frames: Iterable[Frame],
    intrinsics: Intrinsics,
    voxel_size: float = 0.02,
    trunc_voxels: float = 4.0,
    depth_max: float = 6.0,
    min_observations: int = 3,
    device: str = "cpu",
    block_count: int = 10000,
) -> o3d.geometry.TriangleMesh:
    """Fuse depth images into a TSDF and extract its zero level set as a triangle mesh.

    Args:
        frames: ``(rgb, depth, T_world_cam)`` per frame: ``rgb`` uint8 ``[H, W, 3]`` or None,
            ``depth`` float32 ``[H, W]`` metres (0 or non-finite = no reading), ``T_world_cam``
            ``[4, 4]``. Either every frame has colour or none has.
        intrinsics: the camera of every frame (image size must match the depth).
        voxel_size: TSDF voxel edge in metres.
        trunc_voxels: truncation distance in voxels (``trunc_voxels * voxel_size`` metres).
        depth_max: readings farther than this (metres) are ignored.
        min_observations: voxels observed by fewer frames than this are left out of the
            mesh; raise it to drop surfaces seen once (floaters), lower it to 1 for a handful
            of frames.
        device: ``cpu`` or ``cuda[:N]``; open3d builds without CUDA (open3d-cpu) fall back
            to the CPU with a warning, since fusion is cheap there.
        block_count: initial number of hash-map blocks; the map grows on demand.

    Returns:
        A legacy triangle mesh with vertex normals, and vertex colours when frames had colour.

    Raises:
        ValueError: a frame with the wrong shape or a non-rigid / non-finite pose (naming the
            frame), bad parameters, or an empty result (no frame, no valid depth within
            ``depth_max``, or no surface crossing), with what was integrated.
    """
    if voxel_size <= 0 or trunc_voxels <= 0 or depth_max <= 0 or min_observations < 1:
        raise ValueError(
            f"tsdf_mesh: voxel_size, trunc_voxels, depth_max must be > 0 and min_observations "
            f">= 1, got {voxel_size}, {trunc_voxels}, {depth_max}, {min_observations}"
        )
    o3d_device = _o3d_device(device)
    # open3d looks up the pixel of a voxel by truncating its projection, i.e. takes pixel
    # centres at integer + 0.5, while ours are at integers: shifting the principal point by
    # half a pixel removes a bias of half a pixel's footprint (1.2 cm at 160x120, 2.5 m).
    K_o3d = intrinsics.K.copy()
    K_o3d[:2, 2] += 0.5
    K = o3d.core.Tensor(K_o3d, o3d.core.float64)
    grid: o3d.t.geometry.VoxelBlockGrid | None = None
    colored = False
    n_frames = n_valid = 0
    t_start = time.perf_counter()
    for i, (rgb, depth, T_world_cam) in enumerate(frames):
        depth, T_cam_world = _check_frame(i, depth, T_world_cam, intrinsics)
        if grid is None:
            colored = rgb is not None
            grid = _make_grid(voxel_size, colored, block_count, o3d_device)
        if (rgb is not None) != colored:
            raise ValueError(
                f"tsdf_mesh: frame {i} {'has' if rgb is not None else 'lacks'} colour but "
                f"frame 0 {'has' if colored else 'lacks'} it; give colour for all frames or none"
            )
        valid = int(np.count_nonzero((depth > 0) & (depth <= depth_max)))
        n_frames += 1
        if valid == 0:
            continue
        n_valid += valid
        depth_image = o3d.t.geometry.Image(o3d.core.Tensor(depth, device=o3d_device))
        extrinsic = o3d.core.Tensor(T_cam_world, o3d.core.float64)
        blocks = grid.compute_unique_block_coordinates(
            depth_image, K, extrinsic, 1.0, depth_max, trunc_voxels
        )
        if rgb is None:
            grid.integrate(blocks, depth_image, K, extrinsic, 1.0, depth_max, trunc_voxels)
        else:
            color_image = o3d.t.geometry.Image(
                o3d.core.Tensor(_check_rgb(i, rgb, depth.shape), device=o3d_device)
            )
            grid.integrate(
                blocks, depth_image, color_image, K, K, extrinsic, 1.0, depth_max, trunc_voxels
            )
    seconds = time.perf_counter() - t_start
    what = f"{n_frames} frame(s), {n_valid} depth reading(s) within {depth_max} m"
    if grid is None or n_valid == 0:
        raise ValueError(f"tsdf_mesh: nothing to fuse ({what})")
    # Each frame adds weight 1 and open3d keeps voxels with weight strictly above its
    # threshold, so half a count below min_observations keeps exactly "seen that often".
    threshold = max(min_observations - 0.5, 0.0)
    try:
        mesh = grid.extract_triangle_mesh(weight_threshold=threshold).to_legacy()
    except RuntimeError:  # open3d raises when nothing passes the threshold
        mesh = o3d.geometry.TriangleMesh()
    if len(mesh.triangles) == 0:
        raise ValueError(
            f"tsdf_mesh: no surface seen by at least {min_observations} frame(s) ({what}, "
            f"voxel {voxel_size} m); check depth units and poses, or lower min_observations"
        )
    logger.info(
        "TSDF: %s in %.2f s (%.1f ms per frame), mesh %d vertices, %d triangles",
        what,
        seconds,
        1000 * seconds / n_frames,
        len(mesh.vertices),
        len(mesh.triangles),
    )
    return mesh


def write_mesh(path: str | Path, mesh: o3d.geometry.TriangleMesh) -> Path:
    """Write a mesh as binary PLY (or any format open3d infers from the suffix)."""
    path = Path(path)
    if len(mesh.triangles) == 0:
        raise ValueError(f"write_mesh {path}: the mesh has no triangles")
    path.parent.mkdir(parents=True, exist_ok=True)
    if not o3d.io.write_triangle_mesh(str(path), mesh, write_ascii=False, print_progress=False):
        raise OSError(f"write_mesh {path}: open3d could not write the file")
    return path


def read_mesh(path: str | Path) -> o3d.geometry.TriangleMesh:
    """Read a triangle mesh file, refusing a missing file or one without triangles."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such mesh file")
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        mesh = o3d.io.read_triangle_mesh(str(path), print_progress=False)
    if len(mesh.triangles) == 0:
        raise ValueError(f"{path}: not a triangle mesh open3d can read, or it has no triangles")
    return mesh


def sample_surface(
    mesh: o3d.geometry.TriangleMesh, n: int, seed: int | np.random.SeedSequence = 0
) -> np.ndarray:
    """``n`` points ``[n, 3]`` drawn uniformly by area over the mesh surface (seeded).

    Triangles are chosen with probability proportional to their area, then a point uniformly
    inside each chosen triangle (square-root barycentric trick).
    """
    if n <= 0:
        raise ValueError(f"sample_surface: expected n > 0, got {n}")
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    triangles = np.asarray(mesh.triangles, dtype=np.int64)
    if len(triangles) == 0:
        raise ValueError("sample_surface: the mesh has no triangles")
    corners = vertices[triangles]  # [T, 3, 3]
    areas = 0.5 * np.linalg.norm(
        np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1
    )
    total = areas.sum()
    if not np.isfinite(total) or total <= 0:
        raise ValueError("sample_surface: the mesh has zero (or non-finite) surface area")
    rng = np.random.default_rng(seed)
    chosen = rng.choice(len(triangles), size=n, p=areas / total)
    r1 = np.sqrt(rng.random(n))
    r2 = rng.random(n)
    a, b, c = corners[chosen, 0], corners[chosen, 1], corners[chosen, 2]
    return (1.0 - r1)[:, None] * a + (r1 * (1.0 - r2))[:, None] * b + (r1 * r2)[:, None] * c


def mesh_from_renders(
    render_dir: str | Path,
    frames: slice | str | None = None,
    voxel_size: float = 0.02,
    depth_max: float = 6.0,
    min_observations: int = 3,
    device: str = "cpu",
    show_progress: bool = False,
) -> o3d.geometry.TriangleMesh:
    """TSDF mesh of a folder of rendered images in the Replica layout.

    The folder holds ``results/frame%06d.png|jpg``, ``results/depth%06d.png``, ``traj.txt``
    (the poses the images were rendered at) and ``camera.yaml``; ``cpslam render`` writes
    exactly this, and so does the synthetic generator.
    """
    return _mesh_from_folder(
        render_dir,
        "replica",
        frames,
        voxel_size,
        depth_max,
        min_observations,
        device,
        show_progress,
    )


def reference_mesh_from_ground_truth(
    seq_path: str | Path,
    frames: slice | str | None = None,
    voxel_size: float = 0.02,
    depth_max: float = 6.0,
    min_observations: int = 3,
    device: str = "cpu",
    show_progress: bool = False,
) -> o3d.geometry.TriangleMesh:
    """Reference mesh of a dataset: its own depth fused at its GROUND-TRUTH poses.

    For evaluation only (a stand-in ground-truth surface where a dataset ships none);
    frames without a ground-truth pose are skipped. Any format `open_sequence` reads.
    """
    return _mesh_from_folder(
        seq_path, None, frames, voxel_size, depth_max, min_observations, device, show_progress
    )


def _mesh_from_folder(
    path: str | Path,
    fmt: str | None,
    frames: slice | str | None,
    voxel_size: float,
    depth_max: float,
    min_observations: int,
    device: str,
    show_progress: bool,
) -> o3d.geometry.TriangleMesh:
    from cpslam.common.datasets import DatasetError, open_sequence

    seq = open_sequence(path, fmt=fmt, frames=frames)
    poses = seq.gt_poses()
    if poses is None:
        raise DatasetError(f"{path}: no poses (traj.txt / ground truth) to fuse the depth at")
    posed = np.flatnonzero(np.isfinite(poses).all(axis=(1, 2)))
    if len(posed) < len(seq):
        logger.warning(
            "%s: %d of %d frames have no pose; skipped", path, len(seq) - len(posed), len(seq)
        )

    def stream() -> Iterable[Frame]:
        for i in progress(posed, desc="TSDF fusion", disable=not show_progress):
            frame = seq[int(i)]
            yield frame.rgb, frame.depth, poses[i]

    return tsdf_mesh(
        stream(),
        seq.intrinsics,
        voxel_size=voxel_size,
        depth_max=depth_max,
        min_observations=min_observations,
        device=device,
    )


def _o3d_device(device: str) -> o3d.core.Device:
    if device == "cpu":
        return o3d.core.Device("CPU:0")
    if device.startswith("cuda"):
        index = int(device.split(":")[1]) if ":" in device else 0
        if o3d.core.cuda.is_available() and index < o3d.core.cuda.device_count():
            return o3d.core.Device(f"CUDA:{index}")
        logger.warning(
            "tsdf_mesh: this open3d build has no CUDA device %s; fusing on the CPU", device
        )
        return o3d.core.Device("CPU:0")
    raise ValueError(f"tsdf_mesh: device {device!r}: expected cpu, cuda or cuda:N")


def _make_grid(
    voxel_size: float, colored: bool, block_count: int, device: o3d.core.Device
) -> o3d.t.geometry.VoxelBlockGrid:
    names, dtypes, channels = ["tsdf", "weight"], [o3d.core.float32] * 2, [1, 1]
    if colored:
        names.append("color")
        dtypes.append(o3d.core.float32)
        channels.append(3)
    return o3d.t.geometry.VoxelBlockGrid(
        attr_names=names,
        attr_dtypes=dtypes,
        attr_channels=channels,
        voxel_size=voxel_size,
        block_resolution=8,
        block_count=block_count,
        device=device,
    )


def _check_frame(
    i: int, depth: np.ndarray, T_world_cam: np.ndarray, intrinsics: Intrinsics
) -> tuple[np.ndarray, np.ndarray]:
    """Depth as contiguous float32 with non-finite set to 0, and the extrinsic T_cam_world."""
    depth = np.asarray(depth)
    if depth.shape != intrinsics.shape:
        raise ValueError(
            f"tsdf_mesh: frame {i}: depth shape {depth.shape}, expected {intrinsics.shape} "
            "(height, width) from the intrinsics"
        )
    depth = np.ascontiguousarray(depth, dtype=np.float32)
    if not np.isfinite(depth).all():
        depth = np.where(np.isfinite(depth), depth, np.float32(0.0))
    T = np.asarray(T_world_cam, dtype=np.float64)
    # 1e-3: poses stored as text (7-Scenes) are off orthonormal by about 2e-4; snap them.
    if T.shape != (4, 4) or not is_rigid(T, tol=1e-3):
        raise ValueError(f"tsdf_mesh: frame {i}: T_world_cam must be a finite rigid 4x4 matrix")
    T_cam_world = invert(project_to_rigid(T))
    return depth, T_cam_world


def _check_rgb(i: int, rgb: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Float32 RGB in [0, 1]: open3d fuses float depth only together with float colour."""
    rgb = np.asarray(rgb)
    if rgb.shape != (*shape, 3) or rgb.dtype != np.uint8:
        raise ValueError(
            f"tsdf_mesh: frame {i}: expected rgb uint8 {(*shape, 3)}, got {rgb.dtype} {rgb.shape}"
        )
    return np.ascontiguousarray(rgb, dtype=np.float32) / np.float32(255.0)

"""Binary PLY point clouds (positions, optional colours and normals), readable by open3d,
MeshLab and CloudCompare. Written with numpy so that exporting a map needs no open3d."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from cpslam.common.durable import atomic_open


def write_ply(
    path: str | Path,
    xyz: np.ndarray,
    colors: np.ndarray | None = None,
    normals: np.ndarray | None = None,
) -> Path:
    """Write points `xyz [N, 3]` with optional `colors uint8 [N, 3]` and `normals [N, 3]`."""
    xyz = np.asarray(xyz, dtype=np.float32)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise ValueError(f"write_ply {path}: xyz must be [N, 3], got {xyz.shape}")
    n = len(xyz)
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    header = ["property float x", "property float y", "property float z"]
    if normals is not None:
        normals = np.asarray(normals, dtype=np.float32)
        if normals.shape != (n, 3):
            raise ValueError(f"write_ply {path}: normals must be [{n}, 3], got {normals.shape}")
        fields += [("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")]
        header += ["property float nx", "property float ny", "property float nz"]
    if colors is not None:
        colors = np.asarray(colors)
        if colors.shape != (n, 3) or colors.dtype != np.uint8:
            raise ValueError(
                f"write_ply {path}: colors must be uint8 [{n}, 3], "
                f"got {colors.dtype} {colors.shape}"
            )
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
        header += ["property uchar red", "property uchar green", "property uchar blue"]
    rows = np.empty(n, dtype=fields)
    rows["x"], rows["y"], rows["z"] = xyz.T
    if normals is not None:
        rows["nx"], rows["ny"], rows["nz"] = normals.T
    if colors is not None:
        rows["red"], rows["green"], rows["blue"] = colors.T
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    text = "\n".join(
        ["ply", "format binary_little_endian 1.0", f"element vertex {n}", *header, "end_header"]
    )
    with atomic_open(path, "wb") as f:
        f.write(text.encode("ascii") + b"\n")
        f.write(rows.tobytes())
    return path

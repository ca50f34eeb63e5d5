"""Replica in the NICE-SLAM layout (also each part of CP-SLAM's two-agent collections).

ROOT/results/frame000000.jpg   colour (.jpg or .png; .png wins when both exist)
ROOT/results/depth000000.png   uint16 depth, 6553.5 units per metre
ROOT/traj.txt                  line i: row-major 4x4 T_world_cam of frame i (16 numbers)
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from cpslam.common.camera import Intrinsics
from cpslam.common.datasets.base import (
    DatasetError,
    RGBDSequence,
    check_pose,
    image_size,
    numbered_files,
    pair_colour_depth,
)
from cpslam.common.datasets.sidecar import Sidecar, resolve_intrinsics

logger = logging.getLogger(__name__)

NAME = "replica"
DEPTH_SCALE = 6553.5
DEFAULT_FPS = 30.0
# The renderings of NICE-SLAM's Replica release; they hold only for that image size.
REPLICA_CAMERA = {"fx": 600.0, "fy": 600.0, "cx": 599.5, "cy": 339.5, "width": 1200, "height": 680}


def looks_like(root: Path) -> bool:
    """True if `root` has the Replica layout (a results/ folder with depth images)."""
    results = root / "results"
    return results.is_dir() and next(results.glob("depth*.png"), None) is not None


def load(root: Path, sidecar: Sidecar, intrinsics: Intrinsics | None = None) -> RGBDSequence:
    """Index a Replica-layout sequence (reads file names and one PNG header, no images)."""
    results = root / "results"
    if not results.is_dir():
        raise DatasetError(
            f"{results}: missing folder (Replica layout needs results/ with "
            "frameXXXXXX.jpg|png and depthXXXXXX.png)"
        )
    colour = numbered_files(results, r"frame(\d+)\.(?:jpg|jpeg|png)")
    depth = numbered_files(results, r"depth(\d+)\.png")
    numbers = pair_colour_depth(colour, depth, f"{results}/frame*", f"{results}/depth*.png")

    image_wh = image_size(depth[numbers[0]])
    replica_size = (REPLICA_CAMERA["width"], REPLICA_CAMERA["height"])
    defaults = REPLICA_CAMERA if image_wh == replica_size else None
    camera = resolve_intrinsics(
        root,
        NAME,
        sidecar,
        intrinsics,
        defaults,
        image_wh,
        why_no_defaults=f"images are {image_wh[0]}x{image_wh[1]}, Replica's default camera "
        "only applies to 1200x680",
    )
    fps = sidecar.fps or DEFAULT_FPS
    traj = root / "traj.txt"
    reader = _TrajectoryFile(traj) if traj.is_file() else None
    if reader is None:
        logger.info("%s: no traj.txt, sequence has no ground truth", root)
    return RGBDSequence(
        path=root,
        format=NAME,
        intrinsics=camera,
        indices=numbers,
        timestamps=[n / fps for n in numbers],
        rgb_paths=[colour[n] for n in numbers],
        depth_paths=[depth[n] for n in numbers],
        depth_scale=sidecar.depth_scale or DEPTH_SCALE,
        fps=fps,
        pose_reader=reader,
    )


class _TrajectoryFile:
    """traj.txt, parsed and validated on first use, then indexed by frame number."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._poses: np.ndarray | None = None

    def __call__(self, index: int) -> np.ndarray:
        poses = self._load()
        if index >= len(poses):
            raise DatasetError(f"{self.path}: has {len(poses)} poses, no line for frame {index}")
        return poses[index].copy()

    def _load(self) -> np.ndarray:
        if self._poses is None:
            rows = []
            for lineno, line in enumerate(self.path.read_text().splitlines(), start=1):
                if not line.strip():
                    continue
                where = f"{self.path}:{lineno}"
                try:
                    values = [float(v) for v in line.split()]
                except ValueError as e:
                    raise DatasetError(
                        f"{where}: expected 16 numbers (row-major 4x4), found text ({e})"
                    ) from e
                if len(values) != 16:
                    raise DatasetError(
                        f"{where}: expected 16 numbers (row-major 4x4), found {len(values)}"
                    )
                rows.append(check_pose(np.array(values).reshape(4, 4), where))
            self._poses = np.stack(rows) if rows else np.zeros((0, 4, 4))
        return self._poses

"""ScanNet scenes as exported by ScanNet's SensReader (the layout NICE-SLAM and CP-SLAM use).

    ROOT/color/N.jpg                       colour, 1296x968 (resized here to the depth size)
    ROOT/depth/N.png                       uint16 depth in millimetres
    ROOT/pose/N.txt                        4x4 T_world_cam; rows of -inf/nan mark frames the
                                           reconstruction lost (they get no ground truth)
    ROOT/intrinsic/intrinsic_depth.txt     4x4 matrix whose top-left 3x3 is the depth K

Colour is resized to the depth resolution with INTER_AREA, so the depth intrinsics hold for
both images.
"""

from __future__ import annotations

import logging
from pathlib import Path

from cpslam.common.camera import Intrinsics
from cpslam.common.datasets.base import (
    DatasetError,
    PoseFiles,
    RGBDSequence,
    image_size,
    numbered_files,
    pair_colour_depth,
    parse_matrix,
)
from cpslam.common.datasets.sidecar import Sidecar, resolve_intrinsics

logger = logging.getLogger(__name__)

NAME = "scannet"
DEPTH_SCALE = 1000.0
DEFAULT_FPS = 30.0


def looks_like(root: Path) -> bool:
    """True if `root` has ScanNet's color/ and depth/ folders."""
    return (root / "color").is_dir() and (root / "depth").is_dir()


def load(root: Path, sidecar: Sidecar, intrinsics: Intrinsics | None = None) -> RGBDSequence:
    """Index an exported ScanNet scene (reads file names, K and one PNG header)."""
    for sub in ("color", "depth"):
        if not (root / sub).is_dir():
            raise DatasetError(
                f"{root / sub}: missing folder (ScanNet layout needs color/, "
                "depth/, and optionally pose/ and intrinsic/)"
            )
    colour = numbered_files(root / "color", r"(\d+)\.(?:jpg|jpeg|png)")
    depth = numbered_files(root / "depth", r"(\d+)\.png")
    numbers = pair_colour_depth(colour, depth, f"{root}/color", f"{root}/depth")

    k_file = root / "intrinsic" / "intrinsic_depth.txt"
    defaults = None
    if k_file.is_file():
        K = parse_matrix(k_file, 4, 4)
        defaults = {"fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2]}
    camera = resolve_intrinsics(
        root,
        NAME,
        sidecar,
        intrinsics,
        defaults,
        image_size(depth[numbers[0]]),
        why_no_defaults=f"{k_file} is missing",
    )

    pose_dir = root / "pose"
    poses = numbered_files(pose_dir, r"(\d+)\.txt") if pose_dir.is_dir() else {}
    fps = sidecar.fps or DEFAULT_FPS
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
        pose_reader=PoseFiles(poses, nonfinite_means_missing=True) if poses else None,
        resize_rgb_to_depth=True,
    )

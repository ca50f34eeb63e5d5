"""Microsoft 7-Scenes sequences (one seq-XX folder).

    ROOT/frame-000000.color.png|jpg   colour
    ROOT/frame-000000.depth.png       uint16 depth in millimetres; 0 and 65535 = no reading
    ROOT/frame-000000.pose.txt        4x4 T_world_cam as text (KinectFusion ground truth)
    ROOT/camera-intrinsics.txt        3x3 K (optional)

Without camera-intrinsics.txt the dataset's published calibration is used: fx = fy = 585,
cx = 320, cy = 240 at 640x480. The raw 7-Scenes depth is not perfectly registered to the
colour; the loader pairs them as they are.
"""

from __future__ import annotations

import logging
from pathlib import Path

from cpslam.common.camera import Intrinsics
from cpslam.common.datasets.base import (
    PoseFiles,
    RGBDSequence,
    image_size,
    numbered_files,
    pair_colour_depth,
    parse_matrix,
)
from cpslam.common.datasets.sidecar import Sidecar, resolve_intrinsics

logger = logging.getLogger(__name__)

NAME = "7scenes"
DEPTH_SCALE = 1000.0
DEFAULT_FPS = 30.0
INVALID_DEPTH = 65535
PUBLISHED_CAMERA = {"fx": 585.0, "fy": 585.0, "cx": 320.0, "cy": 240.0}


def looks_like(root: Path) -> bool:
    """True if `root` holds 7-Scenes frame-XXXXXX.depth.png files."""
    return next(root.glob("frame-*.depth.png"), None) is not None


def load(root: Path, sidecar: Sidecar, intrinsics: Intrinsics | None = None) -> RGBDSequence:
    """Index a 7-Scenes sequence folder (reads file names, K and one PNG header)."""
    colour = numbered_files(root, r"frame-(\d+)\.color\.(?:jpg|jpeg|png)")
    depth = numbered_files(root, r"frame-(\d+)\.depth\.png")
    numbers = pair_colour_depth(
        colour, depth, f"{root}/frame-*.color.*", f"{root}/frame-*.depth.png"
    )
    k_file = root / "camera-intrinsics.txt"
    if k_file.is_file():
        K = parse_matrix(k_file, 3, 3)
        defaults = {"fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2]}
    else:
        defaults = dict(PUBLISHED_CAMERA)
    camera = resolve_intrinsics(
        root, NAME, sidecar, intrinsics, defaults, image_size(depth[numbers[0]])
    )

    poses = numbered_files(root, r"frame-(\d+)\.pose\.txt")
    if poses and poses.keys() != set(numbers):
        missing = sorted(set(numbers) - poses.keys())
        if missing:
            logger.warning(
                "%s: %d frames have no pose file (first frame-%06d.pose.txt)",
                root,
                len(missing),
                missing[0],
            )
    reader = PoseFiles(poses) if poses else None
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
        pose_reader=reader,
        invalid_depth_values=(INVALID_DEPTH,),
    )

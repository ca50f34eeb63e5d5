"""TUM RGB-D benchmark sequences.

    ROOT/rgb.txt           "timestamp rgb/NAME.png" per line ('#' lines are comments)
    ROOT/depth.txt         "timestamp depth/NAME.png" per line
    ROOT/groundtruth.txt   "timestamp tx ty tz qx qy qz qw" per line (optional)

Colour and depth are captured unsynchronised; each colour image is paired with the depth
image nearest in time (within `max_dt`, each depth used once, closest pairs first), and
ground truth with the nearest pose in time (within `max_dt`). Depth is 5000 units per metre.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path

import numpy as np

from cpslam.common.camera import Intrinsics
from cpslam.common.datasets.base import (
    DatasetError,
    RGBDSequence,
    check_pose,
    image_size,
    nearest_within,
)
from cpslam.common.datasets.sidecar import Sidecar, resolve_intrinsics
from cpslam.common.geometry import pose_from_tq

logger = logging.getLogger(__name__)

NAME = "tum"
DEPTH_SCALE = 5000.0
DEFAULT_MAX_DT = 0.02
# The published calibrations of the three Kinects (TUM RGB-D "file formats" page), chosen by
# the "freiburgN" in the sequence's folder name.
TUM_CAMERAS = {
    "freiburg1": {"fx": 517.3, "fy": 516.5, "cx": 318.6, "cy": 255.3},
    "freiburg2": {"fx": 520.9, "fy": 521.0, "cx": 325.1, "cy": 249.7},
    "freiburg3": {"fx": 535.4, "fy": 539.2, "cx": 320.1, "cy": 247.6},
}


def looks_like(root: Path) -> bool:
    """True if `root` has TUM's rgb.txt and depth.txt."""
    return (root / "rgb.txt").is_file() and (root / "depth.txt").is_file()


def load(
    root: Path,
    sidecar: Sidecar,
    intrinsics: Intrinsics | None = None,
    max_dt: float = DEFAULT_MAX_DT,
) -> RGBDSequence:
    """Index a TUM RGB-D sequence (reads the three text files and one PNG header)."""
    if max_dt <= 0:
        raise DatasetError(f"max_dt must be positive, got {max_dt}")
    rgb_stamps, rgb_names = _read_list(root / "rgb.txt")
    depth_stamps, depth_names = _read_list(root / "depth.txt")
    pairs = associate(rgb_stamps, depth_stamps, max_dt)
    if not pairs:
        raise DatasetError(
            f"{root}: no colour image in rgb.txt has a depth image in depth.txt within {max_dt} s"
        )
    if len(pairs) < len(rgb_stamps):
        logger.info(
            "%s: %d of %d colour images have no depth within %.3f s and are skipped",
            root,
            len(rgb_stamps) - len(pairs),
            len(rgb_stamps),
            max_dt,
        )
    rows = [i for i, _ in pairs]
    depth_paths = [root / depth_names[j] for _, j in pairs]

    camera_name = next((k for k in TUM_CAMERAS if k in root.resolve().name.lower()), None)
    camera = resolve_intrinsics(
        root,
        NAME,
        sidecar,
        intrinsics,
        TUM_CAMERAS.get(camera_name) if camera_name else None,
        image_size(depth_paths[0]),
        why_no_defaults="the folder name holds no freiburg1/2/3 to pick a published calibration",
    )

    gt_file = root / "groundtruth.txt"
    poses: dict[int, np.ndarray] = {}
    if gt_file.is_file():
        poses = _match_ground_truth(gt_file, rgb_stamps, rows, max_dt)
        logger.info("%s: ground truth for %d of %d frames", root, len(poses), len(rows))
    stamps = rgb_stamps[rows]
    if sidecar.fps is not None:
        fps = sidecar.fps
    else:
        steps = np.diff(stamps)
        fps = 1.0 / float(np.median(steps)) if len(steps) and np.median(steps) > 0 else 30.0
    return RGBDSequence(
        path=root,
        format=NAME,
        intrinsics=camera,
        indices=rows,
        timestamps=stamps,
        rgb_paths=[root / rgb_names[i] for i in rows],
        depth_paths=depth_paths,
        depth_scale=sidecar.depth_scale or DEPTH_SCALE,
        fps=fps,
        pose_reader=poses.get if poses else None,
    )


def associate(stamps_a: np.ndarray, stamps_b: np.ndarray, max_dt: float) -> list[tuple[int, int]]:
    """Pairs (i, j) with |a_i - b_j| <= max_dt, each i and j used once, closest pairs first.

    Returned sorted by i.
    """
    order = np.argsort(stamps_b, kind="stable")
    sorted_b = stamps_b[order]
    candidates = []
    for i, t in enumerate(stamps_a):
        lo = np.searchsorted(sorted_b, t - max_dt, side="left")
        hi = np.searchsorted(sorted_b, t + max_dt, side="right")
        for k in range(lo, hi):
            dt = abs(sorted_b[k] - t)
            if dt <= max_dt:
                candidates.append((dt, i, int(order[k])))
    candidates.sort()
    used_a: set[int] = set()
    used_b: set[int] = set()
    pairs = []
    for _, i, j in candidates:
        if i not in used_a and j not in used_b:
            used_a.add(i)
            used_b.add(j)
            pairs.append((i, j))
    return sorted(pairs)


def _read_list(path: Path) -> tuple[np.ndarray, list[str]]:
    """Timestamps and file names of rgb.txt / depth.txt."""
    stamps, names = [], []
    for lineno, parts in _data_lines(path):
        if len(parts) < 2:
            raise DatasetError(f"{path}:{lineno}: expected 'timestamp filename'")
        stamps.append(_number(parts[0], path, lineno))
        names.append(parts[1])
    if not stamps:
        raise DatasetError(f"{path}: no entries")
    return np.asarray(stamps, dtype=np.float64), names


def _match_ground_truth(
    path: Path, frame_stamps: np.ndarray, rows: list[int], max_dt: float
) -> dict[int, np.ndarray]:
    """Ground truth of each frame row: the pose nearest in time, if within max_dt."""
    stamps, poses = [], []
    for lineno, parts in _data_lines(path):
        if len(parts) != 8:
            raise DatasetError(
                f"{path}:{lineno}: expected 'timestamp tx ty tz qx qy qz qw' "
                f"(8 numbers), found {len(parts)} fields"
            )
        values = np.array([_number(v, path, lineno) for v in parts])
        if not np.all(np.isfinite(values)) or np.linalg.norm(values[4:]) < 1e-6:
            raise DatasetError(f"{path}:{lineno}: non-finite value or zero quaternion")
        stamps.append(values[0])
        poses.append(check_pose(pose_from_tq(values[1:4], values[4:]), f"{path}:{lineno}"))
    nearest = nearest_within(frame_stamps[rows], np.asarray(stamps), max_dt)
    return {row: poses[k] for row, k in zip(rows, nearest, strict=True) if k >= 0}


_COMMENT = re.compile(r"^\s*(#|$)")


def _data_lines(path: Path) -> list[tuple[int, list[str]]]:
    try:
        text = path.read_text()
    except OSError as e:
        raise DatasetError(f"{path}: cannot read ({e.strerror or e})") from e
    return [
        (lineno, line.split())
        for lineno, line in enumerate(text.splitlines(), start=1)
        if not _COMMENT.match(line)
    ]


def _number(text: str, path: Path, lineno: int) -> float:
    try:
        return float(text)
    except ValueError as e:
        raise DatasetError(f"{path}:{lineno}: {text!r} is not a number") from e

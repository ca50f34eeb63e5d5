"""`open_sequence`: find a sequence's format from its layout and index it."""

from __future__ import annotations

import logging
from collections.abc import Mapping
from pathlib import Path

from cpslam.common.camera import Intrinsics
from cpslam.common.datasets import bag, replica, scannet, sevenscenes, tum
from cpslam.common.datasets.base import DatasetError, RGBDSequence, parse_frames
from cpslam.common.datasets.sidecar import Sidecar

logger = logging.getLogger(__name__)

# Checked in this order; the first whose layout matches wins.
FORMATS = {
    replica.NAME: replica,
    tum.NAME: tum,
    sevenscenes.NAME: sevenscenes,
    scannet.NAME: scannet,
    bag.NAME: bag,
}

_LAYOUTS = (
    "replica (results/ with frame*.jpg|png and depth*.png), "
    "tum (rgb.txt and depth.txt), "
    "7scenes (frame-*.color.* and frame-*.depth.png), "
    "scannet (color/ and depth/), "
    "bag (a ROS 1 .bag, an .mcap or .db3 file, or a ROS 2 bag folder with metadata.yaml)"
)


def open_sequence(
    path: str | Path,
    fmt: str | None = None,
    frames: slice | str | None = None,
    intrinsics: Intrinsics | None = None,
    overrides: Mapping[str, float | int | None] | None = None,
    max_dt: float = tum.DEFAULT_MAX_DT,
    topics: Mapping[str, str | None] | None = None,
) -> RGBDSequence:
    """Open an RGB-D sequence folder or bag lazily (index only; images load on `[i]`).

    Args:
        path: the sequence folder, or a bag (ROS 1 .bag, .mcap, .db3, ROS 2 bag folder).
        fmt: one of `FORMATS` ("replica", "tum", "7scenes", "scannet", "bag"); None
            detects it.
        frames: a slice or "START:STOP[:STEP]" over the sequence's frame list; selected
            frames keep their own indices and timestamps.
        intrinsics: complete intrinsics that override every other source.
        overrides: camera.yaml keys (fx, fy, cx, cy, width, height, depth_scale, fps) that
            take precedence over the sequence's camera.yaml; None values are ignored (the
            config's `camera.fx` ... `camera.depth_scale` can be passed with their nulls).
        max_dt: TUM and bags: the largest colour/depth and colour/ground-truth time gap (s).
        topics: bags only: "rgb", "depth", "info", "pose" → topic name (None entries, or
            no mapping, detect them; pose "none" reads no ground truth).

    Raises:
        DatasetError: the folder is missing, no layout matches, or its files are not as the
            format expects; the message names the path and what was expected.
    """
    if isinstance(frames, str):
        frames = parse_frames(frames)  # a typo fails before any file is read
    root = Path(path).expanduser()
    if not root.exists():
        raise DatasetError(f"{root}: no such folder")
    if not root.is_dir() and not bag.looks_like(root):
        raise DatasetError(
            f"{root}: not a folder (expected a sequence folder, or a bag: "
            + ", ".join(bag.SUFFIXES) + " file or ROS 2 bag folder)"
        )
    name = detect_format(root) if fmt is None else _format_name(fmt)
    topics = {k: v for k, v in (topics or {}).items() if v is not None}
    if topics and name != bag.NAME:
        raise DatasetError(
            f"{root}: topics ({', '.join(topics)}) apply to bags only, this is a {name} sequence"
        )
    sidecar = Sidecar.read(root) if root.is_dir() else Sidecar()
    if overrides:
        sidecar = sidecar.updated(overrides, "camera overrides")
    module = FORMATS[name]
    if module is tum:
        sequence = tum.load(root, sidecar, intrinsics, max_dt=max_dt)
    elif module is bag:
        sequence = bag.load(root, sidecar, intrinsics, topics=topics, max_dt=max_dt)
    else:
        sequence = module.load(root, sidecar, intrinsics)
    logger.info("opened %s sequence %s: %d frames", name, root, len(sequence))
    return sequence.select(frames)


def detect_format(root: Path) -> str:
    """The name of the first format whose layout `root` has."""
    for name, module in FORMATS.items():
        if module.looks_like(root):
            return name
    raise DatasetError(f"{root}: not a known RGB-D sequence layout; expected one of {_LAYOUTS}")


def _format_name(fmt: str) -> str:
    name = fmt.strip().lower().replace("-", "")
    aliases = {"sevenscenes": "7scenes", "7scene": "7scenes", "rosbag": "bag", "mcap": "bag"}
    name = aliases.get(name, name)
    if name not in FORMATS:
        raise DatasetError(f"unknown dataset format {fmt!r}; expected one of " + ", ".join(FORMATS))
    return name

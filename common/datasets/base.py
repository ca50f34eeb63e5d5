"""The format-independent part of the loaders: frames, lazy sequences, frame selection, errors.

A loader for one file layout only finds files and reads index/pose text; everything that
touches images (decoding, BGR→RGB, depth scaling, size checks) happens here, once.
"""

from __future__ import annotations

import logging
import re
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, overload

import cv2
import numpy as np

from cpslam.common.camera import Intrinsics
from cpslam.common.geometry import is_rigid, project_to_rigid

logger = logging.getLogger(__name__)

PoseReader = Callable[[int], "np.ndarray | None"]
"""Maps a frame's own index to its ground-truth `T_world_cam` [4, 4], or None if it has none."""


class DatasetError(ValueError):
    """A sequence on disk is missing something or holds something other than expected."""


@dataclass
class RGBDFrame:
    """One RGB-D frame as the rest of the system sees it.

    Attributes:
        index: the sequence's own frame index (the number in the file name, or the row in
            TUM's rgb.txt), kept when frames are selected.
        timestamp: seconds.
        rgb: uint8 [H, W, 3], RGB order.
        depth: float32 [H, W], metres along the optical axis (z-depth); 0 means no reading.
        gt_pose: ground-truth `T_world_cam` float64 [4, 4], or None when the sequence has none
            for this frame. It is for EVALUATION ONLY: no tracking or mapping code may read it.
    """

    index: int
    timestamp: float
    rgb: np.ndarray
    depth: np.ndarray
    gt_pose: np.ndarray | None = None


class RGBDSequence:
    """A lazily loaded RGB-D sequence: construction reads index files, `[i]` reads one frame.

    Loaders build one of these with every frame of the sequence; `select` (or `seq[a:b]`)
    narrows it while each frame keeps its own index and timestamp.
    """

    def __init__(
        self,
        path: Path,
        format: str,
        intrinsics: Intrinsics,
        indices: Sequence[int],
        timestamps: Sequence[float],
        rgb_paths: Sequence[Path],
        depth_paths: Sequence[Path],
        depth_scale: float,
        fps: float,
        pose_reader: PoseReader | None = None,
        invalid_depth_values: tuple[int, ...] = (),
        resize_rgb_to_depth: bool = False,
    ) -> None:
        """
        Args:
            path: the sequence root (for messages and summaries).
            format: the format's name, e.g. "replica".
            intrinsics: the depth camera (colour is assumed registered to depth).
            indices, timestamps, rgb_paths, depth_paths: one entry per frame, in order (the
                file each image is read from).
            depth_scale: raw depth units per metre (depth_m = raw / depth_scale).
            fps: nominal frame rate (Hz).
            pose_reader: ground truth by frame index; None when the sequence has none.
            invalid_depth_values: raw values that mean "no reading" besides 0.
            resize_rgb_to_depth: resize colour to the depth resolution (INTER_AREA) instead
                of rejecting a size mismatch (ScanNet's colour is larger than its depth).
        """
        n = len(indices)
        if not (len(timestamps) == len(rgb_paths) == len(depth_paths) == n):
            raise ValueError("indices, timestamps, rgb_paths and depth_paths differ in length")
        if n == 0:
            raise DatasetError(f"{path}: the sequence has no frames")
        if depth_scale <= 0:
            raise DatasetError(f"{path}: depth_scale must be positive, got {depth_scale}")
        self.path = Path(path)
        self.format = format
        self.intrinsics = intrinsics
        self.indices = np.asarray(indices, dtype=np.int64)
        self.timestamps = np.asarray(timestamps, dtype=np.float64)
        self.rgb_paths = [Path(p) for p in rgb_paths]
        self.depth_paths = [Path(p) for p in depth_paths]
        self.depth_scale = float(depth_scale)
        self.fps = float(fps)
        self._pose_reader = pose_reader
        self.invalid_depth_values = tuple(invalid_depth_values)
        self.resize_rgb_to_depth = resize_rgb_to_depth

    # -- the public interface -------------------------------------------------------------

    def __len__(self) -> int:
        return len(self.indices)

    @overload
    def __getitem__(self, key: int) -> RGBDFrame: ...

    @overload
    def __getitem__(self, key: slice) -> RGBDSequence: ...

    def __getitem__(self, key: int | slice) -> RGBDFrame | RGBDSequence:
        if isinstance(key, slice):
            return self.select(key)
        return self.load(key)

    def __iter__(self) -> Iterator[RGBDFrame]:
        for i in range(len(self)):
            yield self.load(i)

    def __repr__(self) -> str:
        return (
            f"RGBDSequence(format={self.format!r}, path='{self.path}', frames={len(self)}, "
            f"size={self.intrinsics.width}x{self.intrinsics.height})"
        )

    @property
    def has_gt(self) -> bool:
        """Whether ground-truth poses exist (for evaluation only)."""
        return self._pose_reader is not None

    def gt_poses(self) -> np.ndarray | None:
        """Ground-truth `T_world_cam` [N, 4, 4] of the selected frames, reading only pose files.

        Frames without ground truth hold NaN. None when the sequence has no ground truth.
        For evaluation only.
        """
        if self._pose_reader is None:
            return None
        poses = np.full((len(self), 4, 4), np.nan)
        for i, index in enumerate(self.indices):
            pose = self._pose_reader(int(index))
            if pose is not None:
                poses[i] = pose
        return poses

    def select(self, frames: slice | str | None) -> RGBDSequence:
        """The frames at the given positions (Python slice semantics over this frame list)."""
        if frames is None:
            return self
        spec = frames
        if isinstance(frames, str):
            frames = parse_frames(frames)
        positions = np.arange(len(self))[frames]
        if len(positions) == 0:
            raise DatasetError(
                f"{self.path}: frames '{_slice_text(spec)}' select none of the {len(self)} frames"
            )
        return self._subset(positions)

    def load(self, i: int) -> RGBDFrame:
        """Read the frame at position i (negative counts from the end)."""
        n = len(self)
        if not -n <= i < n:
            raise IndexError(f"frame position {i} out of range for {n} frames")
        i %= n
        index = int(self.indices[i])
        rgb, depth, rgb_where, depth_where = self._read_images(i)
        if rgb.shape[:2] != depth.shape:
            if not self.resize_rgb_to_depth:
                raise DatasetError(
                    f"{rgb_where}: colour is {_size(rgb)} but its depth "
                    f"{depth_where} is {_size(depth)}; they must match"
                )
            rgb = cv2.resize(rgb, (depth.shape[1], depth.shape[0]), interpolation=cv2.INTER_AREA)
        expected = (self.intrinsics.height, self.intrinsics.width)
        if depth.shape != expected:
            raise DatasetError(
                f"{depth_where}: image is {_size(depth)} but the intrinsics say "
                f"{expected[1]}x{expected[0]}; fix width/height (camera.yaml) or the data"
            )
        gt_pose = self._pose_reader(index) if self._pose_reader is not None else None
        if gt_pose is not None:
            gt_pose = np.array(gt_pose, dtype=np.float64)  # a copy: callers may modify it
        return RGBDFrame(
            index=index, timestamp=float(self.timestamps[i]), rgb=rgb, depth=depth, gt_pose=gt_pose
        )

    # -- internals ------------------------------------------------------------------------

    def _read_images(self, i: int) -> tuple[np.ndarray, np.ndarray, str, str]:
        """Colour (uint8 RGB) and depth (float32 m) at position i, and where each came from.

        Formats that do not store one image per file (bags) override this and
        `_subset_args`.
        """
        depth = read_depth(self.depth_paths[i], self.depth_scale, self.invalid_depth_values)
        rgb = read_rgb(self.rgb_paths[i])
        return rgb, depth, str(self.rgb_paths[i]), str(self.depth_paths[i])

    def _subset(self, positions: np.ndarray) -> RGBDSequence:
        return type(self)(**self._subset_args(positions))

    def _subset_args(self, positions: np.ndarray) -> dict[str, Any]:
        """Constructor arguments of the sequence of the frames at `positions`."""
        return dict(
            path=self.path,
            format=self.format,
            intrinsics=self.intrinsics,
            indices=self.indices[positions],
            timestamps=self.timestamps[positions],
            rgb_paths=[self.rgb_paths[p] for p in positions],
            depth_paths=[self.depth_paths[p] for p in positions],
            depth_scale=self.depth_scale,
            fps=self.fps,
            pose_reader=self._pose_reader,
            invalid_depth_values=self.invalid_depth_values,
            resize_rgb_to_depth=self.resize_rgb_to_depth,
        )


_FRAMES_RE = re.compile(r"^\s*(\d*)\s*:\s*(\d*)\s*(?::\s*(\d*)\s*)?$")


def parse_frames(spec: str) -> slice:
    """Parse "START:STOP[:STEP]" (non-negative integers, any part may be empty) into a slice.

    Examples: "0:300", ":100", "50:", "::2", "10:200:5".
    """
    match = _FRAMES_RE.match(spec) if isinstance(spec, str) else None
    if match is None:
        raise DatasetError(
            f"frame selection {spec!r} is not of the form START:STOP[:STEP] with non-negative "
            "integers (any part may be empty, e.g. '0:300', ':100', '::2')"
        )
    start, stop, step = (int(g) if g else None for g in match.groups())
    if step == 0:
        raise DatasetError(
            f"frame selection {spec!r}: STEP must be at least 1 in START:STOP[:STEP]"
        )
    return slice(start, stop, step)


def read_rgb(path: Path) -> np.ndarray:
    """Read a colour image as uint8 [H, W, 3] RGB (grey and alpha are converted)."""
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise DatasetError(f"{path}: cannot read colour image (missing or not an image)")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def read_depth(path: Path, depth_scale: float, invalid_values: tuple[int, ...] = ()) -> np.ndarray:
    """Read a uint16 depth image as float32 metres, 0 (and `invalid_values`) meaning no reading."""
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise DatasetError(f"{path}: cannot read depth image (missing or not an image)")
    if raw.dtype != np.uint16 or raw.ndim != 2:
        raise DatasetError(
            f"{path}: depth must be a single-channel uint16 image, got {raw.dtype} with shape "
            f"{raw.shape}"
        )
    depth = raw.astype(np.float32) / np.float32(depth_scale)
    for value in invalid_values:
        depth[raw == value] = 0.0
    return depth


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) of an image, from the PNG header when it is one (no decoding)."""
    try:
        with open(path, "rb") as f:
            head = f.read(24)
    except OSError as e:
        raise DatasetError(f"{path}: cannot read ({e.strerror})") from e
    if head[:8] == b"\x89PNG\r\n\x1a\n" and head[12:16] == b"IHDR":
        return int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise DatasetError(f"{path}: cannot read image (missing or not an image)")
    return img.shape[1], img.shape[0]


def parse_matrix(path: Path, rows: int, cols: int) -> np.ndarray:
    """Read a whitespace-separated text matrix of exactly rows x cols numbers."""
    try:
        text = path.read_text()
    except OSError as e:
        raise DatasetError(f"{path}: cannot read ({e.strerror or e})") from e
    try:
        values = [float(v) for v in text.split()]
    except ValueError as e:
        raise DatasetError(f"{path}: expected {rows}x{cols} numbers, found text ({e})") from e
    if len(values) != rows * cols:
        raise DatasetError(
            f"{path}: expected {rows}x{cols} = {rows * cols} numbers, found {len(values)}"
        )
    return np.asarray(values, dtype=np.float64).reshape(rows, cols)


def check_pose(pose: np.ndarray, where: str) -> np.ndarray:
    """Validate a ground-truth camera-to-world pose and return it made exactly rigid.

    `where` names the file (and line) for the error message.
    """
    if pose.shape != (4, 4) or not np.all(np.isfinite(pose)):
        raise DatasetError(f"{where}: pose must be 4x4 finite numbers")
    # Real ground truth (e.g. KinectFusion's in 7-Scenes) is orthonormal to only ~2e-4.
    if not is_rigid(pose, tol=1e-3):
        raise DatasetError(
            f"{where}: pose is not a rigid transform (rotation not orthonormal "
            "within 1e-3 or last row not [0, 0, 0, 1])"
        )
    # Snap to the nearest rotation so that every consumer (TUM writer, metrics) sees an
    # exactly rigid pose; the change is at most ~1e-3.
    return project_to_rigid(pose)


class PoseFiles:
    """Ground truth stored as one 4x4 text file per frame, validated when read.

    With `nonfinite_means_missing` a pose holding inf/nan (ScanNet's mark for frames its
    reconstruction lost) reads as "no ground truth" instead of raising.
    """

    def __init__(self, files: dict[int, Path], nonfinite_means_missing: bool = False) -> None:
        self.files = files
        self.nonfinite_means_missing = nonfinite_means_missing

    def __call__(self, index: int) -> np.ndarray | None:
        path = self.files.get(index)
        if path is None:
            return None
        pose = parse_matrix(path, 4, 4)
        if self.nonfinite_means_missing and not np.all(np.isfinite(pose)):
            logger.debug("%s: non-finite pose, frame has no ground truth", path)
            return None
        return check_pose(pose, str(path))


def numbered_files(folder: Path, pattern: str) -> dict[int, Path]:
    """Files in `folder` whose name fully matches `pattern` (first group: the frame number).

    When two files share a number (e.g. frame000001.jpg and .png), the later one in sorted
    name order wins, so .png is preferred over .jpg.
    """
    regex = re.compile(pattern)
    found: dict[int, Path] = {}
    for p in sorted(folder.iterdir()):
        m = regex.fullmatch(p.name)
        if m is not None:
            found[int(m.group(1))] = p
    return found


def pair_colour_depth(
    colour: dict[int, Path], depth: dict[int, Path], colour_where: str, depth_where: str
) -> list[int]:
    """The sorted frame numbers, after checking colour and depth hold the same ones."""
    if not depth:
        raise DatasetError(f"{depth_where}: no depth images found")
    if not colour:
        raise DatasetError(f"{colour_where}: no colour images found")
    if colour.keys() != depth.keys():
        no_depth = sorted(colour.keys() - depth.keys())
        no_colour = sorted(depth.keys() - colour.keys())
        parts = []
        if no_depth:
            parts.append(
                f"{len(no_depth)} colour frames have no depth in {depth_where} "
                f"(first missing index {no_depth[0]})"
            )
        if no_colour:
            parts.append(
                f"{len(no_colour)} depth frames have no colour in {colour_where} "
                f"(first missing index {no_colour[0]})"
            )
        raise DatasetError(
            f"colour/depth counts disagree ({len(colour)} vs {len(depth)}): " + "; ".join(parts)
        )
    return sorted(colour)


def nearest_within(query: np.ndarray, stamps: np.ndarray, max_dt: float) -> np.ndarray:
    """For each query time, the index of the nearest of `stamps` (any order), or -1 when that
    is farther than `max_dt` seconds. Several queries may get the same index."""
    stamps = np.asarray(stamps, dtype=np.float64)
    query = np.asarray(query, dtype=np.float64)
    if len(stamps) == 0:
        return np.full(len(query), -1, dtype=np.int64)
    order = np.argsort(stamps, kind="stable")
    ordered = stamps[order]
    k = np.searchsorted(ordered, query)
    before = np.clip(k - 1, 0, len(ordered) - 1)
    after = np.clip(k, 0, len(ordered) - 1)
    best = np.where(np.abs(ordered[before] - query) <= np.abs(ordered[after] - query), before,
                    after)
    return np.where(np.abs(ordered[best] - query) <= max_dt, order[best], -1)


def _size(img: np.ndarray) -> str:
    return f"{img.shape[1]}x{img.shape[0]}"


def _slice_text(frames: slice | str) -> str:
    if isinstance(frames, str):
        return frames
    parts = ["" if v is None else str(v) for v in (frames.start, frames.stop, frames.step)]
    return ":".join(parts[:2] if frames.step is None else parts)

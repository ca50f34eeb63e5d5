"""Trajectories in the TUM format: ``timestamp tx ty tz qx qy qz qw`` per line.

Poses are camera poses ``T_world_cam`` (4x4 float64); quaternions are xyzw. Files written here
are readable by evo and by the TUM RGB-D benchmark tools.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cpslam.common.durable import write_text_atomic
from cpslam.common.geometry import is_rigid, pose_from_tq, pose_to_tq

__all__ = [
    "TUM_HEADER",
    "Trajectory",
    "TrajectoryFormatError",
    "read_tum",
    "sensor_seconds",
    "write_tum",
]

logger = logging.getLogger(__name__)

TUM_HEADER = "# timestamp tx ty tz qx qy qz qw"

# Accepted deviation of a stored quaternion's norm from 1; files written with few decimals
# are a little off, a larger deviation means the line is not a rotation at all.
_QUAT_NORM_TOL = 1e-3


def sensor_seconds(stamps: Iterable[float]) -> float | None:
    """Sensor time (s) the frames with these stamps cover: first to last plus one median
    frame period (100 frames of a 10 Hz stream are 10 s); None for fewer than two frames."""
    t = np.unique(np.asarray(list(stamps), np.float64))
    if len(t) < 2:
        return None
    return float(t[-1] - t[0] + np.median(np.diff(t)))


class TrajectoryFormatError(ValueError):
    """A trajectory file that does not follow the TUM format (message names path and line)."""


@dataclass
class Trajectory:
    """Timestamps ``stamps [N]`` (seconds, strictly increasing) and poses ``[N, 4, 4]``."""

    stamps: np.ndarray
    poses: np.ndarray

    def __post_init__(self) -> None:
        self.stamps, self.poses = _check_arrays(self.stamps, self.poses)

    def __len__(self) -> int:
        return len(self.stamps)

    @classmethod
    def read(cls, path: str | Path) -> Trajectory:
        """Read a TUM file (see ``read_tum``)."""
        return cls(*read_tum(path))

    def write(self, path: str | Path) -> None:
        """Write as a TUM file (see ``write_tum``)."""
        write_tum(path, self.stamps, self.poses)

    @property
    def positions(self) -> np.ndarray:
        """Camera centres ``[N, 3]`` in the world frame."""
        return self.poses[:, :3, 3].copy()


def write_tum(path: str | Path, stamps: np.ndarray, T_world_cam: np.ndarray) -> None:
    """Write poses as a TUM trajectory file (parent folders are created).

    Stamps are written with 6 decimals (microseconds), translations and quaternions with 9.

    Raises:
        ValueError: if there are no poses, shapes disagree, stamps are not strictly
            increasing, or a pose is not rigid.
    """
    stamps, T_world_cam = _check_arrays(stamps, T_world_cam)
    if len(stamps) == 0:
        raise ValueError(f"write_tum: no poses to write to {path}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    t, q = pose_to_tq(T_world_cam)
    lines = [TUM_HEADER]
    for stamp, ti, qi in zip(stamps, t, q, strict=True):
        numbers = " ".join(f"{x:.9f}" for x in (*ti, *qi))
        lines.append(f"{stamp:.6f} {numbers}")
    write_text_atomic(path, "\n".join(lines) + "\n")
    logger.debug("wrote %d poses to %s", len(stamps), path)


def read_tum(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM trajectory file into ``(stamps [N] float64, T_world_cam [N, 4, 4])``.

    Blank lines and lines starting with ``#`` are skipped; fields may be separated by spaces,
    tabs or commas. Poses keep the file order.

    Raises:
        FileNotFoundError: if the file does not exist.
        TrajectoryFormatError: naming the path and line number, for a wrong number of fields,
            a field that is not a finite number, a zero-norm or non-unit quaternion, stamps
            that are not strictly increasing, or a file without poses.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"trajectory file not found: {path}")
    stamps: list[float] = []
    rows: list[list[float]] = []
    for lineno, raw in enumerate(path.read_text().splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        where = f"{path}:{lineno}"
        fields = line.replace(",", " ").split()
        if len(fields) != 8:
            raise TrajectoryFormatError(
                f"{where}: expected 8 fields 'timestamp tx ty tz qx qy qz qw', got {len(fields)}"
            )
        try:
            values = [float(f) for f in fields]
        except ValueError:
            raise TrajectoryFormatError(f"{where}: fields must be numbers, got {line!r}") from None
        if not all(np.isfinite(values)):
            raise TrajectoryFormatError(f"{where}: fields must be finite, got {line!r}")
        norm = float(np.linalg.norm(values[4:]))
        if norm < 1e-12:
            raise TrajectoryFormatError(f"{where}: zero-norm quaternion")
        if abs(norm - 1.0) > _QUAT_NORM_TOL:
            raise TrajectoryFormatError(
                f"{where}: quaternion norm {norm:.6f} is not 1 (not a rotation)"
            )
        if stamps and values[0] <= stamps[-1]:
            raise TrajectoryFormatError(
                f"{where}: timestamp {values[0]:.6f} is not after the previous {stamps[-1]:.6f}"
            )
        stamps.append(values[0])
        rows.append(values[1:])
    if not rows:
        raise TrajectoryFormatError(f"{path}: no poses in trajectory file")
    data = np.asarray(rows, dtype=np.float64)
    return np.asarray(stamps, dtype=np.float64), pose_from_tq(data[:, :3], data[:, 3:])


def _check_arrays(stamps: np.ndarray, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    stamps = np.asarray(stamps, dtype=np.float64)
    poses = np.asarray(poses, dtype=np.float64)
    if stamps.ndim != 1:
        raise ValueError(f"trajectory: expected stamps of shape [N], got {stamps.shape}")
    if poses.shape != (len(stamps), 4, 4):
        raise ValueError(
            f"trajectory: expected poses of shape ({len(stamps)}, 4, 4), got {poses.shape}"
        )
    if not np.all(np.isfinite(stamps)) or np.any(np.diff(stamps) <= 0.0):
        raise ValueError("trajectory: stamps must be finite and strictly increasing")
    if not is_rigid(poses, tol=1e-4):
        bad = [i for i in range(len(poses)) if not is_rigid(poses[i], tol=1e-4)]
        raise ValueError(f"trajectory: poses at index {bad[:5]} are not rigid transforms")
    return stamps, poses

"""Where a trajectory to evaluate comes from: a TUM file, a run folder or a dataset folder.

- a file: read as TUM (``timestamp tx ty tz qx qy qz qw``), unless it is a bag (``.bag``,
  ``.mcap``, ``.db3``), which is a dataset (its pose topic is the ground truth);
- a folder holding ``trajectory.tum`` at its top, or exactly one ``agent_*/trajectory.tum``
  (a cpslam run); several agents' files are an error that lists them;
- otherwise a dataset folder: its timestamps and ground-truth poses, read through
  ``cpslam.common.datasets.open_sequence`` (images are not loaded); a format and a frame
  selection ``START:STOP[:STEP]`` may be given, as for every command that reads a sequence.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from cpslam.common.geometry import is_rigid, project_to_rigid
from cpslam.common.trajectory import Trajectory, read_tum

logger = logging.getLogger(__name__)

TRAJECTORY_NAME = "trajectory.tum"

# How far from orthonormal a dataset's ground-truth rotation may be and still be accepted.
_GT_RIGID_TOL = 1e-2


def load_trajectory(
    path: str | Path, fmt: str | None = None, frames: slice | str | None = None
) -> Trajectory:
    """Trajectory from a TUM file, a run folder or a dataset folder (see module docstring).

    ``fmt`` (a dataset format name; None detects it) and ``frames`` (a slice or
    "START:STOP[:STEP]") apply to dataset folders only: selected frames keep their own
    timestamps, so they still associate with the full estimate or ground truth.

    Raises FileNotFoundError when the path does not exist and ValueError, naming the path,
    when it holds no usable trajectory or when ``fmt``/``frames`` are given for a TUM file.
    """
    kind, resolved = locate_trajectory(path)
    if kind == "tum":
        if fmt is not None or frames is not None:
            # Refused rather than ignored: a selection that silently does nothing would give
            # an ATE over other frames than the caller asked for.
            raise ValueError(
                f"{resolved}: a format or frame selection applies to dataset folders, "
                "not to TUM trajectory files"
            )
        return Trajectory(*read_tum(resolved))
    stamps, poses = _dataset_trajectory(resolved, fmt, frames)
    if len(stamps) == 0:
        raise ValueError(f"{resolved}: dataset has no frames with ground-truth poses")
    try:
        return Trajectory(stamps, poses)
    except ValueError as exc:
        raise ValueError(f"{resolved}: {exc}") from exc


def locate_trajectory(path: str | Path) -> tuple[str, Path]:
    """``("tum", file)`` or ``("dataset", folder or bag)`` for what ``path`` names."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such file or folder")
    if path.is_file():
        from cpslam.common.datasets.bag import SUFFIXES as BAG_SUFFIXES

        return ("dataset" if path.suffix.lower() in BAG_SUFFIXES else "tum"), path
    top = path / TRAJECTORY_NAME
    if top.is_file():
        return "tum", top
    agents = sorted(p for p in path.glob(f"agent_*/{TRAJECTORY_NAME}") if p.is_file())
    if len(agents) == 1:
        return "tum", agents[0]
    if len(agents) > 1:
        listing = ", ".join(str(p) for p in agents)
        raise ValueError(
            f"{path}: holds {len(agents)} agent trajectories ({listing}); pass one of them"
        )
    return "dataset", path


def _dataset_trajectory(
    folder: Path, fmt: str | None, frames: slice | str | None
) -> tuple[np.ndarray, np.ndarray]:
    # Imported here: the dataset readers pull in image libraries that a TUM-only
    # evaluation does not need.
    from cpslam.common.datasets import open_sequence

    try:
        sequence = open_sequence(folder, fmt=fmt, frames=frames)
    except (ValueError, FileNotFoundError) as exc:
        if fmt is not None or frames is not None:
            raise  # the caller meant a dataset: the loader's message says what is wrong
        raise ValueError(
            f"{folder}: neither a {TRAJECTORY_NAME} (at the top or in agent_*/) nor a readable "
            f"dataset folder ({exc})"
        ) from exc
    poses = sequence.gt_poses()
    if poses is None:
        raise ValueError(f"{folder}: dataset ({sequence.format}) has no ground-truth poses")
    stamps = np.asarray(sequence.timestamps, np.float64)
    poses = np.asarray(poses, np.float64)
    # Some datasets mark frames without ground truth by non-finite poses; skip those frames.
    valid = np.isfinite(poses).all(axis=(1, 2))
    if not valid.all():
        logger.warning("%s: %d frames without ground truth skipped", folder, (~valid).sum())
    logger.info("%s: %s dataset, %d ground-truth poses", folder, sequence.format, valid.sum())
    stamps, poses = stamps[valid], poses[valid]
    # Ground truth stored as text matrices (7-Scenes: rotations off orthonormal by ~2e-4) is
    # snapped to the nearest rotation; anything far from rigid is still refused below.
    if len(poses) and is_rigid(poses, tol=_GT_RIGID_TOL):
        poses = project_to_rigid(poses)
    return stamps, poses

"""Pose graphs as g2o text files (``VERTEX_SE3:QUAT`` / ``EDGE_SE3:QUAT``).

gtsam's own ``writeG2o`` refuses robust-wrapped factors and prints six significant digits, so
the pose graph is written here; ``gtsam.readG2o(path, is3D=True)`` and g2o read it back.

Format (one record per line, ``#`` lines are comments):

- ``VERTEX_SE3:QUAT id x y z qx qy qz qw``: node pose ``T_world_node``.
- ``EDGE_SE3:QUAT id_a id_b x y z qx qy qz qw I11 I12 .. I16 I22 .. I66``: measurement
  ``T_a_b`` and the upper triangle (21 values, row by row) of its information matrix, in the
  g2o order translation then rotation.
- ``FIX id``: a node held at its pose (our gauge anchors).
- ``# NODE id agent kind index``: what each vertex is (kind ``kf`` or ``frame``).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from cpslam.common.durable import write_text_atomic
from cpslam.common.geometry import pose_to_tq

__all__ = ["write_g2o"]

Edge = tuple[int, int, np.ndarray, np.ndarray]
"""``(id_a, id_b, T_a_b [4, 4], information [6, 6] translation first)``."""


def write_g2o(
    path: str | Path,
    poses: Sequence[np.ndarray],
    edges: Sequence[Edge],
    fixed: Sequence[int] = (),
    names: Sequence[str] | None = None,
) -> None:
    """Write vertices ``0 .. len(poses) - 1`` with ``poses[i] = T_world_node`` and the edges.

    Numbers are written with 17 significant digits, so a read-back is exact to float64.
    ``names[i]``, if given, goes into a ``# NODE`` comment for vertex i.
    """
    n = len(poses)
    if names is not None and len(names) != n:
        raise ValueError(f"write_g2o: {len(names)} names for {n} poses")
    for a, b, _, info in edges:
        if not (0 <= a < n and 0 <= b < n):
            raise ValueError(f"write_g2o: edge {a} -> {b} names a vertex outside 0..{n - 1}")
        if np.shape(info) != (6, 6):
            raise ValueError(f"write_g2o: edge {a} -> {b} information has shape {np.shape(info)}")
    lines = [f"# cpslam pose graph: {n} vertices, {len(edges)} edges"]
    if names is not None:
        lines += [f"# NODE {i} {name}" for i, name in enumerate(names)]
    for i, T in enumerate(poses):
        lines.append(f"VERTEX_SE3:QUAT {i} {_tq(T)}")
    upper = np.triu_indices(6)
    for a, b, T_a_b, info in edges:
        values = " ".join(_num(v) for v in np.asarray(info, dtype=np.float64)[upper])
        lines.append(f"EDGE_SE3:QUAT {a} {b} {_tq(T_a_b)} {values}")
    lines += [f"FIX {i}" for i in fixed]
    write_text_atomic(path, "\n".join(lines) + "\n")


def _tq(T: np.ndarray) -> str:
    t, q = pose_to_tq(np.asarray(T, dtype=np.float64))
    return " ".join(_num(v) for v in (*t, *q))


def _num(v: float) -> str:
    return f"{float(v):.17g}"

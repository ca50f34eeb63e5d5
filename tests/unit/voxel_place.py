"""A place descriptor for back-end tests that need no image network: the world voxels a view
sees, hashed into a bag (it reads the view's true pose, which only tests may do)."""

from __future__ import annotations

import numpy as np


def voxel_descriptor(depth, intr, T_world_cam, dim=512, voxel=0.5):
    """Bag of the world voxels the view sees (hashed, square-rooted, normalised)."""
    v, u = np.nonzero(depth > 0)
    z = depth[v, u]
    xyz = np.stack(((u - intr.cx) / intr.fx * z, (v - intr.cy) / intr.fy * z, z), 1)
    xyz = xyz @ T_world_cam[:3, :3].T + T_world_cam[:3, 3]
    cells = np.floor(xyz / voxel).astype(np.int64)
    bins = (cells * np.array([73856093, 19349663, 83492791])).sum(1) % dim
    d = np.sqrt(np.bincount(bins, minlength=dim).astype(np.float32))
    return d / np.linalg.norm(d)

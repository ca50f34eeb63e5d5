"""New points from one RGB-D frame: the centre pixel of every patch, back-projected."""

from __future__ import annotations

import numpy as np
import torch

from cpslam.common.camera import Intrinsics
from cpslam.common.field.decoders import FeatureCNN


def patch_points(
    rgb: np.ndarray,
    depth: np.ndarray,
    intrinsics: Intrinsics,
    T_world_cam: np.ndarray | torch.Tensor,
    cnn: FeatureCNN,
    patch: int = 4,
    max_depth: float | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Candidate points of a frame, one per `patch` x `patch` block with a valid depth.

    rgb uint8 [H, W, 3], depth float32 [H, W] metres (0 = invalid), T_world_cam [4, 4].
    Pixels deeper than `max_depth` are skipped when it is given.
    Returns xyz_world float32 [M, 3], features float32 [M, F] (from `cnn` over the whole
    image) and colors uint8 [M, 3], on the CNN's device, ready for `NeuralPointMap.add_points`.
    """
    height, width = depth.shape
    if rgb.shape != (height, width, 3) or (height, width) != (intrinsics.height, intrinsics.width):
        raise ValueError(f"patch_points: rgb {rgb.shape} and depth {depth.shape} must match the "
                         f"intrinsics' {intrinsics.height}x{intrinsics.width}")
    if patch < 1:
        raise ValueError(f"patch_points: patch must be >= 1, got {patch}")
    v, u = np.mgrid[patch // 2 : height : patch, patch // 2 : width : patch]
    v, u = v.ravel(), u.ravel()
    z = depth[v, u].astype(np.float64)
    ok = np.isfinite(z) & (z > 0)
    if max_depth is not None:
        ok &= z <= max_depth
    v, u, z = v[ok], u[ok], z[ok]
    xyz_cam = intrinsics.pixel_rays(u, v) * z[:, None]
    T = np.asarray(torch.as_tensor(T_world_cam).detach().cpu(), dtype=np.float64)
    xyz_world = xyz_cam @ T[:3, :3].T + T[:3, 3]
    device = cnn.conv.weight.device
    features = cnn.at_pixels(rgb, torch.from_numpy(u), torch.from_numpy(v))
    colors = torch.from_numpy(np.ascontiguousarray(rgb[v, u])).to(device)
    return torch.from_numpy(xyz_world).float().to(device), features, colors

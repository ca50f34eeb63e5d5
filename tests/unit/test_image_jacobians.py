"""rendered_jacobians: the image-gradient Jacobians of a view's depth and luminance agree with
finite differences of the view rendered at moved poses (all six directions of xi)."""

from __future__ import annotations

import numpy as np
import torch
from test_tracker import _box_view, _look_at_corner

from cpslam.common.camera import Intrinsics
from cpslam.common.field.image_terms import rendered_jacobians
from cpslam.common.geometry import se3_exp


def _smooth_view(T_world_cam: np.ndarray, intr: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
    """The box's depth with a smooth texture (the box's own stripes have no derivative)."""
    _, depth = _box_view(T_world_cam, intr)
    v, u = np.mgrid[0 : intr.height, 0 : intr.width]
    x_cam = np.stack(((u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, np.ones(u.shape)), -1)
    x = (depth[..., None] * x_cam) @ T_world_cam[:3, :3].T + T_world_cam[:3, 3]
    gray = 0.5 + 0.2 * np.sin(4 * x[..., 0] + 3 * x[..., 2]) * np.cos(5 * x[..., 1] - x[..., 2])
    return np.repeat(gray[..., None], 3, -1), depth


def test_image_jacobians_match_finite_differences_of_the_view() -> None:
    intr = Intrinsics(fx=128.0, fy=128.0, cx=79.5, cy=59.5, width=160, height=120)
    T = _look_at_corner(np.zeros(3))
    rgb, depth = _smooth_view(T, intr)
    v, u = torch.meshgrid(torch.arange(4, 116, 3), torch.arange(4, 156, 3), indexing="ij")
    u, v = u.reshape(-1), v.reshape(-1)
    J_depth, J_gray = rendered_jacobians(torch.from_numpy(rgb).float(),
                                         torch.from_numpy(depth), u, v,
                                         (intr.fx, intr.fy, intr.cx, intr.cy))
    h = 1e-3
    for i in range(6):
        xi = np.zeros(6)
        xi[i] = h
        rgb_m, depth_m = _smooth_view(T @ se3_exp(xi), intr)
        rgb_p, depth_p = _smooth_view(T @ se3_exp(-xi), intr)
        fd_depth = torch.from_numpy((depth_m - depth_p) / (2 * h)).double()[v, u]
        gray_m, gray_p = rgb_m.mean(-1), rgb_p.mean(-1)
        fd_gray = torch.from_numpy((gray_m - gray_p) / (2 * h))[v, u]
        for name, fd, J in (("depth", fd_depth, J_depth[:, i]), ("gray", fd_gray, J_gray[:, i])):
            # Measured: cosines 0.990-0.9998, norm ratios 0.980-1.000 (the smoothing and the
            # box's edges account for the rest).
            cos = float((fd * J).sum() / (fd.norm() * J.norm()))
            assert cos > 0.97, (name, i, cos)
            assert 0.94 < float(J.norm() / fd.norm()) < 1.03, (name, i)

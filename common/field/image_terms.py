"""Residuals of a frame against a reference RGB-D image (the latest keyframe), for tracking.

The neural map renders depth and colour smoothly: its fit, not the camera, limits how
precisely a frame can be placed against it, and a first-frame map fitted for 600 steps was
still biased by millimetres. The keyframe's own images are sharp. Each pixel p of the frame
with depth D_p is back-projected (X = D_p K^-1 p), moved into the reference camera by the
relative pose (X_ref = T_world_ref^-1 T_world_cam X) and projected to u' there; its residuals
are the luminance difference I_ref(u') - I(p) and the depth difference D_ref(u') - z(X_ref),
both with analytic Jacobians through bilinear interpolation of the reference images and of
their gradients. Pixels that leave the reference image, land on its invalid depth, or differ
in depth by more than `max_depth_gap` (an occlusion) are left out.

Everything is torch on the map's device with no autograd; the Jacobians are with respect to
a right increment xi (translation first, camera frame) of T_world_cam, as in `pose_lm`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

__all__ = ["ReferenceImage", "image_residuals"]


@dataclass
class ReferenceImage:
    """A reference RGB-D view: gray float32 [H, W] in [0, 1], depth float32 [H, W] metres
    (0 = invalid), their x/y gradients (per pixel), pose T_world_ref [4, 4] float64 and
    intrinsics (fx, fy, cx, cy) of the same size as the frames it is compared with; weight
    scales its terms against the other views'."""

    gray: torch.Tensor
    depth: torch.Tensor
    grad_gray: torch.Tensor  # [2, H, W]: d/du, d/dv
    grad_depth: torch.Tensor  # [2, H, W]
    T_world_ref: np.ndarray
    camera: tuple[float, float, float, float]
    weight: float = 1.0

    @classmethod
    def from_rgbd(cls, rgb: torch.Tensor, depth: torch.Tensor, T_world_ref: np.ndarray,
                  camera: tuple[float, float, float, float],
                  weight: float = 1.0) -> ReferenceImage:
        """rgb float [H, W, 3] in [0, 1] (or uint8), depth float [H, W] metres."""
        rgb = rgb.float() / 255.0 if rgb.dtype == torch.uint8 else rgb.float()
        gray = _smooth(rgb.mean(-1))
        depth = depth.float()
        return cls(gray, depth, _gradient(gray), _gradient_valid(depth),
                   np.asarray(T_world_ref, dtype=np.float64), camera, weight)


def image_residuals(
    ref: ReferenceImage,
    T_world_cam: np.ndarray,
    xyz_cam: torch.Tensor,
    gray_obs: torch.Tensor,
    max_depth_gap: float = 0.1,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Luminance and depth residuals of the frame's points against the reference.

    xyz_cam: [P, 3] the frame's back-projected pixels (camera frame, float64); gray_obs: [P]
    their luminance. Returns r_gray [P], J_gray [P, 6], r_depth [P], J_depth [P, 6] (float64)
    and valid [P] bool (residuals and Jacobians are 0 where not valid).
    """
    device = xyz_cam.device
    T_rel = torch.as_tensor(np.linalg.inv(ref.T_world_ref) @ T_world_cam, device=device)
    R, t = T_rel[:3, :3], T_rel[:3, 3]
    X = xyz_cam @ R.T + t  # [P, 3] in the reference camera
    fx, fy, cx, cy = ref.camera
    z = X[:, 2]
    front = z > 1e-3
    zs = torch.where(front, z, torch.ones_like(z))
    u = fx * X[:, 0] / zs + cx
    v = fy * X[:, 1] / zs + cy
    height, width = ref.depth.shape
    inside = front & (u >= 0) & (u <= width - 1.001) & (v >= 0) & (v <= height - 1.001)
    samples = _bilinear(torch.stack((ref.gray, ref.depth, *ref.grad_gray, *ref.grad_depth)),
                        u.clamp(0, width - 1.001), v.clamp(0, height - 1.001))
    gray, depth, gu, gv, du, dv = samples.double()
    # A bilinear depth sample mixing an invalid 0 is invalid: compare with the nearest sample.
    valid = inside & (depth > 0) & (_nearest(ref.depth, u, v) > 0) \
        & ((depth - z).abs() < max_depth_gap)
    # dX_ref / dxi for T_world_cam exp(xi): R [I, -[x]x] with x the point in the frame.
    dX = torch.zeros(len(X), 3, 6, dtype=torch.float64, device=device)
    dX[:, :, :3] = R
    dX[:, :, 3:] = -R @ _skew(xyz_cam)
    d_uv = torch.zeros(len(X), 2, 3, dtype=torch.float64, device=device)
    d_uv[:, 0, 0], d_uv[:, 0, 2] = fx / zs, -fx * X[:, 0] / zs**2
    d_uv[:, 1, 1], d_uv[:, 1, 2] = fy / zs, -fy * X[:, 1] / zs**2
    J_uv = d_uv @ dX  # [P, 2, 6]
    J_gray = gu[:, None] * J_uv[:, 0] + gv[:, None] * J_uv[:, 1]
    J_depth = du[:, None] * J_uv[:, 0] + dv[:, None] * J_uv[:, 1] - dX[:, 2]
    r_gray = torch.where(valid, gray - gray_obs.double(), 0.0)
    r_depth = torch.where(valid, depth - z, 0.0)
    zero = ~valid[:, None]
    return (r_gray, J_gray.masked_fill(zero, 0.0), r_depth, J_depth.masked_fill(zero, 0.0),
            valid)


def _bilinear(images: torch.Tensor, u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """images [C, H, W] at float pixel positions u, v [P] (inside): [C, P]."""
    u0, v0 = u.floor().long(), v.floor().long()
    a, b = (u - u0).to(images.dtype), (v - v0).to(images.dtype)
    top = images[:, v0, u0] * (1 - a) + images[:, v0, u0 + 1] * a
    bottom = images[:, v0 + 1, u0] * (1 - a) + images[:, v0 + 1, u0 + 1] * a
    return top * (1 - b) + bottom * b


def _nearest(image: torch.Tensor, u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    height, width = image.shape
    ui = u.round().long().clamp(0, width - 1)
    vi = v.round().long().clamp(0, height - 1)
    return image[vi, ui].double()


def _smooth(image: torch.Tensor) -> torch.Tensor:
    """3x3 binomial blur: wider basin, less aliasing of the gradient."""
    kernel = torch.tensor([1.0, 2.0, 1.0], device=image.device) / 4.0
    padded = torch.nn.functional.pad(image[None, None], (1, 1, 1, 1), mode="replicate")
    out = torch.nn.functional.conv2d(padded, kernel.view(1, 1, 1, 3))
    return torch.nn.functional.conv2d(out, kernel.view(1, 1, 3, 1))[0, 0]


def _gradient(image: torch.Tensor) -> torch.Tensor:
    """Central differences [2, H, W] (d/du, d/dv), one-sided at the border."""
    gu = torch.zeros_like(image)
    gv = torch.zeros_like(image)
    gu[:, 1:-1] = 0.5 * (image[:, 2:] - image[:, :-2])
    gv[1:-1] = 0.5 * (image[2:] - image[:-2])
    return torch.stack((gu, gv))


def _gradient_valid(depth: torch.Tensor) -> torch.Tensor:
    """Depth gradient where both neighbours are valid, 0 elsewhere (no jump to an invalid 0)."""
    grad = _gradient(depth)
    ok = depth > 0
    ok_u = torch.zeros_like(ok)
    ok_v = torch.zeros_like(ok)
    ok_u[:, 1:-1] = ok[:, 2:] & ok[:, :-2]
    ok_v[1:-1] = ok[2:] & ok[:-2]
    return torch.stack((grad[0] * ok_u, grad[1] * ok_v))


def _skew(x: torch.Tensor) -> torch.Tensor:
    """[P, 3] -> [P, 3, 3] cross-product matrices."""
    out = torch.zeros(len(x), 3, 3, dtype=x.dtype, device=x.device)
    out[:, 0, 1], out[:, 0, 2] = -x[:, 2], x[:, 1]
    out[:, 1, 0], out[:, 1, 2] = x[:, 2], -x[:, 0]
    out[:, 2, 0], out[:, 2, 1] = -x[:, 1], x[:, 0]
    return out

"""Mapping: grow the neural point map where a frame is not yet explained, then optimise point
features and decoders on pixels of the current frame and its co-visible keyframes.

New points come from the centre pixel of every patch (`field.patch_size`), back-projected with
the frame's pose; a candidate is kept when the map does not explain it yet (no existing point
within the search radius, or, with `add_points_depth_err`, a rendered depth off by more than
that), and the map's grid filter then keeps at most one point per cell. Features of new points
come from the untrained CNN, colours from the image.

The optimisation runs Adam over the decoders and over the features of the points that can be
seen from the views taking part (points elsewhere keep their features and get no optimiser
state); the feature learning rate decays as lr * decay ** (step / decay_steps) from the start
of every call, as in the paper. The loss is the depth L1 plus colour_weight times the colour
L1 (mean over pixels and channels, colours in [0, 1]) on pixels with valid depth, drawn afresh
at every step and shared equally among the views. With a pose rate (`mapping.pose_lr`) the
first view's pose (the current frame) is optimised jointly, by its own Adam group; the
keyframes' poses stay fixed and anchor the map, so the map cannot simply bend to the frame.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from cpslam.common.camera import Intrinsics
from cpslam.common.field import (
    Decoders,
    FeatureCNN,
    FieldSpec,
    NeuralPointMap,
    camera_rays,
    patch_points,
    render_rays,
)
from cpslam.common.geometry_torch import torch_se3_exp

logger = logging.getLogger(__name__)

__all__ = ["MapResult", "Mapper", "View"]


@dataclass
class View:
    """One image taking part in mapping: the current frame or a keyframe's small copy.

    rgb: float32 [h, w, 3] in [0, 1]; depth: float32 [h, w] metres (0 = invalid), both on the
    map's device; T_world_cam: [4, 4] float64; intrinsics: of this image's size.
    """

    rgb: torch.Tensor
    depth: torch.Tensor
    T_world_cam: np.ndarray
    intrinsics: Intrinsics

    def __post_init__(self) -> None:
        if tuple(self.depth.shape) != self.intrinsics.shape or \
                tuple(self.rgb.shape) != (*self.intrinsics.shape, 3):
            raise ValueError(f"View: rgb {tuple(self.rgb.shape)} / depth "
                             f"{tuple(self.depth.shape)} do not match the intrinsics' "
                             f"{self.intrinsics.shape}")
        self.valid = (self.depth.reshape(-1) > 0).nonzero(as_tuple=True)[0]


@dataclass
class MapResult:
    """One optimisation call: steps run, loss of the first and last step, seconds, and the
    first view's refined pose ([4, 4] float64; None when its pose was not optimised)."""

    steps: int
    loss_first: float
    loss_last: float
    seconds: float
    T_world_cam: np.ndarray | None = None


class Mapper:
    """Point insertion and feature/decoder optimisation.

    Args:
        spec: the field (ray sampler, patch size of new points, neighbours per sample, search
            radius and backend, rays per rendering pass).
        lr_decoders, lr_features: Adam learning rates.
        feature_lr_decay, feature_lr_decay_steps: feature lr decay (reset every call).
        color_weight: weight of the colour L1 term.
        add_points_depth_err: None = add where no point is within radius; a number = add where
            the rendered depth is off by more than this (m).
        pose_average: the refined pose is T_world_cam @ exp(mean xi) over this last share of
            the steps (0 = the last step's xi); the last step's pose put mapping frames
            further off than the frames around them (docs/performance.md).
    """

    def __init__(
        self,
        spec: FieldSpec,
        *,
        lr_decoders: float,
        lr_features: float,
        feature_lr_decay: float,
        feature_lr_decay_steps: int,
        color_weight: float,
        add_points_depth_err: float | None,
        pose_average: float,
    ) -> None:
        self.spec = spec
        self.sampler = spec.sampler()
        self.lr_decoders, self.lr_features = lr_decoders, lr_features
        self.feature_lr_decay = feature_lr_decay
        self.feature_lr_decay_steps = feature_lr_decay_steps
        self.color_weight = color_weight
        self.patch_size = spec.patch_size
        self.add_points_depth_err = add_points_depth_err
        self.pose_average = pose_average
        self.k, self.radius = spec.k_neighbors, spec.radius
        self.backend, self.chunk = spec.neighbour_backend, spec.chunk_rays

    # --------------------------------------------------------------------------- new points

    def add_points(
        self,
        point_map: NeuralPointMap,
        decoders: Decoders,
        cnn: FeatureCNN,
        rgb: np.ndarray,
        depth: np.ndarray,
        intrinsics: Intrinsics,
        T_world_cam: np.ndarray,
        anchor_kf: int,
        generator: torch.Generator | None = None,
    ) -> torch.Tensor:
        """Add the frame's unexplained patch centres, anchored to keyframe `anchor_kf` (already
        in the map's pose table). rgb uint8 [H, W, 3], depth float32 [H, W]. Returns the ids of
        the points added, int64 [M]."""
        xyz, features, colors = patch_points(rgb, depth, intrinsics, T_world_cam, cnn,
                                             patch=self.patch_size)
        if len(xyz) and len(point_map):
            keep = self._unexplained(point_map, decoders, xyz, intrinsics, T_world_cam,
                                     generator)
            xyz, features, colors = xyz[keep], features[keep], colors[keep]
        return point_map.add_points(xyz, anchor_kf, features, colors)

    @torch.no_grad()
    def _unexplained(
        self,
        point_map: NeuralPointMap,
        decoders: Decoders,
        xyz_world: torch.Tensor,
        intrinsics: Intrinsics,
        T_world_cam: np.ndarray,
        generator: torch.Generator | None,
    ) -> torch.Tensor:
        """bool [M]: candidates the map does not explain yet."""
        index = point_map.neighbour_index(self.backend)
        if self.add_points_depth_err is None:
            return index.query(xyz_world, 1, self.radius)[:, 0] < 0
        # Render the candidates' own pixels (projected back from their positions) and compare
        # the expected depth with the observed one.
        T = torch.as_tensor(T_world_cam, dtype=torch.float64, device=xyz_world.device)
        cam = (xyz_world.double() - T[:3, 3]) @ T[:3, :3]
        z = cam[:, 2]
        u = cam[:, 0] / z * intrinsics.fx + intrinsics.cx
        v = cam[:, 1] / z * intrinsics.fy + intrinsics.cy
        rays_o, rays_d = camera_rays(intrinsics, T, u, v)
        out = render_rays(point_map, decoders, rays_o, rays_d, z.float(), self.sampler,
                          generator, k=self.k, radius=self.radius, backend=self.backend,
                          chunk=self.chunk)
        return (out["depth"] - z.float()).abs() > self.add_points_depth_err

    # --------------------------------------------------------------------------- optimising

    def optimise(
        self,
        point_map: NeuralPointMap,
        decoders: Decoders,
        views: list[View],
        iters: int,
        n_pixels: int,
        generator: torch.Generator,
        pose_lr: float = 0.0,
        checkpoint_every: int = 0,
        checkpoint: Callable[[], None] | None = None,
        lr_scale: float = 1.0,
    ) -> MapResult:
        """Optimise features (of the points seen by `views`) and decoders for `iters` steps
        on `n_pixels` pixels per step. Returns the first and last step's loss.

        pose_lr > 0 also optimises the pose of views[0] (the current frame) as
        T_world_cam @ exp(xi), xi an se(3) increment in its camera frame, by Adam at this
        rate; the map points stay where they are while it moves, and the refined pose (xi
        averaged over the last `pose_average` share of the steps) is returned in the result
        (the view itself is left unchanged).

        lr_scale multiplies both learning rates of the map (decoders and features) for this
        call.

        checkpoint_every > 0: every this many steps (not after the last) the features so far
        are written into the map and `checkpoint()` is called, so another thread can publish
        a copy mid-way; the optimisation itself goes on unchanged."""
        start = time.perf_counter()
        refine = pose_lr > 0 and len(views) > 0 and len(views[0].valid) > 0
        views = [view for view in views if len(view.valid)]
        if iters < 1 or not views or len(point_map) == 0:
            return MapResult(0, math.nan, math.nan, time.perf_counter() - start)
        rows = self._rows_in_view(point_map, views)
        active = nn.Parameter(point_map.features.detach()[rows].clone())
        groups = [
            {"params": list(decoders.parameters()), "lr": self.lr_decoders * lr_scale},
            {"params": [active], "lr": self.lr_features * lr_scale},
        ]
        if refine:
            T0 = torch.as_tensor(views[0].T_world_cam, dtype=torch.float64,
                                 device=views[0].depth.device)
            xi = torch.zeros(6, dtype=torch.float64, device=T0.device, requires_grad=True)
            groups.append({"params": [xi], "lr": pose_lr})
        optimiser = torch.optim.Adam(groups)
        share = _split(n_pixels, len(views))
        first = last = math.nan
        average_from = min(iters - 1, int(iters * (1.0 - self.pose_average)))
        xi_sum = None
        for it in range(iters):
            decay = self.feature_lr_decay ** (it / self.feature_lr_decay_steps)
            optimiser.param_groups[1]["lr"] = lr_scale * self.lr_features * decay
            T_first = T0 @ torch_se3_exp(xi) if refine else None
            rays_o, rays_d, depth_obs, color_obs = _batch(views, share, generator, T_first)
            features = point_map.features.detach().index_copy(0, rows, active)
            out = render_rays(point_map, decoders, rays_o, rays_d, depth_obs, self.sampler,
                              generator, k=self.k, radius=self.radius, features=features,
                              backend=self.backend, chunk=self.chunk)
            loss = (out["depth"] - depth_obs).abs().mean()
            if self.color_weight > 0:
                loss = loss + self.color_weight * (out["color"] - color_obs).abs().mean()
            optimiser.zero_grad(set_to_none=True)
            loss.backward()
            optimiser.step()
            last = float(loss.detach())
            if refine and it >= average_from:
                xi_sum = xi.detach().clone() if xi_sum is None else xi_sum + xi.detach()
            if it == 0:
                first = last
            if checkpoint is not None and checkpoint_every > 0 and it + 1 < iters \
                    and (it + 1) % checkpoint_every == 0:
                point_map.set_features(rows, active)
                checkpoint()
        point_map.set_features(rows, active)
        T_refined = None
        if refine:
            with torch.no_grad():
                T_refined = (T0 @ torch_se3_exp(xi_sum / (iters - average_from))).cpu().numpy()
        seconds = time.perf_counter() - start
        logger.debug("mapping: %d steps over %d views, %d active points, loss %.4f -> %.4f "
                     "(%.2f s)", iters, len(views), len(rows), first, last, seconds)
        return MapResult(iters, first, last, seconds, T_refined)

    def _rows_in_view(self, point_map: NeuralPointMap, views: list[View]) -> torch.Tensor:
        """Rows of the points whose neighbourhood (radius) reaches into any of the views."""
        xyz = point_map.xyz_world().double()
        seen = torch.zeros(len(xyz), dtype=torch.bool, device=xyz.device)
        for view in views:
            intr = view.intrinsics
            T = torch.as_tensor(view.T_world_cam, dtype=torch.float64, device=xyz.device)
            cam = (xyz - T[:3, 3]) @ T[:3, :3]
            z = cam[:, 2]
            zs = z.clamp(min=1e-6)
            # A point up to one radius outside the frustum still shapes border pixels.
            mu = self.radius * intr.fx / zs
            mv = self.radius * intr.fy / zs
            u = intr.fx * cam[:, 0] / zs + intr.cx
            v = intr.fy * cam[:, 1] / zs + intr.cy
            seen |= (z > -self.radius) & (u > -0.5 - mu) & (u < intr.width - 0.5 + mu) \
                & (v > -0.5 - mv) & (v < intr.height - 0.5 + mv)
        return seen.nonzero(as_tuple=True)[0]


def _split(n: int, parts: int) -> list[int]:
    """n pixels shared among `parts` views as evenly as possible (the first gets the rest)."""
    base = max(1, n // parts)
    return [base + (n - base * parts if i == 0 and n > base * parts else 0)
            for i in range(parts)]


def _batch(
    views: list[View], share: list[int], generator: torch.Generator,
    T_first: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Rays, observed depth and colour of `share[i]` random valid pixels of every view
    (views[0] seen from T_first instead of its own pose when given)."""
    rays_o, rays_d, depth, color = [], [], [], []
    for i, (view, n) in enumerate(zip(views, share, strict=True)):
        pick = torch.randint(0, len(view.valid), (n,), generator=generator,
                             device=generator.device).to(view.valid.device)
        flat = view.valid[pick]
        width = view.intrinsics.width
        u, v = flat % width, flat // width
        T = T_first if T_first is not None and i == 0 else torch.as_tensor(
            view.T_world_cam, dtype=torch.float64, device=view.depth.device)
        o, d = camera_rays(view.intrinsics, T, u, v)
        rays_o.append(o)
        rays_d.append(d)
        depth.append(view.depth[v, u])
        color.append(view.rgb[v, u])
    return torch.cat(rays_o), torch.cat(rays_d), torch.cat(depth), torch.cat(color)

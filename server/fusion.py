"""Group maps: members' sub-maps fused in the group frame, points shared with the members,
and the decoders fine-tuned on the group's keyframes.

The maps are keyframe-anchored, so placing a member's sub-map in the group frame is setting
its keyframes' poses (corrected by the pose graph, or the member's alignment applied to its
own poses); no point coordinate is rewritten.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from cpslam.common.camera import Intrinsics
from cpslam.common.field import Decoders, FieldSpec, NeuralPointMap, camera_rays, render_rays
from cpslam.common.field.grid import grid_winners

__all__ = ["MemberMap", "View", "finetune_decoders", "fuse", "select_foreign"]

logger = logging.getLogger(__name__)


@dataclass
class MemberMap:
    """One member's points and keyframe poses in the group frame."""

    agent_id: str
    index: int
    point_map: NeuralPointMap
    """Sub-map whose keyframe poses are ``T_group_kf`` (agent key = index)."""


@dataclass(frozen=True)
class View:
    """A keyframe image for fine-tuning: RGB uint8 [H, W, 3], depth float32 [H, W] metres,
    camera pose in the group frame [4, 4]."""

    rgb: np.ndarray
    depth: np.ndarray
    T_group_cam: np.ndarray
    intrinsics: Intrinsics


def fuse(members: Sequence[MemberMap], feature_dim: int, cell_size: float,
         grid_filter: bool = True) -> NeuralPointMap:
    """The group map: all members' points in the group frame, one point per grid cell."""
    fused = NeuralPointMap(feature_dim, cell_size, members[0].index if members else 0)
    for m in members:
        fused.merge(m.point_map, np.eye(4), grid_filter=False)
    if grid_filter:
        removed = fused.grid_filter()
        logger.info("fused %d members: %d points (%d removed by the grid filter)",
                    len(members), len(fused), removed)
    return fused


def select_foreign(receiver: MemberMap, others: Sequence[MemberMap], cell_size: float
                   ) -> dict[str, np.ndarray]:
    """Which points of the other members the receiver needs: those in grid cells its own
    points do not occupy (one per cell). Returns source agent -> bool mask over its points."""
    own = receiver.point_map.xyz_world().double().cpu().numpy()
    xyz = [m.point_map.xyz_world().double().cpu().numpy() for m in others]
    keep = grid_winners(np.concatenate([own, *xyz]) if xyz else own, cell_size,
                        n_fixed=len(own))
    out, start = {}, len(own)
    for m, x in zip(others, xyz, strict=True):
        out[m.agent_id] = keep[start : start + len(x)]
        start += len(x)
    return out


def finetune_decoders(
    decoders: Decoders,
    point_map: NeuralPointMap,
    views: Sequence[View],
    iters: int,
    lr: float,
    seed: int,
    spec: FieldSpec,
    *,
    color_weight: float,
    lr_features: float = 0.0,
    n_pixels: int = 1024,
) -> list[float]:
    """Fine-tune `decoders` (and, with ``lr_features`` > 0, the map's features) in place on
    random pixels of the views, with the mapping loss depth L1 + color_weight * colour L1,
    rendered as the agents do (`spec`: sampler, neighbours, radius, search backend).

    Every step draws `n_pixels` pixels with valid depth spread over all views. Returns the
    loss of every step. Nothing happens (empty list) without views, points or iterations.
    """
    if iters <= 0 or not views or len(point_map) == 0:
        return []
    sampler = spec.sampler()
    device = point_map.device
    gen = torch.Generator().manual_seed(seed)
    rays = [_valid_pixels(v, device) for v in views]
    rays = [r for r in rays if r[0].shape[0] > 0]
    if not rays:
        return []
    o = torch.cat([r[0] for r in rays])
    d = torch.cat([r[1] for r in rays])
    depth = torch.cat([r[2] for r in rays])
    color = torch.cat([r[3] for r in rays])
    params = [{"params": list(decoders.parameters()), "lr": lr}]
    if lr_features > 0:
        params.append({"params": [point_map.features], "lr": lr_features})
    optimizer = torch.optim.Adam(params)
    decoders.train()
    losses = []
    for _ in range(iters):
        pick = torch.randint(0, o.shape[0], (min(n_pixels, o.shape[0]),), generator=gen,
                             device=gen.device)
        out = render_rays(point_map, decoders, o[pick], d[pick], depth[pick], sampler,
                          generator=gen, k=spec.k_neighbors, radius=spec.radius,
                          backend=spec.neighbour_backend)
        loss = (out["depth"] - depth[pick]).abs().mean() + color_weight * (
            out["color"] - color[pick]).abs().mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        losses.append(float(loss.detach()))
    decoders.eval()
    logger.info("fine-tune: %d steps on %d views, loss %.4f -> %.4f", iters, len(rays),
                losses[0], losses[-1])
    return losses


def _valid_pixels(view: View, device: torch.device
                  ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """World rays, depth and colour [0, 1] of every pixel with a valid depth."""
    depth = np.asarray(view.depth, np.float32)
    if depth.shape != (view.intrinsics.height, view.intrinsics.width):
        raise ValueError(f"fine-tune view: depth {depth.shape} does not match the intrinsics "
                         f"{view.intrinsics.height}x{view.intrinsics.width}")
    v, u = np.nonzero(np.isfinite(depth) & (depth > 0))
    T = torch.as_tensor(view.T_group_cam, dtype=torch.float64, device=device)
    o, d = camera_rays(view.intrinsics, T, torch.from_numpy(u), torch.from_numpy(v))
    z = torch.from_numpy(depth[v, u]).to(device)
    rgb = torch.from_numpy(view.rgb[v, u].astype(np.float32) / 255.0).to(device)
    return o, d, z, rgb

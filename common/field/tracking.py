"""Camera tracking against the neural point map: the pose that makes the rendered depth match
the observed one.

Per frame, `n_pixels` pixels with valid depth and their ray samples are drawn once (from the
caller's generator), so the loss is a deterministic function of the pose: keeping the
best-loss pose and early stopping compare like with like. The pose is the initial guess times
an se(3) increment `T_world_cam = T_init @ exp(xi)` (xi in the camera frame), optimised with
Adam. The loss is the L1 depth error (plus an optional colour L1) over the pixels that pass the
outlier mask, recomputed at every step from the batch medians:

- depth error e = |D - D_hat| outside [outlier_err_lo * median(e), outlier_err_hi * median(e)]
  is masked: large errors are outliers (occlusions, unmapped surfaces), and pixels that are
  already explained to a fraction of the typical error only add sign noise to an L1 gradient;
- rendered depth variance above outlier_var_factor * median(variance) is masked (the ray
  crosses an uncertain region of the map).

The map is fixed while tracking, so the neighbour search of the samples is reused across
steps until the pose has moved the farthest sample by more than `reuse_neighbours` metres
(the decoders still see exact offsets x - p_k, recomputed in torch every step).

Used by the agent (every frame against its own map) and by the server (a loop keyframe against
another agent's sub-map, `cpslam.server.refine`), so it lives with the field in `common/`.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
import torch

from cpslam.common.field.decoders import Decoders
from cpslam.common.field.points import NeuralPointMap
from cpslam.common.field.renderer import camera_rays, render_samples
from cpslam.common.field.sampler import RaySampler
from cpslam.common.geometry_torch import torch_se3_exp

if TYPE_CHECKING:
    from cpslam.common.camera import Intrinsics

logger = logging.getLogger(__name__)

_PIXEL_SAMPLING = ("uniform", "stratified")

__all__ = ["TrackResult", "Tracker", "outlier_mask", "sample_pixels"]


@dataclass
class TrackResult:
    """Outcome of tracking one frame.

    T_world_cam: [4, 4] float64 the chosen pose; iters: optimisation steps run; loss: the
    loss at the chosen pose (best or last evaluated); best_iter: step whose pose was chosen;
    losses: loss of every step (at the pose before that step's update).
    """

    T_world_cam: np.ndarray
    iters: int
    loss: float
    best_iter: int
    losses: list[float] = field(default_factory=list)


class Tracker:
    """Pose optimisation of one frame against a fixed map.

    Args:
        intrinsics: of the processed frames.
        sampler: ray sampler (the paper's near/uniform samples around the observed depth).
        iters: optimisation steps per frame.
        n_pixels: pixels with valid depth drawn per frame (M2).
        lr: Adam learning rate of the se(3) increment.
        lr_end_factor: the learning rate decays exponentially to lr * lr_end_factor at the
            last step (1 = constant, the paper).
        color_weight: weight of a colour L1 term (0 = depth only, the paper).
        err_lo, err_hi, var_factor: the outlier mask (see the module docstring).
        keep_best: return the lowest-loss pose instead of the last one.
        early_stop_tol: stop when the relative loss change of a step is below this (0 = never).
        k, radius: neighbours per sample and search radius.
        backend: neighbour search backend.
        chunk: rays per rendering pass (None = all).
        reuse_neighbours: metres the farthest sample may move before the neighbour search is
            redone (0 = search at every step).
        pixel_sampling: "uniform" (the paper: independent draws among the valid pixels) or
            "stratified" (one draw per cell of a grid over the image, see `sample_pixels`).
    """

    def __init__(
        self,
        intrinsics: Intrinsics,
        sampler: RaySampler,
        iters: int = 100,
        n_pixels: int = 1500,
        lr: float = 0.0015,
        lr_end_factor: float = 1.0,
        color_weight: float = 0.0,
        err_lo: float = 0.1,
        err_hi: float = 10.0,
        var_factor: float = 2.0,
        keep_best: bool = True,
        early_stop_tol: float = 0.0,
        k: int = 8,
        radius: float = 0.15,
        backend: str = "auto",
        chunk: int | None = None,
        reuse_neighbours: float = 0.01,
        pixel_sampling: str = "uniform",
    ) -> None:
        if iters < 1 or n_pixels < 1 or lr <= 0:
            raise ValueError(f"Tracker: need iters >= 1, n_pixels >= 1, lr > 0; got {iters}, "
                             f"{n_pixels}, {lr}")
        if not 0 < lr_end_factor <= 1:
            raise ValueError(f"Tracker: need 0 < lr_end_factor <= 1, got {lr_end_factor}")
        if not 0 <= err_lo < err_hi or var_factor <= 0:
            raise ValueError(f"Tracker: need 0 <= err_lo < err_hi and var_factor > 0, got "
                             f"{err_lo}, {err_hi}, {var_factor}")
        if pixel_sampling not in _PIXEL_SAMPLING:
            raise ValueError(f"Tracker: pixel_sampling must be one of {_PIXEL_SAMPLING}, got "
                             f"{pixel_sampling!r}")
        self.pixel_sampling = pixel_sampling
        self.intrinsics = intrinsics
        self.sampler = sampler
        self.iters = iters
        self.n_pixels = n_pixels
        self.lr = lr
        self.lr_end_factor = lr_end_factor
        self.color_weight = color_weight
        self.err_lo, self.err_hi, self.var_factor = err_lo, err_hi, var_factor
        self.keep_best = keep_best
        self.early_stop_tol = early_stop_tol
        self.k, self.radius, self.backend, self.chunk = k, radius, backend, chunk
        self.reuse_neighbours = reuse_neighbours

    def track(
        self,
        point_map: NeuralPointMap,
        decoders: Decoders,
        rgb: torch.Tensor,
        depth: torch.Tensor,
        T_init: np.ndarray,
        generator: torch.Generator,
    ) -> TrackResult:
        """Optimise the pose of one frame.

        rgb: float [H, W, 3] in [0, 1] (only read when color_weight > 0); depth: float32
        [H, W] metres, 0 = invalid; T_init: [4, 4] initial T_world_cam; generator: draws the
        pixels and sample jitter.
        """
        if tuple(depth.shape) != self.intrinsics.shape:
            raise ValueError(f"Tracker.track: depth is {tuple(depth.shape)}, the intrinsics "
                             f"say {self.intrinsics.shape}")
        if len(point_map) == 0:
            raise ValueError("Tracker.track: the map has no points to track against")
        device = point_map.device
        u, v = sample_pixels(depth, self.n_pixels, generator,
                             stratified=self.pixel_sampling == "stratified")
        depth_obs = depth[v, u]
        color_obs = rgb[v, u] if self.color_weight > 0 else None
        t = self.sampler(depth_obs, generator)
        t_far = float(t.max())
        index = point_map.neighbour_index(self.backend)
        features = point_map.features.detach()  # the map is fixed: no feature gradients

        T0 = torch.as_tensor(np.asarray(T_init, dtype=np.float64), device=device)
        xi = torch.zeros(6, dtype=torch.float64, device=device, requires_grad=True)
        optimiser = torch.optim.Adam([xi], lr=self.lr)
        decoders.requires_grad_(False)
        cached: tuple[torch.Tensor, torch.Tensor] | None = None  # (xi at search, neighbours)
        losses: list[float] = []
        best = (math.inf, xi.detach().clone(), 0)
        try:
            for it in range(self.iters):
                optimiser.param_groups[0]["lr"] = self.lr * self.lr_end_factor ** (
                    it / max(self.iters - 1, 1))
                T = T0 @ torch_se3_exp(xi)
                rays_o, rays_d = camera_rays(self.intrinsics, T, u, v)
                if cached is None or _motion_bound(xi.detach() - cached[0], t_far) \
                        > self.reuse_neighbours:
                    x = rays_o[:, None, :] + t[..., None] * rays_d[:, None, :]
                    cached = (xi.detach().clone(), index.query(x.detach().reshape(-1, 3),
                                                               self.k, self.radius))
                out = render_samples(point_map, decoders, rays_o, rays_d, t, self.k,
                                     self.radius, features=features, backend=self.backend,
                                     chunk=self.chunk, neighbours=cached[1],
                                     color=color_obs is not None)
                err = (out["depth"] - depth_obs).abs()
                mask = outlier_mask(err.detach(), out["var"].detach(), self.err_lo,
                                    self.err_hi, self.var_factor)
                if not bool(mask.any()):
                    logger.debug("tracking: every pixel masked at step %d, stopping", it)
                    break
                loss = err[mask].mean()
                if color_obs is not None:
                    loss = loss + self.color_weight * (out["color"] - color_obs)[mask].abs().mean()
                value = float(loss.detach())
                losses.append(value)
                if value < best[0]:
                    best = (value, xi.detach().clone(), it)
                if self.early_stop_tol > 0 and len(losses) > 1 and \
                        abs(losses[-2] - value) <= self.early_stop_tol * max(losses[-2], 1e-12):
                    break
                if not loss.requires_grad:  # no sample has a map point near: nothing to move
                    logger.debug("tracking: no sample reaches the map at step %d, stopping", it)
                    break
                optimiser.zero_grad(set_to_none=True)
                loss.backward()
                optimiser.step()
        finally:
            decoders.requires_grad_(True)
        if self.keep_best and losses:
            loss_out, xi_out, best_iter = best
        else:
            loss_out, xi_out, best_iter = (losses[-1] if losses else math.nan), xi.detach(), \
                len(losses)
        with torch.no_grad():
            T_out = (T0 @ torch_se3_exp(xi_out)).cpu().numpy()
        return TrackResult(T_out, len(losses), float(loss_out), best_iter, losses)


def sample_pixels(
    depth: torch.Tensor, n: int, generator: torch.Generator, stratified: bool = False
) -> tuple[torch.Tensor, torch.Tensor]:
    """n pixel columns u and rows v [n] (int64) among those with depth > 0 (all valid pixels
    in order when there are fewer than n).

    Uniform: n independent draws (with replacement). Stratified: the image is cut into about
    n square cells and one pixel is drawn in each (cells whose pick has no depth give none);
    the shortfall is made up with uniform draws and a surplus dropped at random. The pixels
    then cover the whole view, so a frame's pose does not hinge on which part of the image a
    small random batch happened to favour.
    """
    flat = depth.reshape(-1) > 0
    valid = flat.nonzero(as_tuple=True)[0]
    if len(valid) == 0:
        raise ValueError("no pixel has a valid depth")
    height, width = depth.shape
    if len(valid) <= n:
        return valid % width, valid // width
    gdev = generator.device
    if not stratified:
        pick = torch.randint(0, len(valid), (n,), generator=generator, device=gdev)
        valid = valid[pick.to(valid.device)]
        return valid % width, valid // width
    cell = math.sqrt(height * width / n)
    n_u, n_v = math.ceil(width / cell), math.ceil(height / cell)
    cu = torch.arange(n_u, device=gdev, dtype=torch.float64).repeat(n_v)
    cv = torch.arange(n_v, device=gdev, dtype=torch.float64).repeat_interleave(n_u)
    jitter = torch.rand(2, n_u * n_v, generator=generator, device=gdev, dtype=torch.float64)
    u = ((cu + jitter[0]) * cell).long().clamp(max=width - 1)
    v = ((cv + jitter[1]) * cell).long().clamp(max=height - 1)
    index = (v * width + u).to(flat.device)
    index = index[flat[index]]
    if len(index) > n:
        keep = torch.randperm(len(index), generator=generator, device=gdev)[:n]
        index = index[keep.to(index.device)]
    elif len(index) < n:
        extra = torch.randint(0, len(valid), (n - len(index),), generator=generator,
                              device=gdev)
        index = torch.cat([index, valid[extra.to(valid.device)]])
    return index % width, index // width


def outlier_mask(
    err: torch.Tensor, var: torch.Tensor, err_lo: float, err_hi: float, var_factor: float
) -> torch.Tensor:
    """Pixels kept by the tracking loss: err within [err_lo, err_hi] times its median and
    variance at most var_factor times its median (bool [R])."""
    mu = err.median()
    keep = (err >= err_lo * mu) & (err <= err_hi * mu)
    return keep & (var <= var_factor * var.median())


def _motion_bound(dxi: torch.Tensor, t_far: float) -> float:
    """Upper bound of how far a sample up to t_far deep moves under the increment dxi (the
    ray direction has z = 1, so its length is at most about sqrt(2) at our fields of view)."""
    return float(dxi[:3].norm() + dxi[3:].norm() * t_far * math.sqrt(2.0))

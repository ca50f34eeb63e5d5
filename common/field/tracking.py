"""Camera tracking against the neural point map: the pose that makes the rendered depth (and,
with a colour weight, colour) match the observed one.

Two optimisers (`method`):

- "adam" (the paper): first-order steps on an se(3) increment, described below;
- "lm": Levenberg-Marquardt on robustly weighted depth and luminance residuals with a weak
  prior at the initial guess (`cpslam.common.field.pose_lm`). It converges in a few steps,
  stops when the pose no longer moves, and leaves directions the image cannot constrain at
  the initial guess, where Adam, which normalises every coordinate's step, moves them by its
  learning rate whatever the size of their gradient. With a colour weight it runs twice:
  depth alone from the initial guess (at most `depth_iters` solves), then depth and
  luminance from there (at most `iters`).

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

With "adam" the pose is the initial guess times an se(3) increment as above; "lm" uses the
same pixels and samples and ignores lr, lr_end_factor, keep_best, early_stop_tol and err_lo.

Used by the agent (every frame against its own map) and by the server (a loop keyframe against
another agent's sub-map, `cpslam.server.loops.refinement`), so it lives with the field in `common/`.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import numpy as np
import torch

from cpslam.common.camera import pixel_rays_torch
from cpslam.common.field.decoders import Decoders
from cpslam.common.field.image_terms import ReferenceImage
from cpslam.common.field.points import NeuralPointMap
from cpslam.common.field.pose_lm import LMSettings, solve_pose_lm
from cpslam.common.field.renderer import camera_rays, render_samples
from cpslam.common.field.spec import FieldSpec
from cpslam.common.geometry_torch import torch_se3_exp

if TYPE_CHECKING:
    from cpslam.common.camera import Intrinsics

logger = logging.getLogger(__name__)

_PIXEL_SAMPLING = ("uniform", "stratified")
_METHODS = ("adam", "lm")
# Fixed scales of `Tracker.score` (m, luminance) and the error a pixel off the map counts as.
_SCORE_DEPTH, _SCORE_COLOR, _SCORE_MISS = 0.02, 0.05, 3.0

__all__ = ["TrackResult", "Tracker", "outlier_mask", "sample_pixels"]


@dataclass
class TrackResult:
    """Outcome of tracking one frame.

    T_world_cam: [4, 4] float64 the chosen pose; iters: optimisation steps run ("lm": the
    solves of both phases); loss: the loss at the chosen pose (best or last evaluated; "lm":
    robust cost per kept pixel); best_iter: step whose pose was chosen; losses: loss of every
    step (at the pose before that step's update; "lm": at every linearisation point of the
    last phase); inlier_ratio: share of the drawn pixels the loss kept at the chosen pose;
    residual_m: median absolute depth error (m) of the pixels whose rays reach the map, at the
    chosen pose; information: [6, 6] Gauss-Newton information of the pose increment
    (translation first, "lm" only, else None).
    """

    T_world_cam: np.ndarray
    iters: int
    loss: float
    best_iter: int
    losses: list[float] = field(default_factory=list)
    inlier_ratio: float = math.nan
    residual_m: float = math.nan
    information: np.ndarray | None = None


class Tracker:
    """Pose optimisation of one frame against a fixed map.

    Args:
        intrinsics: of the processed frames.
        spec: the field (ray sampler, neighbours per sample, radius, search backend, rays per
            rendering pass).
        iters: optimisation steps per frame.
        n_pixels: pixels with valid depth drawn per frame (M2).
        lr: Adam learning rate of the se(3) increment.
        lr_end_factor: the learning rate decays exponentially to lr * lr_end_factor at the
            last step (1 = constant, the paper).
        color_weight: weight of a colour L1 term (0 = depth only, the paper).
        err_lo, err_hi, var_factor: the outlier mask (see the module docstring).
        keep_best: return the lowest-loss pose instead of the last one.
        early_stop_tol: stop when the relative loss change of a step is below this (0 = never).
        reuse_neighbours: metres the farthest sample may move before the neighbour search is
            redone (0 = search at every step).
        pixel_sampling: "uniform" (the paper: independent draws among the valid pixels) or
            "stratified" (one draw per cell of a grid over the image, see `sample_pixels`).
        method: "adam" (the paper) or "lm" (Levenberg-Marquardt, see the module docstring).
        prior_sigma_t, prior_sigma_r: "lm" only: standard deviations (m, rad) of the prior
            that holds the pose at its initial guess where the image does not constrain it.
        reference_weight, reference_pixels: "lm" only: weight of the residuals against a
            reference view (`track`'s `reference`, see `cpslam.common.field.image_terms`)
            and how many of the frame's pixels enter them (0 = off).
        n_near, n_uniform: samples per ray around the observed depth and uniform ones
            (None: the spec's, as mapping uses).
        relinearise_steps: "lm" only: accepted steps per solve that get new Jacobians, later
            ones reuse them (None: every step; see `cpslam.common.field.pose_lm`).
        depth_iters: "lm" with a colour term only: solves of the depth-only phase before the
            luminance one (None: `iters`); a call with its own `iters` uses those for both.
        step_stretch: "lm" only: after an accepted step that lowered the cost by more than
            1.5 times its quadratic model's prediction, the next step is first tried this many
            times longer and, when that does not lower the cost, as solved (1: off).
    """

    def __init__(
        self,
        intrinsics: Intrinsics,
        spec: FieldSpec,
        *,
        iters: int,
        n_pixels: int,
        lr: float,
        lr_end_factor: float,
        color_weight: float,
        err_lo: float,
        err_hi: float,
        var_factor: float,
        keep_best: bool,
        early_stop_tol: float,
        pixel_sampling: str,
        method: str,
        prior_sigma_t: float,
        prior_sigma_r: float,
        reference_weight: float,
        reference_pixels: int,
        n_near: int | None,
        n_uniform: int | None,
        relinearise_steps: int | None,
        depth_iters: int | None,
        step_stretch: float,
        reuse_neighbours: float = 0.01,
    ) -> None:
        if depth_iters is not None and depth_iters < 1:
            raise ValueError(f"Tracker: depth_iters must be >= 1 or None, got {depth_iters}")
        if not step_stretch >= 1.0:
            raise ValueError(f"Tracker: step_stretch must be >= 1, got {step_stretch}")
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
        if method not in _METHODS:
            raise ValueError(f"Tracker: method must be one of {_METHODS}, got {method!r}")
        if not (prior_sigma_t > 0 and prior_sigma_r > 0):
            raise ValueError(f"Tracker: prior sigmas must be > 0, got {prior_sigma_t}, "
                             f"{prior_sigma_r}")
        self.method = method
        self.reference_weight, self.reference_pixels = reference_weight, reference_pixels
        self.prior_sigma_t, self.prior_sigma_r = prior_sigma_t, prior_sigma_r
        self.pixel_sampling = pixel_sampling
        self.intrinsics = intrinsics
        self.spec = spec
        self.sampler = spec.sampler(n_near=n_near, n_uniform=n_uniform)
        self.iters = iters
        self.n_pixels = n_pixels
        self.lr = lr
        self.lr_end_factor = lr_end_factor
        self.color_weight = color_weight
        self.err_lo, self.err_hi, self.var_factor = err_lo, err_hi, var_factor
        self.keep_best = keep_best
        self.early_stop_tol = early_stop_tol
        self.k, self.radius = spec.k_neighbors, spec.radius
        self.backend, self.chunk = spec.neighbour_backend, spec.chunk_rays
        self.reuse_neighbours = reuse_neighbours
        self.relinearise_steps = relinearise_steps
        self.depth_iters = depth_iters
        self.step_stretch = step_stretch

    def track(
        self,
        point_map: NeuralPointMap,
        decoders: Decoders,
        rgb: torch.Tensor,
        depth: torch.Tensor,
        T_init: np.ndarray,
        generator: torch.Generator,
        iters: int | None = None,
        reference: ReferenceImage | Sequence[ReferenceImage] | None = None,
    ) -> TrackResult:
        """Optimise the pose of one frame.

        rgb: float [H, W, 3] in [0, 1] (only read when color_weight > 0); depth: float32
        [H, W] metres, 0 = invalid; T_init: [4, 4] initial T_world_cam; generator: draws the
        pixels and sample jitter; iters: steps for this call (default: the tracker's);
        reference: a view, or views ("lm" with reference_weight > 0), the frame is also
        compared with.
        """
        explicit = iters is not None
        iters = self.iters if iters is None else int(iters)
        depth_iters = iters if explicit or self.depth_iters is None else self.depth_iters
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
        if self.method == "lm":
            terms = None
            refs = [reference] if isinstance(reference, ReferenceImage) else list(reference or ())
            if refs and self.reference_weight > 0:
                terms = self._reference_points(rgb, depth, generator, refs)
            return self._track_lm(point_map, decoders, u, v, t, depth_obs, color_obs, T_init,
                                  iters, depth_iters, terms)
        t_far = float(t.max())
        index = point_map.neighbour_index(self.backend)
        features = point_map.features.detach()  # the map is fixed: no feature gradients

        T0 = torch.as_tensor(np.asarray(T_init, dtype=np.float64), device=device)
        xi = torch.zeros(6, dtype=torch.float64, device=device, requires_grad=True)
        optimiser = torch.optim.Adam([xi], lr=self.lr)
        decoders.requires_grad_(False)
        cached: tuple[torch.Tensor, torch.Tensor] | None = None  # (xi at search, neighbours)
        render_cache: dict = {}  # what depends only on the neighbours (render_samples)
        losses: list[float] = []
        best = (math.inf, xi.detach().clone(), 0)
        kept: list[float] = []  # share of the pixels the mask kept, per step
        medians: list[float] = []  # median depth error of the pixels reaching the map
        try:
            for it in range(iters):
                optimiser.param_groups[0]["lr"] = self.lr * self.lr_end_factor ** (
                    it / max(iters - 1, 1))
                T = T0 @ torch_se3_exp(xi)
                rays_o, rays_d = camera_rays(self.intrinsics, T, u, v)
                if cached is None or _motion_bound(xi.detach() - cached[0], t_far) \
                        > self.reuse_neighbours:
                    x = rays_o[:, None, :] + t[..., None] * rays_d[:, None, :]
                    cached = (xi.detach().clone(), index.query(x.detach().reshape(-1, 3),
                                                               self.k, self.radius))
                    render_cache = {}
                out = render_samples(point_map, decoders, rays_o, rays_d, t, self.k,
                                     self.radius, features=features, backend=self.backend,
                                     chunk=self.chunk, neighbours=cached[1],
                                     color=color_obs is not None, cache=render_cache)
                err = (out["depth"] - depth_obs).abs()
                mask = outlier_mask(err.detach(), out["var"].detach(), self.err_lo,
                                    self.err_hi, self.var_factor)
                if not bool(mask.any()):
                    logger.debug("tracking: every pixel masked at step %d, stopping", it)
                    break
                hit = out["acc"].detach() > 0.5
                kept.append(float(mask.float().mean()))
                medians.append(float(err.detach()[hit].median()) if bool(hit.any())
                               else math.inf)
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
        at = min(best_iter, len(kept) - 1)
        ratio, residual = (kept[at], medians[at]) if kept else (0.0, math.inf)
        return TrackResult(T_out, len(losses), float(loss_out), best_iter, losses, ratio,
                           residual)

    def _reference_points(self, rgb: torch.Tensor, depth: torch.Tensor,
                          generator: torch.Generator, refs: list[ReferenceImage]
                          ) -> tuple[list[ReferenceImage], torch.Tensor, torch.Tensor]:
        """The frame's pixels for the reference terms: back-projected points and luminance."""
        intr = self.intrinsics
        u, v = sample_pixels(depth, self.reference_pixels, generator, stratified=True)
        d = depth[v, u].double()
        xyz = pixel_rays_torch(intr, u.double(), v.double()) * d[:, None]
        return refs, xyz.to(depth.device), rgb[v, u].double().mean(-1)

    @torch.no_grad()
    def score(
        self,
        point_map: NeuralPointMap,
        decoders: Decoders,
        rgb: torch.Tensor,
        depth: torch.Tensor,
        poses: list[np.ndarray],
        generator: torch.Generator,
    ) -> list[float]:
        """One robust cost per candidate pose of this frame, on one common set of pixels and
        samples and with fixed scales, so candidates found in different ways compare (lower
        is better): the mean Huber cost of the depth error over `_SCORE_DEPTH` metres plus,
        with a colour weight, that of the luminance error over `_SCORE_COLOR`; a pixel whose
        ray reaches no map point costs as an error of `_SCORE_MISS` scales."""
        u, v = sample_pixels(depth, self.n_pixels, generator,
                             stratified=self.pixel_sampling == "stratified")
        depth_obs = depth[v, u]
        gray_obs = rgb[v, u].mean(-1) if self.color_weight > 0 else None
        t = self.sampler(depth_obs, generator)
        index = point_map.neighbour_index(self.backend)
        out_scores = []
        for T in poses:
            T_t = torch.as_tensor(np.asarray(T, dtype=np.float64), device=point_map.device)
            rays_o, rays_d = camera_rays(self.intrinsics, T_t, u, v)
            x = rays_o[:, None, :] + t[..., None] * rays_d[:, None, :]
            neighbours = index.query(x.reshape(-1, 3), self.k, self.radius)
            out = render_samples(point_map, decoders, rays_o, rays_d, t, self.k, self.radius,
                                 backend=self.backend, chunk=self.chunk, neighbours=neighbours,
                                 color=gray_obs is not None)
            miss = out["acc"] <= 0.5
            err = ((out["depth"] - depth_obs) / _SCORE_DEPTH).masked_fill(miss, _SCORE_MISS)
            cost = _huber(err).mean()
            if gray_obs is not None:
                err_c = ((out["color"].mean(-1) - gray_obs) / _SCORE_COLOR).masked_fill(
                    miss, _SCORE_MISS)
                cost = cost + self.color_weight * _huber(err_c).mean()
            out_scores.append(float(cost))
        return out_scores

    def _track_lm(self, point_map: NeuralPointMap, decoders: Decoders, u: torch.Tensor,
                  v: torch.Tensor, t: torch.Tensor, depth_obs: torch.Tensor,
                  color_obs: torch.Tensor | None, T_init: np.ndarray, iters: int,
                  depth_iters: int, reference: tuple | None = None) -> TrackResult:
        settings = LMSettings(
            iters=iters, color_weight=self.color_weight, err_hi=self.err_hi,
            var_factor=self.var_factor, k=self.k, radius=self.radius, backend=self.backend,
            chunk=self.chunk, reuse_neighbours=self.reuse_neighbours,
            prior_sigma_t=self.prior_sigma_t, prior_sigma_r=self.prior_sigma_r,
            reference_weight=self.reference_weight, relinearise_steps=self.relinearise_steps,
            step_stretch=self.step_stretch)
        intr = self.intrinsics
        gray = None if color_obs is None else color_obs.mean(-1)
        decoders.requires_grad_(False)
        try:
            T_start, depth_solves = T_init, 0
            if gray is not None:
                # Depth first: its basin is wide (a rendered surface moves smoothly with the
                # pose), while luminance is periodic on striped or tiled texture and, from a
                # guess a degree off, pulls towards the wrong stripe.
                first = solve_pose_lm(point_map, decoders, u, v, t, depth_obs, None, intr,
                                      T_init, replace(settings, iters=depth_iters))
                T_start, depth_solves = first.T_world_cam, first.iters
            sol = solve_pose_lm(point_map, decoders, u, v, t, depth_obs, gray, intr, T_start,
                                settings, reference)
        finally:
            decoders.requires_grad_(True)
        loss = sol.costs[-1] if sol.costs else math.nan
        # The frame's work is both phases' solves, not the last phase's alone.
        solves = depth_solves + sol.iters
        return TrackResult(sol.T_world_cam, solves, loss, solves, sol.costs,
                           sol.inlier_ratio, sol.residual_m, sol.information)


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


def _huber(x: torch.Tensor) -> torch.Tensor:
    a = x.abs()
    return torch.where(a <= 1.0, 0.5 * x * x, a - 0.5)


def _motion_bound(dxi: torch.Tensor, t_far: float) -> float:
    """Upper bound of how far a sample up to t_far deep moves under the increment dxi (the
    ray direction has z = 1, so its length is at most about sqrt(2) at our fields of view)."""
    return float(dxi[:3].norm() + dxi[3:].norm() * t_far * math.sqrt(2.0))

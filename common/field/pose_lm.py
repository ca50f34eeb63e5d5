"""Levenberg-Marquardt refinement of one camera pose against the neural point map.

The residuals of a pixel p are its rendered depth minus the observed one and, with a colour
weight, its rendered minus observed luminance (the mean of R, G and B). Both are divided by a
robust scale (1.4826 times their median absolute value at the current pose, never below a
floor) and go through a Huber kernel, so a pixel counts in standard units whatever the scene's
depth or contrast. A weak Gaussian prior keeps the pose near its initial guess; it matters only
along directions the image does not constrain (a camera in front of a bare wall can slide
along it without changing the depth), which it holds at the guess instead of letting noise
move them. Pixels whose ray reaches no map point, whose depth error exceeds `err_hi` times
the median, or whose rendered depth variance exceeds `var_factor` times the median are left
out at each linearisation point.

The Jacobian of every residual with respect to the pose increment xi (translation first,
camera frame, T = T_cur @ exp(xi)) comes from one backward pass per residual kind: a ray's
rendered depth depends only on its own origin o and direction d, so the gradient of their sum
with respect to o [R, 3] and d [R, 3] holds every ray's derivative, and
dr/drho = R^T dr/do, dr/dphi = d_cam x (R^T dr/dd).

Steps: solve (H + lambda diag(H)) dx = -g, evaluate the cost at T @ exp(dx) with the same
pixels, samples, neighbours, mask and scales; accept and shrink lambda if it went down, else
grow lambda and solve again. With `step_stretch` s > 1, where the last accepted step lowered
the cost by more than 1.5 times what the quadratic model predicted (its steps fall short),
the next step is first tried s times longer, then as solved. The neighbour search is redone
at an accepted pose that moved its farthest sample by more than `reuse_neighbours`. The mask
and scales are re-estimated after each of the first three accepted steps and after a new
search, then kept: re-weighting at every step can cycle between two poses a fraction of a
millimetre apart. Converged when a step moves less than `tol_t` metres and `tol_r` radians
(accepted or not) or an accepted one lowers the cost by less than a relative 1e-5. With
`relinearise_steps` = n, only the first n accepted steps (and any that redo the neighbour
search) get new Jacobians; later ones keep those of the last linearisation point and
recompute only the residuals, their robust weights and so H and g (chord steps), and their
candidates are rendered without the autograd graph. The pose then moves by little per step,
over which the Jacobians hardly change; the cost that accepts or rejects a step is exact
either way.

The solution's information matrix (H at the last linearisation point, 6 x 6, translation
first, in units of the normalised residuals) says how well each direction is constrained.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from cpslam.common.camera import Intrinsics, pixel_rays_torch
from cpslam.common.field.decoders import Decoders
from cpslam.common.field.image_terms import ReferenceImage, image_residuals
from cpslam.common.field.points import NeuralPointMap
from cpslam.common.field.renderer import render_samples
from cpslam.common.geometry import invert, se3_exp, se3_log

__all__ = ["LMSettings", "LMSolution", "solve_pose_lm"]

_LAMBDA_START, _LAMBDA_MIN, _LAMBDA_MAX = 1e-3, 1e-7, 1e4
_RESCALE_STEPS = 3  # accepted steps after which the mask and robust scales are kept
_REL_TOL = 1e-5  # an accepted step that lowers the cost by less than this share: converged
_MIN_PIXELS = 12  # fewer kept pixels than this cannot pin six degrees of freedom
_MISS = 3.0  # normalised error a reference pixel counts as once it leaves the reference view
# A step is tried stretched when the last accepted one lowered the cost by more than this times
# what the quadratic model predicted for its step as solved (an exact model gives 1).
_STRETCH_RHO = 1.5


@dataclass(frozen=True)
class LMSettings:
    """What `solve_pose_lm` needs besides the data (see the module docstring)."""

    iters: int
    color_weight: float
    err_hi: float
    var_factor: float
    k: int
    radius: float
    backend: str
    chunk: int | None
    reuse_neighbours: float
    prior_sigma_t: float
    prior_sigma_r: float
    huber: float = 1.345
    tol_t: float = 1e-4
    tol_r: float = 1e-4
    depth_floor: float = 0.002
    color_floor: float = 0.01
    reference_weight: float = 0.0
    relinearise_steps: int | None = None
    step_stretch: float = 1.0


@dataclass
class LMSolution:
    """T_world_cam [4, 4] float64; iters: solves (accepted or not); cost per kept pixel at
    each linearisation point (``costs``, the last one at the returned pose); information
    [6, 6] at the returned pose; inlier_ratio: share of the drawn pixels kept there;
    residual_m: median absolute depth error (m) there of the pixels whose rays reach the map."""

    T_world_cam: np.ndarray
    iters: int
    costs: list[float]
    information: np.ndarray
    inlier_ratio: float
    residual_m: float


def solve_pose_lm(
    point_map: NeuralPointMap,
    decoders: Decoders,
    u: torch.Tensor,
    v: torch.Tensor,
    t: torch.Tensor,
    depth_obs: torch.Tensor,
    gray_obs: torch.Tensor | None,
    intrinsics: Intrinsics,
    T_init: np.ndarray,
    settings: LMSettings,
    reference: tuple[list[ReferenceImage], torch.Tensor, torch.Tensor] | None = None,
) -> LMSolution:
    """Refine T_init [4, 4] for the pixels u, v [R] (columns, rows) with samples t [R, n],
    observed depth [R] and luminance [R] (None without a colour term). The decoders must not
    require gradients (the caller freezes them). reference: (the reference views, the
    frame's points xyz_cam [P, 3] and their luminance [P]) adds the image terms of
    `cpslam.common.field.image_terms` against each view, weighted by
    settings.reference_weight."""
    problem = _Problem(point_map, decoders, u, v, t, depth_obs, gray_obs, intrinsics,
                       settings, reference)
    T_init = np.asarray(T_init, dtype=np.float64)
    T_prior_inv = invert(T_init)
    prior = np.array([settings.prior_sigma_t ** -2] * 3 + [settings.prior_sigma_r ** -2] * 3)
    T = T_init.copy()
    state = problem.evaluate(T, refresh=True)
    scales = problem.scales(state)
    empty = LMSolution(T, 0, [], np.diag(prior), 0.0, math.inf)
    if scales is None:
        return empty
    lam, costs, iters, accepted = _LAMBDA_START, [], 0, 0
    H = g = None
    jacobians: list[torch.Tensor] | None = None  # of the last linearisation point, when kept
    cost_cur = math.inf
    rho_last = 0.0  # actual over predicted cost decrease of the last accepted step
    while iters < settings.iters:
        if H is None:  # linearise at the current pose
            xi = se3_log(T_prior_inv @ T)
            H, g, jacobians = problem.normal_equations(state, scales, jacobians)
            H, g = H + np.diag(prior), g + prior * xi
            cost_cur = problem.cost(state, scales) + 0.5 * float(prior @ (xi * xi))
            costs.append(cost_cur / scales.kept)
        iters += 1
        try:
            dx = -np.linalg.solve(H + lam * np.diag(np.diag(H)), g)
        except np.linalg.LinAlgError:
            break
        # A candidate that would keep the current Jacobians needs no graph for new ones.
        chord = settings.relinearise_steps is not None \
            and accepted >= settings.relinearise_steps
        # Longer first where the last accepted step did much better than the model said.
        stretches = (settings.step_stretch, 1.0) if rho_last > _STRETCH_RHO \
            and settings.step_stretch > 1.0 else (1.0,)
        for stretch in stretches:
            step = stretch * dx
            T_new = T @ se3_exp(step)
            candidate = problem.evaluate(T_new, graph=not chord)
            xi_new = se3_log(T_prior_inv @ T_new)
            cost_new = problem.cost(candidate, scales) + 0.5 * float(prior @ (xi_new * xi_new))
            if cost_new < cost_cur:
                break
        small = np.linalg.norm(dx[:3]) < settings.tol_t and np.linalg.norm(dx[3:]) < settings.tol_r
        if not cost_new < cost_cur:
            lam *= 10.0
            if lam > _LAMBDA_MAX or small:  # even a tiny step does not help: converged
                break
            continue
        predicted = -float(g @ dx + 0.5 * dx @ H @ dx)  # of the step as solved
        rho_last = (cost_cur - cost_new) / predicted if predicted > 0 else 0.0
        T, state, lam = T_new, candidate, max(lam / 10.0, _LAMBDA_MIN)
        accepted += 1
        refreshed = problem.moved_beyond_search(T)
        if refreshed:
            state = problem.evaluate(T, refresh=True)
        if refreshed or accepted <= _RESCALE_STEPS:
            # The mask and scales follow the pose while it moves much, then stay put.
            new_scales = problem.scales(state)
            if new_scales is None:
                break
            scales = new_scales
        if refreshed or not chord:  # new neighbours, or still relinearising
            jacobians = None
        H = None
        if small or cost_cur - cost_new < _REL_TOL * cost_cur:
            break
    if H is None:  # the last step was accepted: the information and cost at the final pose
        xi = se3_log(T_prior_inv @ T)
        H, _, _ = problem.normal_equations(state, scales, jacobians)
        H = H + np.diag(prior)
        costs.append((problem.cost(state, scales) + 0.5 * float(prior @ (xi * xi)))
                     / scales.kept)
    return LMSolution(T, iters, costs, H, scales.kept / max(len(u), 1), scales.median_hit)


@dataclass
class _Scales:
    """The mask and robust scales of one linearisation point."""

    mask: torch.Tensor  # bool [R]
    depth: float
    color: float
    kept: int
    median_hit: float  # median |depth error| (m) of the pixels reaching the map
    # Per reference view (None: too few of its pixels): bool [P] pixels in use, and the
    # robust scales of its luminance and depth residuals.
    refs: list[tuple[torch.Tensor, float, float] | None] = field(default_factory=list)


class _Problem:
    """Rendering, residuals, Jacobians and costs of one frame's pixels."""

    def __init__(self, point_map: NeuralPointMap, decoders: Decoders, u: torch.Tensor,
                 v: torch.Tensor, t: torch.Tensor, depth_obs: torch.Tensor,
                 gray_obs: torch.Tensor | None, intrinsics: Intrinsics,
                 settings: LMSettings,
                 reference: tuple[list[ReferenceImage], torch.Tensor, torch.Tensor] | None
                 ) -> None:
        device = point_map.device
        self.point_map, self.decoders, self.s = point_map, decoders, settings
        self.t = t.to(device)
        self.depth_obs = depth_obs.to(device=device, dtype=torch.float64)
        self.gray_obs = None if gray_obs is None else gray_obs.to(device=device,
                                                                  dtype=torch.float64)
        self.d_cam = pixel_rays_torch(intrinsics, u.to(device, torch.float64), v.to(device))
        self.features = point_map.features.detach()
        self.index = point_map.neighbour_index(settings.backend)
        self.t_far = float(self.t.max())
        self.T_search: np.ndarray | None = None
        self.neighbours: torch.Tensor | None = None
        self.render_cache: dict = {}  # what depends only on the neighbours (render_samples)
        self.reference = reference if reference is not None and settings.reference_weight > 0 \
            else None
        # Each reference view's weight: settings.reference_weight times the view's own.
        self.view_weights = [settings.reference_weight * view.weight
                             for view in (self.reference[0] if self.reference else [])]

    def evaluate(self, T: np.ndarray, refresh: bool = False, graph: bool = True) -> dict:
        """Render at pose T; refresh: redo the neighbour search; graph: keep the autograd graph
        the Jacobians need (a state without it only gives residuals and costs)."""
        device = self.d_cam.device
        R = torch.as_tensor(T[:3, :3], device=device)
        rays_d = (self.d_cam @ R.T).float().requires_grad_(graph)
        rays_o = torch.as_tensor(T[:3, 3], device=device).float().expand_as(rays_d) \
            .clone().requires_grad_(graph)
        if refresh or self.neighbours is None:
            x = rays_o.detach()[:, None, :] + self.t[..., None] * rays_d.detach()[:, None, :]
            self.neighbours = self.index.query(x.reshape(-1, 3), self.s.k, self.s.radius)
            self.T_search = T.copy()
            self.render_cache = {}
        with torch.set_grad_enabled(graph):
            out = render_samples(self.point_map, self.decoders, rays_o, rays_d, self.t,
                                 self.s.k, self.s.radius, features=self.features,
                                 backend=self.s.backend, chunk=self.s.chunk,
                                 neighbours=self.neighbours, color=self.gray_obs is not None,
                                 cache=self.render_cache)
        state = {"R": R, "rays_o": rays_o, "rays_d": rays_d, "out": out, "graph": graph,
                 "r_depth": out["depth"].detach().double() - self.depth_obs}
        if self.gray_obs is not None:
            state["gray"] = out["color"].mean(-1)
            state["r_color"] = state["gray"].detach().double() - self.gray_obs
        if self.reference is not None:
            refs, xyz, gray = self.reference
            state["ref"] = [image_residuals(ref, T, xyz, gray) for ref in refs]
        return state

    def moved_beyond_search(self, T: np.ndarray) -> bool:
        """Whether the farthest sample moved more than reuse_neighbours since the search."""
        if self.T_search is None:
            return True
        xi = se3_log(invert(self.T_search) @ T)
        moved = np.linalg.norm(xi[:3]) + np.linalg.norm(xi[3:]) * self.t_far * math.sqrt(2.0)
        return bool(moved > self.s.reuse_neighbours)

    def scales(self, state: dict) -> _Scales | None:
        """Mask and robust scales at this pose; None when too few pixels are left."""
        out, r = state["out"], state["r_depth"]
        hit = out["acc"].detach() > 0.5
        if int(hit.sum()) < _MIN_PIXELS:
            return None
        var = out["var"].detach()
        mask = hit & (r.abs() <= self.s.err_hi * r[hit].abs().median()) \
            & (var <= self.s.var_factor * var[hit].median())
        kept = int(mask.sum())
        if kept < _MIN_PIXELS:
            return None
        depth = _robust_scale(r[mask], self.s.depth_floor)
        color = 1.0
        if self.gray_obs is not None:
            color = _robust_scale(state["r_color"][mask], self.s.color_floor)
        scales = _Scales(mask, depth, color, kept, float(r[hit].abs().median()))
        for r_gray, _, r_depth, _, valid in state.get("ref", ()):
            scales.refs.append(None if int(valid.sum()) < _MIN_PIXELS else (
                valid, _robust_scale(r_gray[valid], self.s.color_floor),
                _robust_scale(r_depth[valid], self.s.depth_floor)))
        return scales

    def cost(self, state: dict, sc: _Scales) -> float:
        """Robust cost of the kept pixels (Huber of the normalised residuals)."""
        total = _huber(state["r_depth"][sc.mask] / sc.depth, self.s.huber).sum()
        if self.gray_obs is not None:
            total = total + self.s.color_weight * _huber(
                state["r_color"][sc.mask] / sc.color, self.s.huber).sum()
        for (r_gray, _, r_depth, _, valid), ref, weight in zip(
                state.get("ref", ()), sc.refs, self.view_weights, strict=True):
            if ref is None:
                continue
            mask, gray_scale, depth_scale = ref
            for r, scale in ((r_gray, gray_scale), (r_depth, depth_scale)):
                # A pixel that left the reference view costs as a large error, so that a
                # pose cannot lower the cost by pushing pixels out of it.
                x = torch.where(valid, r / scale, _MISS)[mask]
                total = total + weight * _huber(x, self.s.huber).sum()
        return float(total)

    def normal_equations(
        self, state: dict, sc: _Scales, jacobians: list[torch.Tensor] | None = None
    ) -> tuple[np.ndarray, np.ndarray, list[torch.Tensor]]:
        """H = J^T W J and g = J^T W r over the kept pixels (float64 numpy, [6, 6] and [6]),
        and the rendered terms' Jacobians of every ray ([R, 6] per kind).
        jacobians: those of an earlier call (same rays), used instead of new ones."""
        kinds = [("depth", state["out"]["depth"], state["r_depth"], sc.depth, 1.0)]
        if self.gray_obs is not None:
            kinds.append(("color", state["gray"], state["r_color"], sc.color,
                          self.s.color_weight))
        if jacobians is None:
            if not state["graph"]:
                raise RuntimeError("normal_equations: the state was rendered without a graph "
                                   "and no Jacobians were given")
            jacobians = [self._jacobian(state, value, retain=i + 1 < len(kinds))
                         for i, (_, value, _, _, _) in enumerate(kinds)]
        H = torch.zeros(6, 6, dtype=torch.float64, device=self.d_cam.device)
        g = torch.zeros(6, dtype=torch.float64, device=self.d_cam.device)
        for J_all, (_, _, residual, scale, weight) in zip(jacobians, kinds, strict=True):
            J = J_all[sc.mask] / scale
            r = residual[sc.mask] / scale
            w = weight * _huber_weight(r, self.s.huber)
            H += (J * w[:, None]).T @ J
            g += (J * w[:, None]).T @ r
        for (r_gray, J_gray, r_depth, J_depth, valid), ref, weight in zip(
                state.get("ref", ()), sc.refs, self.view_weights, strict=True):
            if ref is None:
                continue
            mask, gray_scale, depth_scale = ref
            use = mask & valid
            for r, J, scale in ((r_gray, J_gray, gray_scale), (r_depth, J_depth, depth_scale)):
                r, J = r[use] / scale, J[use] / scale
                w = weight * _huber_weight(r, self.s.huber)
                H += (J * w[:, None]).T @ J
                g += (J * w[:, None]).T @ r
        return H.cpu().numpy(), g.cpu().numpy(), jacobians

    def _jacobian(self, state: dict, value: torch.Tensor, retain: bool) -> torch.Tensor:
        """d value_r / d xi [R, 6] for the per-ray rendered quantity value [R]."""
        if not value.requires_grad:  # no sample reaches the map: nothing moves it
            return torch.zeros(len(self.d_cam), 6, dtype=torch.float64, device=self.d_cam.device)
        g_o, g_d = torch.autograd.grad(value.sum(), (state["rays_o"], state["rays_d"]),
                                       retain_graph=retain, allow_unused=True)
        zeros = torch.zeros_like(self.d_cam)
        R = state["R"]
        g_o = zeros if g_o is None else g_o.double() @ R
        g_d = zeros if g_d is None else g_d.double() @ R
        return torch.cat((g_o, torch.linalg.cross(self.d_cam, g_d, dim=-1)), dim=-1)


def _robust_scale(r: torch.Tensor, floor: float) -> float:
    """1.4826 x the median absolute residual (the normal's sigma), never below floor."""
    return max(1.4826 * float(r.abs().median()), floor)


def _huber(x: torch.Tensor, k: float) -> torch.Tensor:
    a = x.abs()
    return torch.where(a <= k, 0.5 * x * x, k * (a - 0.5 * k))


def _huber_weight(x: torch.Tensor, k: float) -> torch.Tensor:
    a = x.abs()
    return torch.where(a <= k, torch.ones_like(a), k / a.clamp(min=1e-12))

"""Volume rendering of the neural point field: sample rays, gather neighbours, decode,
alpha-composite depth, colour and depth variance.

Gradients reach the point features, the decoder weights and whatever produced the rays (the
camera pose): the neighbour search runs on detached positions, but offsets x - p_k and
inverse-distance weights are recomputed in torch from the returned indices.

Full images (`render_image`) have no observed depth to guide the samples, so they are rendered
in three steps: (1) geometry only: march each ray in steps of one search radius over the depth
range of the map points in view and stop at the first sample that has a point within the
radius; (2) decode a short window behind that first hit and take its expected depth as the
guide; (3) render with the paper's sampler around the guide. A ray whose first neighbourhood
is a stray point with little occupancy therefore stays empty even if a surface lies behind.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import torch

from cpslam.common.camera import pixel_rays_torch
from cpslam.common.field.decoders import Decoders
from cpslam.common.field.points import NeuralPointMap
from cpslam.common.field.sampler import RaySampler
from cpslam.common.field.search import NeighbourIndex

if TYPE_CHECKING:
    from cpslam.common.camera import Intrinsics

# Window decoded behind the first hit in render_image, in units of the search radius.
_WINDOW_START, _WINDOW_END, _WINDOW_SAMPLES = -0.5, 2.0, 6


def render_rays(
    point_map: NeuralPointMap,
    decoders: Decoders,
    rays_o: torch.Tensor,
    rays_d: torch.Tensor,
    depth_obs: torch.Tensor,
    sampler: RaySampler,
    generator: torch.Generator | None = None,
    *,
    k: int,
    radius: float,
    features: torch.Tensor | None = None,
    depth_range: tuple[float, float] | None = None,
    backend: str = "auto",
    chunk: int | None = None,
) -> dict[str, torch.Tensor]:
    """Render R rays with samples from `sampler` guided by the observed depth.

    rays_o, rays_d: [R, 3] world frame, directions with camera z = 1 so that t is z-depth.
    depth_obs: [R] observed depth guiding the samples (0 = none).
    generator: jitter of the samples (same state, same samples).
    k, radius: neighbours gathered per sample, within radius metres.
    features: [N, F] to use instead of `point_map.features` (subset optimisation).
    depth_range: (D_min, D_max) for the sampler instead of the batch's (see RaySampler).
    backend: neighbour search backend (see NeighbourIndex).
    chunk: rays per pass (all at once when None).
    Returns depth [R], color [R, 3], var [R] (depth variance), acc [R] (sum of weights),
    t [R, n] and weights [R, n] per sample, n_valid_samples (int64 scalar: samples that had
    at least one neighbour).
    """
    if depth_obs.shape != rays_o.shape[:1]:
        raise ValueError(f"render_rays: depth_obs must be [{rays_o.shape[0]}], "
                         f"got {tuple(depth_obs.shape)}")
    # Sample all rays with one generator call so the result does not depend on `chunk`.
    t = sampler(depth_obs, generator, depth_range)
    return render_samples(point_map, decoders, rays_o, rays_d, t, k, radius, features,
                          backend, chunk)


def render_samples(
    point_map: NeuralPointMap,
    decoders: Decoders,
    rays_o: torch.Tensor,
    rays_d: torch.Tensor,
    t: torch.Tensor,
    k: int,
    radius: float,
    features: torch.Tensor | None = None,
    backend: str = "auto",
    chunk: int | None = None,
    neighbours: torch.Tensor | None = None,
    color: bool = True,
    cache: dict | None = None,
) -> dict[str, torch.Tensor]:
    """Render R rays at given sample depths t [R, n] (ascending along each ray).

    Same arguments and result as `render_rays`, which calls it after sampling.
    neighbours: [R * n, k] map rows of each sample's neighbours (-1 = none), as returned by
    `NeuralPointMap.neighbour_index().query`, to skip the search (a tracker that moves the
    rays by less than a fraction of the radius can reuse one search over several steps).
    color: False skips the colour decoder (colour comes back as zeros).
    cache: with `neighbours`, a dict the caller keeps between calls with the same
        neighbours, features and decoders (a tracker's steps): the pair lists, the pairs' point
        positions and, where nothing there needs a gradient, the decoders' per-point hidden
        layer are computed on the first call and reused; the caller empties it when any of
        them changes. The result is the same as without it.
    """
    if rays_o.shape != rays_d.shape or rays_o.ndim != 2 or rays_o.shape[1] != 3:
        raise ValueError(f"render: rays_o {tuple(rays_o.shape)} and rays_d "
                         f"{tuple(rays_d.shape)} must both be [R, 3]")
    if t.ndim != 2 or t.shape[0] != rays_o.shape[0]:
        raise ValueError(f"render: t must be [{rays_o.shape[0]}, n], got {tuple(t.shape)}")
    feats = point_map.features if features is None else features
    if feats.shape != (len(point_map), point_map.feature_dim):
        raise ValueError(f"render: features must be [{len(point_map)}, "
                         f"{point_map.feature_dim}], got {tuple(feats.shape)}")
    xyz = point_map.xyz_world()
    index = point_map.neighbour_index(backend)
    n_rays, n_per_ray = t.shape
    if neighbours is not None and neighbours.shape != (n_rays * n_per_ray, k):
        raise ValueError(f"render: neighbours must be [{n_rays * n_per_ray}, {k}], "
                         f"got {tuple(neighbours.shape)}")
    step = max(n_rays, 1) if chunk is None else max(1, chunk)
    parts = [
        _render_chunk(xyz, feats, index, decoders, rays_o[i : i + step], rays_d[i : i + step],
                      t[i : i + step], k, radius,
                      None if neighbours is None
                      else neighbours[i * n_per_ray : (i + step) * n_per_ray], color,
                      None if cache is None or neighbours is None else cache.setdefault(i, {}))
        for i in range(0, max(n_rays, 1), step)
    ]
    if len(parts) == 1:
        return parts[0]
    out = {key: torch.cat([p[key] for p in parts]) for key in parts[0] if key != "n_valid_samples"}
    out["n_valid_samples"] = sum(p["n_valid_samples"] for p in parts)
    return out


def camera_rays(
    intrinsics: Intrinsics, T_world_cam: torch.Tensor, u: torch.Tensor, v: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """World rays through pixels (u [R] columns, v [R] rows; pixel centres at integers).

    Returns rays_o [R, 3] and rays_d [R, 3] float32 with camera-frame z = 1, differentiable
    with respect to T_world_cam [4, 4] (any float dtype).
    """
    T = T_world_cam.to(dtype=torch.float32)
    u = u.to(device=T.device, dtype=torch.float32)
    v = v.to(device=T.device, dtype=torch.float32)
    dirs = pixel_rays_torch(intrinsics, u, v)  # [R, 3] camera frame
    rays_d = dirs @ T[:3, :3].T
    rays_o = T[:3, 3].expand_as(rays_d)
    return rays_o, rays_d


@torch.no_grad()
def render_image(
    point_map: NeuralPointMap,
    decoders: Decoders,
    intrinsics: Intrinsics,
    T_world_cam: torch.Tensor,
    sampler: RaySampler,
    *,
    k: int,
    radius: float,
    step: int = 1,
    min_acc: float = 0.5,
    chunk: int = 2048,
    backend: str = "auto",
) -> dict[str, torch.Tensor]:
    """Render a full image (every `step`-th pixel) without observed depth.

    See the module docstring for the three passes. Rays whose window opacity stays below
    `min_acc` are left empty (depth 0, colour 0). `sampler` is the final pass's (one with
    perturb=False puts the samples at bin centres). `chunk` rays go through each pass at once:
    about 2k keeps the per-pair tensors in cache (8k was twice as slow on CPU).
    Returns depth [h, w], color [h, w, 3], var [h, w], acc [h, w] with h = ceil(H / step).
    """
    device = point_map.device
    T = torch.as_tensor(T_world_cam, device=device)
    vs = torch.arange(0, intrinsics.height, step, device=device)
    us = torch.arange(0, intrinsics.width, step, device=device)
    h, w = len(vs), len(us)
    vv, uu = torch.meshgrid(vs, us, indexing="ij")
    rays_o, rays_d = camera_rays(intrinsics, T, uu.reshape(-1), vv.reshape(-1))
    out = {
        "depth": torch.zeros(h * w, device=device),
        "color": torch.zeros(h * w, 3, device=device),
        "var": torch.zeros(h * w, device=device),
        "acc": torch.zeros(h * w, device=device),
    }
    z_range = _depth_range_in_view(point_map, intrinsics, T, radius)
    if z_range is not None:
        index = point_map.neighbour_index(backend)
        t_hit = _first_hit(index, rays_o, rays_d, z_range, radius, chunk)
        hit = (t_hit > 0).nonzero(as_tuple=True)[0]
        offsets = torch.linspace(_WINDOW_START, _WINDOW_END, _WINDOW_SAMPLES, device=device)
        t_window = (t_hit[hit, None] + radius * offsets).clamp(min=1e-3)
        window = render_samples(point_map, decoders, rays_o[hit], rays_d[hit], t_window, k,
                                radius, backend=backend, chunk=chunk)
        keep = window["acc"] >= min_acc
        hit = hit[keep]
        # No ray left (a pose far from the map, or nothing opaque yet): the sampler cannot
        # take its range from an empty batch, and the image is empty anyway.
        if len(hit) > 0:
            guide = window["depth"][keep] / window["acc"][keep]
            fine = render_rays(point_map, decoders, rays_o[hit], rays_d[hit], guide,
                               sampler, k=k, radius=radius,
                               backend=backend, chunk=chunk)
            for key in out:
                out[key][hit] = fine[key]
    return {
        "depth": out["depth"].reshape(h, w),
        "color": out["color"].reshape(h, w, 3),
        "var": out["var"].reshape(h, w),
        "acc": out["acc"].reshape(h, w),
    }


def _render_chunk(
    xyz: torch.Tensor,
    features: torch.Tensor,
    index: NeighbourIndex,
    decoders: Decoders,
    rays_o: torch.Tensor,
    rays_d: torch.Tensor,
    t: torch.Tensor,
    k: int,
    radius: float,
    nbr: torch.Tensor | None = None,
    color: bool = True,
    cache: dict | None = None,
) -> dict[str, torch.Tensor]:
    n_rays, n_per_ray = t.shape
    t = t.to(rays_o.device)
    x = (rays_o[:, None, :] + t[..., None] * rays_d[:, None, :]).reshape(-1, 3)  # [S, 3]
    if nbr is None:
        nbr = index.query(x.detach(), k, radius)
    nbr = nbr.to(x.device)  # [S, k]
    pairs = cache if cache else _sample_pairs(nbr, xyz, x.device)
    if cache is not None and not cache:
        cache.update(pairs)
    # What carries a gradient (trainable features or decoders, movable points) is recomputed
    # at every call; the rest is kept.
    hidden, xyz_pair = pairs.get("hidden"), pairs.get("xyz")
    if hidden is None:
        hidden = decoders.point_hidden(features.index_select(0, pairs["points"]))
        if cache is not None and not hidden.requires_grad:
            cache["hidden"] = hidden
    if xyz_pair is None:
        xyz_pair = xyz.index_select(0, pairs["global"]).to(x.dtype)
        if cache is not None and not xyz_pair.requires_grad:
            cache["xyz"] = xyz_pair
    offsets = x.index_select(0, pairs["sample"]) - xyz_pair
    occ, rgb = decoders.forward_pairs(None, pairs["point"], offsets, pairs["sample"],
                                      x.shape[0], color, point_hidden=hidden)
    occ = occ.reshape(n_rays, n_per_ray)
    rgb = rgb.reshape(n_rays, n_per_ray, 3)
    # w_i = o_i prod_{j<i} (1 - o_j) along each ray (samples sorted by depth).
    survive = torch.cumprod(1.0 - occ, dim=1)
    transmittance = torch.cat((torch.ones_like(survive[:, :1]), survive[:, :-1]), dim=1)
    weights = occ * transmittance
    depth = (weights * t).sum(dim=1)
    return {
        "depth": depth,
        "color": (weights[..., None] * rgb).sum(dim=1),
        "var": (weights * (t - depth[:, None]) ** 2).sum(dim=1),
        "acc": weights.sum(dim=1),
        "t": t,
        "weights": weights,
        "n_valid_samples": (nbr[:, 0] >= 0).sum(),
    }


def _sample_pairs(nbr: torch.Tensor, xyz: torch.Tensor, device: torch.device
                  ) -> dict[str, torch.Tensor]:
    """The (sample, neighbour) pairs of nbr [S, k]: sample [V], global [V] (map rows),
    point [V] (rows of points) and points [P] (the distinct map rows)."""
    flat = nbr.reshape(-1)
    at = (flat >= 0).nonzero(as_tuple=True)[0]
    pair_global = flat.index_select(0, at)
    # Features enter C's first layer once per distinct point, not once per pair. The distinct
    # points come from a mask over the map (linear time) rather than torch.unique (a sort).
    used = torch.zeros(len(xyz), dtype=torch.bool, device=device).index_fill_(0, pair_global, True)
    return {"sample": torch.div(at, nbr.shape[1], rounding_mode="floor"), "global": pair_global,
            "point": (torch.cumsum(used, 0) - 1).index_select(0, pair_global),
            "points": used.nonzero(as_tuple=True)[0]}


def _first_hit(
    index: NeighbourIndex,
    rays_o: torch.Tensor,
    rays_d: torch.Tensor,
    z_range: tuple[float, float],
    radius: float,
    chunk: int,
) -> torch.Tensor:
    """Depth [R] of each ray's first sample (one every `radius`) with a point within `radius`,
    0 where there is none."""
    near, far = z_range
    n = max(1, math.ceil((far - near) / radius))
    t = near + radius * (torch.arange(n, device=rays_o.device, dtype=rays_o.dtype) + 0.5)
    out = []
    for i in range(0, len(rays_o), chunk):
        o, d = rays_o[i : i + chunk], rays_d[i : i + chunk]
        x = (o[:, None, :] + t[None, :, None] * d[:, None, :]).reshape(-1, 3)
        found = (index.query(x, 1, radius)[:, 0] >= 0).reshape(len(o), n).to(x.device)
        first = torch.argmax(found.to(torch.uint8), dim=1)  # first True (0 when none)
        out.append(torch.where(found.any(dim=1), t[first], 0.0))
    if not out:
        return torch.zeros(0, device=rays_o.device)
    return torch.cat(out)


def _depth_range_in_view(
    point_map: NeuralPointMap, intrinsics: Intrinsics, T_world_cam: torch.Tensor, radius: float
) -> tuple[float, float] | None:
    """z-range [near, far] of the map points that project into the image, widened by radius."""
    if len(point_map) == 0:
        return None
    T = T_world_cam.to(torch.float64)
    xyz = point_map.xyz_world().double()
    cam = (xyz - T[:3, 3]) @ T[:3, :3]  # R^T (x - t) for each row
    z = cam[:, 2]
    front = z > 1e-6
    u = intrinsics.fx * cam[:, 0] / z.clamp(min=1e-6) + intrinsics.cx
    v = intrinsics.fy * cam[:, 1] / z.clamp(min=1e-6) + intrinsics.cy
    margin = 2.0  # pixels: points just outside still reach rays at the border
    seen = front & (u > -0.5 - margin) & (u < intrinsics.width - 0.5 + margin) \
        & (v > -0.5 - margin) & (v < intrinsics.height - 0.5 + margin)
    if not bool(seen.any()):
        return None
    near = max(float(z[seen].min()) - radius, 1e-3)
    far = float(z[seen].max()) + radius
    return near, far

"""Speed figures of the neural point field on this machine, printed as JSON.

- neighbour query: 30k samples x K=8 within r=0.15 m among 50k surface points
  (scipy cKDTree with 1 and all workers, torch hash grid on the CPU);
- rendering a batch of 1500 rays (16 near + 4 uniform samples, K=8) from a box room whose
  map is the grid-filtered back-projection of one 320x240 depth image: forward and
  forward+backward, with the `gpu` preset's decoder widths and with small ones.

Usage: python bench/field.py [--threads N] [--repeat R]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import statistics
import time
from collections.abc import Callable

import numpy as np
import torch

from cpslam.common.camera import Intrinsics
from cpslam.common.config import load_config
from cpslam.common.field import (
    Decoders,
    FeatureCNN,
    NeighbourIndex,
    NeuralPointMap,
    camera_rays,
    patch_points,
    render_image,
    render_rays,
)
from cpslam.common.field_config import field_spec

ROOM_LO = np.array([-3.0, -1.5, -3.0])
ROOM_HI = np.array([3.0, 1.5, 3.0])
# The defaults' field (the paper's sampler and neighbours, the `gpu` preset's decoder widths)
# and the same with small decoders.
SPEC = field_spec(load_config("gpu", env={}).field)
SPECS = {
    "gpu": SPEC,
    "small": dataclasses.replace(SPEC, c_hidden=64, g_hidden=64, u_hidden=64),
}
KR = {"k": SPEC.k_neighbors, "radius": SPEC.radius}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--threads", type=int, default=None, help="torch threads (default: torch's)"
    )
    parser.add_argument("--repeat", type=int, default=7, help="timed repetitions (median kept)")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    report = {
        "machine": {"cpu": platform.processor() or platform.machine(),
                    "cores": os.cpu_count(), "torch_threads": torch.get_num_threads(),
                    "torch": torch.__version__,
                    "load_average_1min_at_start": round(os.getloadavg()[0], 2)},
        "neighbour_query_ms": bench_search(args.repeat),
        "render_1500_rays_ms": bench_render(args.repeat),
        "map_ms": bench_map(args.repeat),
    }
    print(json.dumps(report, indent=2))


def bench_search(repeat: int) -> dict[str, float]:
    gen = np.random.default_rng(0)
    points = torch.from_numpy(_surface_points(50_000, gen)).float()
    queries = points[torch.from_numpy(gen.integers(0, 50_000, 30_000))]
    queries = queries + torch.from_numpy(gen.normal(0.0, 0.08, (30_000, 3))).float()
    out = {}
    for name, backend, workers in (("kdtree_1_worker", "kdtree", 1),
                                   ("kdtree_all_workers", "kdtree", -1),
                                   ("torch_grid_cpu", "torch", -1)):
        index = NeighbourIndex(points, backend=backend, workers=workers)
        out[name] = _median_ms(lambda index=index: index.query(queries, 8, 0.15), repeat)
        out[name + "_with_build"] = _median_ms(
            lambda b=backend, w=workers: NeighbourIndex(points, b, w).query(queries, 8, 0.15),
            repeat,
        )
    return out


def bench_render(repeat: int) -> dict[str, dict[str, float]]:
    intr = Intrinsics(fx=256.0, fy=256.0, cx=159.5, cy=119.5, width=320, height=240)
    T_world_cam = torch.eye(4, dtype=torch.float64)
    depth = _box_depth(intr)
    point_map = _map_from_depth(intr, depth)
    gen = torch.Generator().manual_seed(0)
    u = torch.randint(0, intr.width, (1500,), generator=gen)
    v = torch.randint(0, intr.height, (1500,), generator=gen)
    rays_o, rays_d = camera_rays(intr, T_world_cam, u, v)
    depth_obs = torch.from_numpy(depth)[v, u]
    sampler = SPEC.sampler()
    out: dict[str, dict[str, float]] = {"scene": {"points": len(point_map)}}
    for name, spec in SPECS.items():
        dec = spec.decoders(seed=0)

        def forward(dec: Decoders = dec) -> None:
            with torch.no_grad():
                render_rays(point_map, dec, rays_o, rays_d, depth_obs, sampler, gen, **KR)

        def forward_backward(dec: Decoders = dec) -> None:
            res = render_rays(point_map, dec, rays_o, rays_d, depth_obs, sampler, gen, **KR)
            ((res["depth"] - depth_obs).abs().mean() + res["color"].mean()).backward()

        dec.rows_evaluated = 0
        forward()
        out[name] = {
            "pairs_per_batch": dec.rows_evaluated,
            "forward": _median_ms(forward, repeat),
            "forward_backward": _median_ms(forward_backward, repeat),
        }
    return out


def bench_map(repeat: int) -> dict[str, float]:
    """Adding 5k points to a 50k-point map (grid filter included) and a full-image render."""
    gen = np.random.default_rng(1)
    xyz = torch.from_numpy(_surface_points(55_000, gen)).float()
    base = NeuralPointMap(feature_dim=32, cell_size=0.05)
    base.set_keyframe_poses(0, np.eye(4))
    base.add_points(xyz[:50_000], 0, torch.zeros(50_000, 32),
                    torch.zeros(50_000, 3, dtype=torch.uint8))

    def add() -> None:
        point_map = base.subset(torch.ones(len(base), dtype=torch.bool))
        point_map.add_points(xyz[50_000:], 0, torch.zeros(5_000, 32),
                             torch.zeros(5_000, 3, dtype=torch.uint8))

    intr = Intrinsics(fx=256.0, fy=256.0, cx=159.5, cy=119.5, width=320, height=240)
    point_map = _map_from_depth(intr, _box_depth(intr))
    dec = SPECS["small"].decoders(seed=0)
    T_world_cam = torch.eye(4, dtype=torch.float64)
    return {
        "base_points": len(base),
        "add_5k_points_to_map": _median_ms(add, repeat),
        "render_image_320x240_small": _median_ms(
            lambda: render_image(point_map, dec, intr, T_world_cam, SPEC.sampler(perturb=False),
                                 **KR), max(1, repeat // 3)
        ),
    }


def _surface_points(n: int, gen: np.random.Generator) -> np.ndarray:
    """n points uniformly on the six walls of the box room."""
    size = ROOM_HI - ROOM_LO
    areas = np.array([size[1] * size[2], size[0] * size[2], size[0] * size[1]]).repeat(2)
    face = gen.choice(6, size=n, p=areas / areas.sum())
    xyz = ROOM_LO + gen.random((n, 3)) * size
    axis = face // 2
    xyz[np.arange(n), axis] = np.where(face % 2 == 0, ROOM_LO[axis], ROOM_HI[axis])
    return xyz


def _box_depth(intr: Intrinsics) -> np.ndarray:
    """z-depth of the box room's walls seen from the origin (looking along +z)."""
    v, u = np.mgrid[0 : intr.height, 0 : intr.width]
    d = intr.pixel_rays(u, v).reshape(*u.shape, 3)
    with np.errstate(divide="ignore"):
        t = np.where(d > 0, ROOM_HI / d, np.where(d < 0, ROOM_LO / d, np.inf))
    return t.min(-1).astype(np.float32)


def _map_from_depth(intr: Intrinsics, depth: np.ndarray) -> NeuralPointMap:
    """Paper-style map: centres of 4x4 patches back-projected, CNN features, grid filter."""
    rgb = np.full((intr.height, intr.width, 3), 128, dtype=np.uint8)
    xyz, feats, colors = patch_points(rgb, depth, intr, np.eye(4), FeatureCNN(32), patch=4)
    point_map = NeuralPointMap(feature_dim=32, cell_size=0.14)
    point_map.set_keyframe_poses(0, np.eye(4))
    point_map.add_points(xyz, 0, feats, colors)
    return point_map


def _median_ms(fn: Callable[[], object], repeat: int) -> float:
    fn()  # warm-up
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return round(1000.0 * statistics.median(times), 2)


if __name__ == "__main__":
    main()

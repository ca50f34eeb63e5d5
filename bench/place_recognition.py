"""Place recognition figures: recall@1 and recall@5 of global descriptors on true revisits,
printed as JSON.

A true revisit of a query frame is another frame whose ground-truth camera is within 0.5 m and
30 degrees of it and more than 100 frames away (`--min-gap`); frames within the gap are never
retrieved. Frames of different agents of a collection are pooled and always count as far apart.
Recall@k is the fraction of queries that have a true revisit and find one among their k most
similar frames; `chance` is the recall a random ranking would get. Per variant also: `pair_ap`,
the average precision of all eligible pairs ranked by similarity (what a similarity threshold
sees), cosine-similarity quantiles of true revisits and of the other pairs (to set the loop
thresholds), descriptor length, ms per descriptor (batches of 16, resize included) and start-up
time (backbone load plus, for untrained NetVLAD, k-means over procedural images).

Sequences: the 7-Scenes red kitchen excerpt (`--kitchen`, default ../shared/data/
7scenes-kitchen-0-299, every frame) and synthetic collections (`--synth DIR`: one sequence in
Replica layout or a collection of agent_* sequences, repeatable; `--synth-generate` renders a
two-agent apartment loop into a temporary folder with cpslam.tools.synth.generate).

Variants are aggregation:layer:param with param = clusters (netvlad) or p (gem).

Usage: python bench/place_recognition.py [--synth-generate] [--synth DIR ...] [--step 2]
       [--variants gem:stage6:1 netvlad:stage6:8] [--threads N] [--relaxed-gap 30]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from odometry_runs import KITCHEN

from cpslam.agent.descriptor import DescriptorExtractor
from cpslam.common.datasets import open_sequence

REPO = Path(__file__).resolve().parents[1]
_AGENT_OFFSET = 10**9  # added to frame indices of agent i, so agents never fall within the gap
DEFAULT_VARIANTS = [
    "gem:stage6:1",
    "gem:stage6:3",
    "gem:head:1",
    "gem:head:3",
    "netvlad:stage6:8",
    "netvlad:stage5:32",
    "netvlad:head:32",
]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--kitchen", type=Path, default=KITCHEN, help="7-Scenes excerpt")
    parser.add_argument("--no-kitchen", action="store_true", help="skip the 7-Scenes excerpt")
    parser.add_argument("--kitchen-step", type=int, default=1, help="every n-th kitchen frame")
    parser.add_argument(
        "--synth",
        type=Path,
        action="append",
        default=[],
        help="synthetic sequence or collection directory (repeatable)",
    )
    parser.add_argument(
        "--synth-generate",
        action="store_true",
        help="render a two-agent synthetic apartment loop to a temporary folder",
    )
    parser.add_argument("--synth-frames", type=int, default=600, help="frames per agent")
    parser.add_argument("--synth-seed", type=int, default=0)
    parser.add_argument("--step", type=int, default=2, help="every n-th synthetic frame")
    parser.add_argument(
        "--variants",
        nargs="+",
        default=DEFAULT_VARIANTS,
        help="aggregation:layer:param, param = clusters (netvlad) or p (gem)",
    )
    parser.add_argument("--image-size", type=int, default=224)
    parser.add_argument("--max-dist", type=float, default=0.5, help="metres")
    parser.add_argument("--max-angle", type=float, default=30.0, help="degrees")
    parser.add_argument("--min-gap", type=int, default=100, help="frames")
    parser.add_argument(
        "--relaxed-gap",
        type=int,
        default=None,
        help="also report recall with this smaller gap (labelled relaxed)",
    )
    parser.add_argument("--threads", type=int, default=None, help="torch threads")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)

    sequences: dict[str, tuple[list[Path], int]] = {}
    warnings = []
    if not args.no_kitchen:
        if args.kitchen.is_dir():
            sequences[args.kitchen.name] = ([args.kitchen], args.kitchen_step)
        else:
            warnings.append(f"7-Scenes excerpt not found at {args.kitchen}: skipped")
    tmp = None
    if args.synth_generate:
        tmp = tempfile.TemporaryDirectory(prefix="cpslam-pr-")
        dirs = generate_apartment(Path(tmp.name), args.synth_frames, args.synth_seed)
        sequences[f"synthetic-apartment-seed{args.synth_seed}"] = (dirs, args.step)
    for folder in args.synth:
        agents = sorted(folder.glob("agent_*"))
        sequences[f"synthetic:{folder.name}"] = (agents or [folder], args.step)

    gaps = {"": args.min_gap}
    if args.relaxed_gap is not None:
        gaps["relaxed_"] = args.relaxed_gap
    report: dict = {
        "machine": {
            "cpu": platform.processor() or platform.machine(),
            "cores": os.cpu_count(),
            "torch_threads": torch.get_num_threads(),
            "torch": torch.__version__,
        },
        "criterion": {
            "max_dist_m": args.max_dist,
            "max_angle_deg": args.max_angle,
            "min_gap_frames": args.min_gap,
            "relaxed_gap_frames": args.relaxed_gap,
            "image_size": args.image_size,
        },
        "warnings": warnings,
        "sequences": {},
    }
    try:
        for name, (dirs, step) in sequences.items():
            images, T_world_cam, indices = load_frames(dirs, step)
            pairs = {
                tag: revisits(T_world_cam, indices, args.max_dist, args.max_angle, gap)
                for tag, gap in gaps.items()
            }
            seq: dict = {"agents": len(dirs), "frames": len(images), "step": step}
            for tag, (true, eligible) in pairs.items():
                seq[f"{tag}queries"] = int(true.any(axis=1).sum())
                seq[f"{tag}chance"] = chance(true, eligible)
            seq["variants"] = {}
            for spec in args.variants:
                desc, info = describe(images, spec, args.image_size)
                for tag, (true, eligible) in pairs.items():
                    info[f"{tag}result"] = recall(desc @ desc.T, true, eligible)
                seq["variants"][spec] = info
            report["sequences"][name] = seq
    finally:
        if tmp is not None:
            tmp.cleanup()
    print(json.dumps(report, indent=2))


def load_frames(dirs: list[Path], step: int) -> tuple[list[np.ndarray], np.ndarray, np.ndarray]:
    """RGB images, ground-truth poses [N, 4, 4] and frame indices [N] of every step-th frame of
    each sequence, pooled; each agent's indices are offset so that agents are always far apart."""
    images: list[np.ndarray] = []
    poses, indices = [], []
    for agent, folder in enumerate(dirs):
        sequence = open_sequence(folder, frames=slice(None, None, step))
        T_world_cam = sequence.gt_poses()
        if T_world_cam is None:
            raise ValueError(f"{folder}: the benchmark needs ground-truth poses")
        images += [frame.rgb for frame in sequence]
        poses.append(T_world_cam)
        indices.append(np.asarray(sequence.indices, np.int64) + agent * _AGENT_OFFSET)
    return images, np.concatenate(poses), np.concatenate(indices)


def generate_apartment(folder: Path, frames: int, seed: int) -> list[Path]:
    """A two-agent synthetic apartment collection with loops, rendered by the synthesizer."""
    from cpslam.tools.synth import generate

    result = generate(
        folder / "apartment", scene="apartment", agents=2, frames=frames, loop=True, seed=seed
    )
    return list(result.agent_dirs)


def revisits(
    T_world_cam: np.ndarray,
    indices: np.ndarray,
    max_dist: float,
    max_angle_deg: float,
    min_gap: int,
) -> tuple[np.ndarray, np.ndarray]:
    """(true [N, N], eligible [N, N]): pairs that are true revisits, pairs that may be retrieved
    (more than min_gap frames apart)."""
    t = T_world_cam[:, :3, 3]
    R = T_world_cam[:, :3, :3]
    dist = np.linalg.norm(t[:, None] - t[None], axis=-1)
    cos = (np.einsum("iab,jab->ij", R, R) - 1.0) / 2.0
    angle = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    eligible = np.abs(indices[:, None] - indices[None]) > min_gap
    true = (dist < max_dist) & (angle < max_angle_deg) & eligible
    return true, eligible


def recall(
    sim: np.ndarray, true: np.ndarray, eligible: np.ndarray, ks: tuple[int, ...] = (1, 5)
) -> dict:
    """Recall@k over queries with a true revisit, plus similarity quantiles of the pairs."""
    sim = np.where(eligible, sim, -np.inf)
    queries = np.flatnonzero(true.any(axis=1))
    out: dict = {"queries": int(len(queries))}
    if len(queries) == 0:
        return out
    order = np.argsort(-sim[queries], axis=1, kind="stable")
    for k in ks:
        hits = np.take_along_axis(true[queries], order[:, :k], axis=1).any(axis=1)
        out[f"recall@{k}"] = round(float(hits.mean()), 4)
    upper = np.triu(eligible, 1)
    ranked = true[upper][np.argsort(-sim[upper], kind="stable")]
    precision = np.cumsum(ranked) / np.arange(1, len(ranked) + 1)
    out["pair_ap"] = round(float((precision * ranked).sum() / max(ranked.sum(), 1)), 4)
    pos, neg = sim[upper & true], sim[upper & ~true]
    q = [0.05, 0.5, 0.95]
    out["sim_true_q05_50_95"] = [round(float(v), 3) for v in np.quantile(pos, q)]
    if len(neg):
        out["sim_other_q05_50_95"] = [round(float(v), 3) for v in np.quantile(neg, q)]
    return out


def chance(true: np.ndarray, eligible: np.ndarray, ks: tuple[int, ...] = (1, 5)) -> dict:
    """Expected recall@k of a random ranking."""
    queries = np.flatnonzero(true.any(axis=1))
    if len(queries) == 0:
        return {}
    n = eligible[queries].sum(axis=1)
    t = true[queries].sum(axis=1)
    out = {}
    for k in ks:
        miss = [
            math.comb(int(ni - ti), k) / math.comb(int(ni), k) if ni >= k else 0.0
            for ni, ti in zip(n, t, strict=True)
        ]
        out[f"recall@{k}"] = round(float(1.0 - np.mean(miss)), 4)
    return out


def describe(images: list[np.ndarray], spec: str, image_size: int) -> tuple[np.ndarray, dict]:
    """Descriptors [N, D] of the images by the variant `spec`, and its timings."""
    try:
        aggregation, layer, param = spec.split(":")
        value = float(param)
    except ValueError as err:
        raise SystemExit(f"variant {spec!r}: expected aggregation:layer:param") from err
    kwargs = {"clusters": int(value)} if aggregation == "netvlad" else {"gem_p": value}
    start = time.perf_counter()
    extractor = DescriptorExtractor(
        aggregation=aggregation, layer=layer, image_size=image_size, **kwargs
    )
    startup = time.perf_counter() - start
    extractor.compute_batch(images[:4])  # warm-up
    start = time.perf_counter()
    desc = extractor.compute_batch(images)
    per = (time.perf_counter() - start) / len(images)
    return desc, {
        "dim": extractor.dim,
        "ms_per_descriptor": round(1000 * per, 1),
        "startup_s": round(startup, 2),
    }


if __name__ == "__main__":
    main()

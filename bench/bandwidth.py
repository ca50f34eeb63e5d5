"""Agent -> server bandwidth before and after the compact link, with the joint ATE of both.

    python bench/bandwidth.py                          # the demo's scene: 2 agents x 100 frames
    python bench/bandwidth.py --frames 0:150:3 --preset tiny          # a quick look
    python bench/bandwidth.py --variants before after no-decoder-delta
    python bench/bandwidth.py --variants after coalesce2 --scene room --scene-seed 7
    python bench/bandwidth.py --variants after --real          # real 7-Scenes frames

The demo's setup run in-process (`cpslam run`'s lock-step loop on the in-memory bus, the same
nodes and codec as over Zenoh): `cpslam dataset synth --scene apartment --agents 2
--num-frames 300` (320x240, cached under runs/bench-data/), every third frame, keyframes every
10 processed frames (`--scene`, `--scene-seed`: another synthetic scene, for data the
defaults were not tuned on; `--noise`: with Kinect-like depth noise; `--real`: the shared
7-Scenes kitchen frames as two agents, `--real-split` slices, real depth noise and texture).
Variants (the `link` section, docs/configuration.md):

- before: every mapping call a delta of every point whose float16 features changed, full
  float32 decoders, no compression (the wire format before the link section, but for the
  float16 keyframe descriptors of protocol 4);
- after: the link section's defaults (coalesced deltas, relative change threshold, int8
  features, int8 decoder deltas, zstd);
- no-decoder-delta: after with full float32 decoders (the ATE with and without decoder deltas);
- coalesce2: after with a sub-map delta every 2 mapping calls instead of 4;
- threshold2: after with ``link.feature_threshold`` 0.2 instead of 0.1;
- spacing1, spacing2, spacing3: after with ``loop.spacing`` 1 (every loop candidate verified,
  its keyframe images pulled), 2 or 3 (candidates within 1 or 2 keyframes of a verified pair
  skipped);
- images-half, images-half-spacing3: after with keyframe images pulled at half the processed
  width and height (``loop.image_scale`` 0.5), the second also with ``loop.spacing`` 3;
- no-feature-rows: after with every point resent whole (``link.feature_rows`` off);
  images-half-no-feature-rows: both;
- images-0.4: after with keyframe images at 0.4 of the processed size;
- no-refine, images-half-no-refine: without the rendering refinement of loop poses
  (``loop.refine`` off), at full and at half image size;
- no-finetune, images-half-no-finetune: without the server's fine-tunes on keyframe images
  (``federation.finetune_iters`` and ``refinement.finetune_iters`` 0), at full and half size;
- images-half-info2: half size with loop edges weighted 0.2 instead of 0.09
  (``loop.information_scale``);
- bits6, bits5, bits4: sub-map feature codes of that many bits (``link.feature_bits``);
  jpeg80: keyframe colour at JPEG quality 80; images-half-bits5, images-half-jpeg80-bits5:
  those together;
- noisy-half, noisy-full: keyframe images at half the processed size once merged when the
  agent's depth is noisy (``link.noisy_image_scale`` 0.5, the default), or as asked (1);
- depth-mm, depth0.5, depth1, depth1.5: keyframe depth in millimetres, or as inverse depth in
  steps of 0.5, 1 or 1.5 mm x depth² (``link.depth_step_mm_per_m2``); images-half-depth1-bits6:
  half-size images, inverse depth at 1 and 6-bit features together;
- step-fixed, noisy-half-step-fixed: the depth step fixed (``link.depth_step_noise_ratio`` 0)
  at full size and with noisy-half; step-noise1, step-noise3: that ratio at 1 and 3;
- decoder-int8, decoder-f16: full decoder weights as int8 rows with one scale each, or as
  float16 (``link.decoder_full_codec``);
- held2, held1: points the server holds resent with every second sub-map delta only
  (``link.held_every_deltas`` 2, the default), or with each (1);
- depth-png: keyframe depth as 16-bit PNG instead of zstd-delta (``link.depth_codec``);
  noisy-half-jpeg80: noisy-half with colour at JPEG quality 80.

Per variant and agent: bytes per second of sensor time per message type (the server's
counters in metrics.json), the joint se3 ATE of both global trajectories, the merge time, and
what the server's copy of each agent's map costs in rendering: each agent's final map rendered
at its keyframes with its own features and with the features the server holds (the link's
mirror of what it sent, as the server decodes it), compared as PSNR and depth difference.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
from odometry_runs import KITCHEN  # noqa: E402

VARIANTS = {
    "before": [
        "link.submap_every_mappings=1",
        "link.feature_threshold=0",
        "link.feature_codec=float16",
        "link.decoder_delta=false",
        "link.zstd_level=0",
        "link.feature_rows=false",
    ],
    "after": [],
    "no-decoder-delta": ["link.decoder_delta=false"],
    "coalesce2": ["link.submap_every_mappings=2"],
    "threshold2": ["link.feature_threshold=0.2"],
    "spacing1": ["loop.spacing=1"],
    "spacing2": ["loop.spacing=2"],
    "spacing3": ["loop.spacing=3"],
    "images-half": ["loop.image_scale=0.5"],
    "images-half-spacing3": ["loop.image_scale=0.5", "loop.spacing=3"],
    "no-feature-rows": ["link.feature_rows=false"],
    "images-half-no-feature-rows": ["loop.image_scale=0.5", "link.feature_rows=false"],
    "images-0.4": ["loop.image_scale=0.4"],
    "no-refine": ["loop.refine=false"],
    "images-half-no-refine": ["loop.image_scale=0.5", "loop.refine=false"],
    "no-finetune": ["federation.finetune_iters=0", "refinement.finetune_iters=0"],
    "images-half-no-finetune": ["loop.image_scale=0.5", "federation.finetune_iters=0",
                                "refinement.finetune_iters=0"],
    "images-half-info2": ["loop.image_scale=0.5", "loop.information_scale=0.2"],
    "bits6": ["link.feature_bits=6"],
    "bits5": ["link.feature_bits=5"],
    "bits4": ["link.feature_bits=4"],
    "jpeg80": ["link.jpeg_quality=80"],
    "images-half-bits5": ["loop.image_scale=0.5", "link.feature_bits=5"],
    "images-half-jpeg80-bits5": ["loop.image_scale=0.5", "link.jpeg_quality=80",
                                 "link.feature_bits=5"],
    "noisy-half": ["link.noisy_image_scale=0.5"],
    "noisy-full": ["link.noisy_image_scale=1"],
    "held2": ["link.held_every_deltas=2"],
    "held1": ["link.held_every_deltas=1"],
    "depth-mm": ["link.depth_step_mm_per_m2=0"],
    "depth0.5": ["link.depth_step_mm_per_m2=0.5"],
    "depth1": ["link.depth_step_mm_per_m2=1"],
    "depth1.5": ["link.depth_step_mm_per_m2=1.5"],
    "images-half-depth1-bits6": ["loop.image_scale=0.5", "link.depth_step_mm_per_m2=1",
                                 "link.feature_bits=6"],
    "step-fixed": ["link.depth_step_noise_ratio=0"],
    "noisy-half-step-fixed": ["link.noisy_image_scale=0.5", "link.depth_step_noise_ratio=0"],
    "step-noise1": ["link.depth_step_noise_ratio=1"],
    "step-noise3": ["link.depth_step_noise_ratio=3"],
    "decoder-int8": ["link.decoder_full_codec=int8"],
    "decoder-f16": ["link.decoder_full_codec=float16"],
    "depth-png": ["link.depth_codec=png"],
    "noisy-half-jpeg80": ["link.noisy_image_scale=0.5", "link.jpeg_quality=80"],
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="cpu")
    parser.add_argument("--frames", default="0:300:3", help="frames of each agent's walk")
    parser.add_argument(
        "--variants", nargs="+", default=["before", "after"], choices=sorted(VARIANTS)
    )
    parser.add_argument(
        "--render-views",
        type=int,
        default=3,
        help="keyframes per agent rendered for the server-copy comparison",
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--scene", default="apartment", choices=["apartment", "room"])
    parser.add_argument("--scene-seed", type=int, default=0, help="seed of the generated scene")
    parser.add_argument("--noise", action="store_true", help="Kinect-like depth noise in the scene")
    parser.add_argument("--real", action="store_true", help="the 7-Scenes kitchen frames instead")
    parser.add_argument("--real-split", default="0:150:3,150:300:3",
                        help="frame slices of the two real agents, comma-separated")
    parser.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "bandwidth.json")
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)
    from benchinfo import bench_header

    report = {
        **bench_header("bandwidth", sys.argv),
        "preset": args.preset,
        "frames": args.frames,
        "seed": args.seed,
        "scene": "7-Scenes kitchen" if args.real else args.scene,
        "scene_seed": None if args.real else args.scene_seed,
        "noise": None if args.real else args.noise,
        "real_split": args.real_split if args.real else None,
        "variants": {},
    }
    for name in args.variants:
        t0 = time.perf_counter()
        report["variants"][name] = run_variant(
            args.preset, args.frames, VARIANTS[name], args.seed, args.render_views,
            args.scene, args.scene_seed, args.real_split.split(",") if args.real else None,
            args.noise)
        report["variants"][name]["wall_s"] = round(time.perf_counter() - t0, 1)
        print(f"{name}: {json.dumps(report['variants'][name]['summary'])}", flush=True)
    v = report["variants"]
    if "before" in v and "after" in v:
        b, a = v["before"]["summary"], v["after"]["summary"]
        report["ratio_after_over_before"] = {
            "bytes_per_sensor_s": round(
                a["bytes_per_sensor_s_mean"] / b["bytes_per_sensor_s_mean"], 4
            ),
            "joint_ate": (
                round(a["joint_ate_cm"] / b["joint_ate_cm"], 4)
                if a["joint_ate_cm"] and b["joint_ate_cm"]
                else None
            ),
        }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=1) + "\n")
    print(f"wrote {args.out}")


def run_variant(preset: str, frames: str, sets: list[str], seed: int, views: int,
                scene: str = "apartment", scene_seed: int = 0,
                real_split: list[str] | None = None, noise: bool = False) -> dict:
    import tempfile

    from cpslam.agent.standalone import open_for_config
    from cpslam.common.config import load_config
    from cpslam.demo import scene_data
    from cpslam.run import run_collab

    cfg = load_config(preset, overrides=["keyframes.every=10", f"run.seed={seed}", *sets], env={})
    if real_split:
        seqs = [open_for_config(cfg, KITCHEN, frames=f) for f in real_split]
    else:
        paths = scene_data(
            ROOT / "runs" / "bench-data", scene, 2, 300, 320, 240, scene_seed, show_progress=False,
            noise=noise)
        seqs = [open_for_config(cfg, p, frames=frames) for p in paths]
    with tempfile.TemporaryDirectory() as tmp:
        result = run_collab(cfg, seqs, Path(tmp) / "run", "cpu", show_progress=False)
        metrics = json.loads((Path(tmp) / "run" / "metrics.json").read_text())
    per_agent = {}
    for aid, entry in metrics["bus"]["per_agent"].items():
        per_agent[aid] = {
            "sensor_s": round(entry.get("sensor_s", 0.0), 3),
            "bytes": entry["from_agent_bytes"],
            "bytes_per_sensor_s": round(entry.get("from_agent_bytes_per_sensor_s", 0.0), 1),
            "by_type": {
                t: {
                    "messages": c["messages"],
                    "bytes": c["bytes"],
                    "bytes_per_sensor_s": round(c.get("bytes_per_sensor_s", 0.0), 1),
                }
                for t, c in sorted(entry["from_agent"].items())
            },
        }
    for aid, node in result.nodes.items():
        per_agent.setdefault(aid, {})["server_copy"] = server_copy_error(cfg, node, views)
    ev = result.evaluation or {}
    joint = ev.get("global_joint_se3_rmse_m")
    rates = [a["bytes_per_sensor_s"] for a in per_agent.values() if "bytes_per_sensor_s" in a]
    return {
        "sets": sets,
        "agents": per_agent,
        "summary": {
            "bytes_per_sensor_s_mean": round(float(np.mean(rates)), 1) if rates else None,
            "joint_ate_cm": round(100 * joint, 3) if joint is not None else None,
            "origin_ate_cm": {
                a: round(100 * v, 3) for a, v in (ev.get("global_origin_rmse_m") or {}).items()
            },
            "merge_time_s": ev.get("merge_time_s"),
            "loops": {k: metrics.get("loops", {}).get(k) for k in ("found", "accepted", "skipped")},
            "merged": ev.get("merged"),
        },
    }


def server_copy_error(cfg, node, views: int) -> dict:
    """Each agent's own map rendered at `views` keyframes with its features and with the
    server's copy of them: colour PSNR of one against the other, mean |depth difference|,
    and the features' relative RMS error."""
    import torch

    from cpslam.common.field.renderer import render_image
    from cpslam.common.field_config import field_spec

    odo, mirror = node.odometry, node.link.mirror
    pm = odo.point_map
    own = (pm.agent_id == odo.agent_id).nonzero(as_tuple=True)[0]
    ids = pm.point_id[own].cpu().numpy()
    pos = np.minimum(np.searchsorted(mirror.ids, ids), max(len(mirror.ids) - 1, 0))
    held = len(mirror.ids) > 0 and bool((mirror.ids[pos] == ids).all())
    if not held:
        return {"skipped": "the server's copy lacks some points"}
    local = pm.features.detach().clone()
    server = local.clone()
    # the server stores float16 of what it decoded
    server[own] = torch.from_numpy(mirror.features[pos].astype(np.float16).astype(np.float32))
    rel_rms = float((server[own] - local[own]).norm() / local[own].norm().clamp(min=1e-12))
    f = cfg.field
    sampler = field_spec(f).sampler(perturb=False)
    kfs = list(odo.keyframes)
    pick = np.unique(np.linspace(0, len(kfs) - 1, views).round().astype(int))
    psnr, depth_cm = [], []
    intr = odo.keyframes.intrinsics
    for i in pick:
        T = torch.as_tensor(kfs[i].T_world_cam, dtype=torch.float64)
        renders = []
        for feats in (local, server):
            pm.set_features(torch.arange(len(pm)), feats)
            with torch.no_grad():
                out = render_image(
                    pm,
                    odo.decoders,
                    intr,
                    T,
                    sampler,
                    k=f.k_neighbors,
                    radius=f.radius,
                    step=2,
                    backend=f.neighbour_backend,
                )
            renders.append(out)
        pm.set_features(torch.arange(len(pm)), local)
        a, b = (r["color"].clamp(0, 1).double() for r in renders)
        mse = float(((a - b) ** 2).mean())
        psnr.append(99.0 if mse == 0 else 10 * np.log10(1.0 / mse))
        both = (renders[0]["depth"] > 0) & (renders[1]["depth"] > 0)
        if both.any():
            diff = (renders[0]["depth"] - renders[1]["depth"]).abs()[both]
            depth_cm.append(100 * float(diff.mean()))
    return {
        "feature_rel_rms": round(rel_rms, 5),
        "views": len(pick),
        "psnr_server_vs_local_db": round(float(np.mean(psnr)), 2),
        "depth_diff_cm": round(float(np.mean(depth_cm)), 4) if depth_cm else None,
    }


if __name__ == "__main__":
    main()

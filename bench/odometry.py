"""Single-agent odometry quality and speed, printed as a table and as JSON.

- synthetic: `cpslam dataset synth --scene room --loop --frames 300` at 320x240 (generated once
  and cached under runs/bench-data/), ATE with origin and se3 alignment;
- real: ../shared/data/7scenes-kitchen-0-299 processed at camera.downscale (320x240 for the
  cpu preset), ATE with se3 alignment, next to Open3D's frame-to-frame RGB-D odometry
  (`compute_rgbd_odometry`, hybrid term, chained) at the same resolution and at 640x480.
  Its ground truth jumps 36 mm / 1.4 deg between frames 121 and 122 (a step the camera did
  not make: both estimators measure 4-8 mm there), so the real sequence also gets the ATE over
  the pieces between such jumps, each aligned on its own (`cpslam.common.eval.segments`), for
  both methods, with its own ratio.

Timings are wall-clock on this machine with `run.num_threads` torch threads (`auto` in the
cpu preset: every usable core for one run, the cores divided among the runs with `--jobs`);
on CUDA they are synchronised per frame. Mapping is reported per call (what the paper calls
a mapping step: one round of optimisation iterations) and per optimisation iteration. The
paper's figures on an RTX 3090 (tracking 0.30 s per frame, mapping 10.1 s per step) are
printed next to ours; compare them with the `paper` preset on a GPU (`--device cuda`).

Both sequences also get the relative pose error over 1 and 10 frames (RPE: jitter and local
drift, independent of the alignment). One seed is one sample: `--seeds 0 1 2` runs every
sequence once per seed (`run.seed`: pixel draws and ray jitter) and adds the mean and the
worst, and `--jobs 2` runs two of those at once (each on half the cores; timings then
include the other job's load).

Usage: python bench/odometry.py [--preset cpu] [--device auto|cpu|cuda[:i]] [--frames N]
       [--only synth|real] [--seeds S ...] [--jobs N] [--set a.b=v ...] [--json PATH]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context
from pathlib import Path

import numpy as np
import torch

from cpslam.agent.odometry import Odometry
from cpslam.common.camera import Intrinsics, resize_rgbd
from cpslam.common.config import load_config
from cpslam.common.datasets import open_sequence
from cpslam.common.device import configure_torch, resolve_device
from cpslam.common.eval import evaluate_ate, evaluate_rpe, reference_jumps, segmented_ate

REPO = Path(__file__).resolve().parents[1]
SYNTH_DIR = REPO / "runs" / "bench-data" / "room-loop-300-320x240"
# The CP-SLAM paper's timings on an RTX 3090: tracking per frame, mapping per mapping step.
PAPER = {"tracking_s_per_frame": 0.30, "mapping_s_per_call": 10.1}
KITCHEN = REPO.parent / "shared" / "data" / "7scenes-kitchen-0-299"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="cpu")
    parser.add_argument("--frames", type=int, default=300, help="frames of each sequence")
    parser.add_argument("--only", choices=("synth", "real"), default=None)
    parser.add_argument("--set", nargs="*", default=[], help="config overrides a.b=value")
    parser.add_argument("--seeds", type=int, nargs="*", default=None,
                        help="run.seed values, one run each (default: the config's)")
    parser.add_argument("--jobs", type=int, default=1, help="runs at once (processes)")
    parser.add_argument("--json", type=Path, default=None, help="also write the JSON here")
    parser.add_argument("--device", default="cpu", help="auto, cpu, cuda or cuda:N")
    args = parser.parse_args()
    cfg = load_config(args.preset, overrides=args.set, env={})
    device = resolve_device(args.device)
    seeds = args.seeds or [cfg.run.seed]
    report: dict = {
        "machine": {"cpu": platform.processor() or platform.machine(), "cores": os.cpu_count(),
                    "torch": torch.__version__,
                    "load_average_1min_at_start": round(os.getloadavg()[0], 2)},
        "preset": args.preset, "overrides": args.set, "frames": args.frames, "device": device,
        "seeds": seeds, "jobs": args.jobs,
        "gpu": torch.cuda.get_device_name(device) if device.startswith("cuda") else None,
        "paper_rtx3090": PAPER,
    }
    kinds = [k for k in ("synth", "real") if args.only in (None, k)]
    if "real" in kinds and not KITCHEN.is_dir():
        report["real"] = {"skipped": f"no data at {KITCHEN}"}
        kinds.remove("real")
    if "synth" in kinds:
        _ensure_synthetic()
    share = max(1, min(args.jobs, len(kinds) * len(seeds)))  # runs side by side share the cores
    report["machine"]["torch_threads"] = configure_torch(cfg.run.num_threads,
                                                         cfg.run.deterministic, share)
    jobs = [(args.preset, args.set, kind, seed, args.frames, device, share)
            for kind in kinds for seed in seeds]
    if args.jobs > 1 and len(jobs) > 1:
        with ProcessPoolExecutor(args.jobs, mp_context=get_context("spawn")) as pool:
            results = list(pool.map(_run_job, jobs))
    else:
        results = [_run_job(job) for job in jobs]
    for kind in kinds:
        runs = [r for job, r in zip(jobs, results, strict=True) if job[2] == kind]
        name = "synthetic" if kind == "synth" else "real"
        report[name] = _summarise(runs, seeds)
        if kind == "real":
            _compare_open3d(report[name], cfg, args.frames)
    print_table(report)
    text = json.dumps(report, indent=2)
    print(text)
    if args.json:
        args.json.write_text(text + "\n")


def _ensure_synthetic() -> None:
    if not (SYNTH_DIR / "agent_0" / "traj.txt").is_file():
        from cpslam.common.synth import generate

        generate(SYNTH_DIR, scene="room", frames=300, width=320, height=240, loop=True,
                 overwrite=True)


def _run_job(job: tuple) -> dict:
    """One odometry run (in a worker process when --jobs > 1)."""
    preset, overrides, kind, seed, frames, device, share = job
    cfg = load_config(preset, overrides=[*overrides, f"run.seed={seed}"], env={})
    configure_torch(cfg.run.num_threads, cfg.run.deterministic, share)
    if kind == "synth":
        seq = open_sequence(SYNTH_DIR / "agent_0", frames=slice(0, frames))
        # The synthetic data is already 320x240: process it at its own size.
        return run_odometry(cfg, seq, factor=1.0, aligns=("origin", "se3"), device=device)
    seq = open_sequence(KITCHEN, frames=slice(0, frames))
    return run_odometry(cfg, seq, factor=cfg.camera.downscale, aligns=("se3",), device=device,
                        pieces=True)


def _summarise(runs: list[dict], seeds: list[int]) -> dict:
    """The first seed's run at the top level (as with one seed), every seed's accuracy under
    "per_seed", and their mean and worst."""
    out = dict(runs[0])
    keys = [k for k in runs[0] if k.startswith(("ate_", "rpe"))]
    out["per_seed"] = [{"seed": seed, **{k: r[k] for k in keys}, "mean_s_per_frame":
                        r["mean_s_per_frame"]} for seed, r in zip(seeds, runs, strict=True)]
    if len(runs) > 1:
        out["mean_over_seeds"] = {k: round(float(np.mean([r[k] for r in runs])), 3)
                                  for k in [*keys, "mean_s_per_frame"]}
        out["worst_over_seeds"] = {k: max(r[k] for r in runs) for k in keys}
    return out


def _compare_open3d(out: dict, cfg, frames: int) -> None:
    seq = open_sequence(KITCHEN, frames=slice(0, frames))
    out["open3d"] = {}
    for factor in sorted({cfg.camera.downscale, 1.0}):
        size = "x".join(map(str, _size(seq.intrinsics, factor)))
        out["open3d"][size] = open3d_odometry(seq, factor, cfg.camera.depth_max)
    for key, suffix in (("ate_se3_cm", ""), ("ate_se3_pieces_cm", "_pieces")):
        best = min(v[key] for v in out["open3d"].values())
        out[f"ratio{suffix}_ours_over_best_open3d"] = round(out[key] / best, 3)
        if "mean_over_seeds" in out:
            out[f"ratio{suffix}_mean_over_best_open3d"] = round(
                out["mean_over_seeds"][key] / best, 3)
            out[f"ratio{suffix}_worst_over_best_open3d"] = round(
                out["worst_over_seeds"][key] / best, 3)


def run_odometry(cfg, seq, factor: float, aligns: tuple[str, ...], device: str = "cpu",
                 pieces: bool = False) -> dict:
    """One run; with `pieces`, also the se3 ATE over the pieces between ground-truth jumps."""
    intrinsics = seq.intrinsics.scaled(factor) if factor != 1.0 else seq.intrinsics
    odometry = Odometry.from_config(cfg, intrinsics, device)
    track, mapping, map_calls, step_times = [], [], [], []
    start = time.perf_counter()
    for i in range(len(seq)):
        frame = seq[i]
        if factor != 1.0:
            frame.rgb, frame.depth = resize_rgbd(frame.rgb, frame.depth, factor)
        result = odometry.step(frame)
        if device.startswith("cuda"):
            torch.cuda.synchronize(device)
        track.append(result.track_time_s)
        mapping.append(result.map_time_s)
        if result.map_steps and i > 0:
            map_calls.append(result.map_time_s)
            step_times.append(result.map_optimise_time_s / result.map_steps)
        if i % 50 == 0:
            print(f"  frame {i}/{len(seq)}: {time.perf_counter() - start:.0f} s, "
                  f"{result.n_points} points", file=sys.stderr, flush=True)
    total = time.perf_counter() - start
    stamps, poses = odometry.trajectory()
    out = {"frames": len(seq), "resolution": f"{intrinsics.width}x{intrinsics.height}"}
    gt = seq.gt_poses()  # reads every pose file: once per run
    for align in aligns:
        ate = evaluate_ate(seq.timestamps, gt, stamps, poses, align=align)
        out[f"ate_{align}_cm"] = round(100 * ate.rmse, 3)
    if pieces:
        out.update(_pieces(seq.timestamps, gt, stamps, poses))
    out.update(_rpe(seq.timestamps, gt, stamps, poses))
    out.update({
        "mean_s_per_frame": round(total / len(seq), 3),
        "tracking_s_per_frame": round(float(np.mean(track[1:])), 3),
        "mapping_s_per_call": round(float(np.mean(map_calls)), 3) if map_calls else None,
        "mapping_s_per_iter": round(float(np.mean(step_times)), 4) if step_times else None,
        "first_mapping_s": round(mapping[0], 2),
        "points": len(odometry.point_map),
        "keyframes": len(odometry.keyframes),
        "peak_gpu_memory_mb": round(torch.cuda.max_memory_allocated(device) / 2**20, 1)
        if device.startswith("cuda") else None,
    })
    return out


def open3d_odometry(seq, factor: float, depth_max: float) -> dict:
    """Open3D RGB-D odometry (hybrid term), frame to frame, chained from identity."""
    import open3d as o3d

    intr = seq.intrinsics.scaled(factor) if factor != 1.0 else seq.intrinsics
    pinhole = o3d.camera.PinholeCameraIntrinsic(intr.width, intr.height, intr.fx, intr.fy,
                                                intr.cx, intr.cy)
    option = o3d.pipelines.odometry.OdometryOption()
    option.depth_max = depth_max
    jacobian = o3d.pipelines.odometry.RGBDOdometryJacobianFromHybridTerm()
    poses = [np.eye(4)]
    previous = None
    failures = 0
    start = time.perf_counter()
    for i in range(len(seq)):
        frame = seq[i]
        rgb, depth = frame.rgb, frame.depth
        if factor != 1.0:
            rgb, depth = resize_rgbd(rgb, depth, factor)
        image = o3d.geometry.RGBDImage.create_from_color_and_depth(
            o3d.geometry.Image(np.ascontiguousarray(rgb)),
            o3d.geometry.Image(np.ascontiguousarray(depth)),
            depth_scale=1.0, depth_trunc=depth_max, convert_rgb_to_intensity=True)
        if previous is not None:
            ok, T_prev_cur, _ = o3d.pipelines.odometry.compute_rgbd_odometry(
                image, previous, pinhole, np.eye(4), jacobian, option)
            if not ok:
                failures += 1
                T_prev_cur = np.eye(4)
            poses.append(poses[-1] @ T_prev_cur)
        previous = image
    seconds = time.perf_counter() - start
    gt, chained = seq.gt_poses(), np.stack(poses)
    ate = evaluate_ate(seq.timestamps, gt, seq.timestamps, chained, align="se3")
    return {"ate_se3_cm": round(100 * ate.rmse, 3),
            **_pieces(seq.timestamps, gt, seq.timestamps, chained),
            **_rpe(seq.timestamps, gt, seq.timestamps, chained), "failures": failures,
            "mean_s_per_frame": round(seconds / len(seq), 3)}


def _pieces(gt_stamps: np.ndarray, gt_poses: np.ndarray, stamps: np.ndarray,
            poses: np.ndarray) -> dict:
    """se3 ATE over the pieces between the ground truth's jumps, and where it jumps."""
    jumps = reference_jumps(gt_poses)
    result = segmented_ate(gt_stamps, gt_poses, stamps, poses, jumps, align="se3")
    return {"ate_se3_pieces_cm": round(100 * result.rmse, 3),
            "gt_jumps_after_frame": [int(j) for j in jumps]}


def _rpe(gt_stamps: np.ndarray, gt_poses: np.ndarray, stamps: np.ndarray,
         poses: np.ndarray) -> dict:
    """Mean relative pose error over 1 and 10 frames, in mm and degrees (a span as long as
    the run or longer is left out)."""
    out = {}
    for delta in (d for d in (1, 10) if d < len(poses)):
        rpe = evaluate_rpe(gt_stamps, gt_poses, stamps, poses, delta=delta)
        out[f"rpe{delta}_mm"] = round(1000 * rpe.trans_mean, 2)
        out[f"rpe{delta}_deg"] = round(rpe.rot_mean_deg, 3)
    return out


def _size(intr: Intrinsics, factor: float) -> tuple[int, int]:
    scaled = intr.scaled(factor) if factor != 1.0 else intr
    return scaled.width, scaled.height


def print_table(report: dict) -> None:
    rows = [("sequence", "ATE origin cm", "ATE se3 cm", "se3 pieces cm", "RPE1 mm/deg",
             "RPE10 mm/deg", "s/frame", "track s/frame", "map s/call", "map s/iter", "points")]

    def accuracy(r: dict) -> tuple[str, ...]:
        return (str(r.get("ate_origin_cm", "-")), str(r["ate_se3_cm"]),
                str(r.get("ate_se3_pieces_cm", "-")),
                *(f"{r[f'rpe{d}_mm']}/{r[f'rpe{d}_deg']}" if f"rpe{d}_mm" in r else "-"
                  for d in (1, 10)))

    for name in ("synthetic", "real"):
        r = report.get(name)
        if not r or "skipped" in r:
            continue
        rows.append((f"{name} ({r['resolution']}, cpslam, seed {report['seeds'][0]})",
                     *accuracy(r), str(r["mean_s_per_frame"]), str(r["tracking_s_per_frame"]),
                     str(r["mapping_s_per_call"]), str(r.get("mapping_s_per_iter")),
                     str(r["points"])))
        for run in r["per_seed"][1:]:
            rows.append((f"{name} cpslam, seed {run['seed']}", *accuracy(run),
                         str(run["mean_s_per_frame"]), "", "", "", ""))
        if "mean_over_seeds" in r:
            m = r["mean_over_seeds"]
            rows.append((f"{name} cpslam, mean of {len(r['per_seed'])} seeds", *accuracy(m),
                         str(m["mean_s_per_frame"]), "", "", "", ""))
        for size, o in r.get("open3d", {}).items():
            rows.append((f"{name} ({size}, Open3D hybrid)", "-", *accuracy(o)[1:],
                         str(o["mean_s_per_frame"]), "-", "-", "-", "-"))
        for which, label in (("ours", "first seed"), ("mean", "mean"),
                             ("worst", "worst seed")):
            if f"ratio_{which}_over_best_open3d" in r:
                rows.append((f"{name}: ATE ratio cpslam ({label}) / best Open3D", "",
                             str(r[f"ratio_{which}_over_best_open3d"]),
                             str(r.get(f"ratio_pieces_{which}_over_best_open3d", "-")),
                             "", "", "", "", "", "", ""))
    paper = report["paper_rtx3090"]
    rows.append(("CP-SLAM paper (RTX 3090, paper preset)", "-", "-", "-", "-", "-", "-",
                 str(paper["tracking_s_per_frame"]), str(paper["mapping_s_per_call"]), "-", "-"))
    widths = [max(len(row[i]) for row in rows) for i in range(len(rows[0]))]
    for row in rows:
        print("  ".join(cell.ljust(w) for cell, w in zip(row, widths, strict=True)))


if __name__ == "__main__":
    main()

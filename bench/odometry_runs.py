"""One odometry run, Open3D's RGB-D odometry on the same frames, and the bench's scenes (the
parts of bench/odometry.py that run inside a job's process)."""

from __future__ import annotations

import importlib.util
import os
import resource
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
DATA = REPO / "runs" / "bench-data"
KITCHEN = REPO.parent / "shared" / "data" / "7scenes-kitchen-0-299"
# The CP-SLAM paper's timings on an RTX 3090: tracking per frame, mapping per mapping step;
# and the GPU memory others measured running its official code.
PAPER = {"tracking_s_per_frame": 0.30, "mapping_s_per_call": 10.1, "gpu_memory_gib": 7.70}
SIZE = (320, 240)
MIN_FRAMES = 3
"""Frames a run does before its time budget can stop it (an se3 alignment needs three)."""


def scene_specs(n: int, base: int) -> list[dict]:
    """n synthetic scenes from scene seed `base` (`cpslam.tools.synth.cycle.scene_cycle`)."""
    from cpslam.tools.synth.cycle import scene_cycle

    return scene_cycle(n, base)


def ensure_scene(spec: dict, frames: int) -> Path:
    """The scene's sequence folder, rendered on first use."""
    out = DATA / f"{spec['name']}-{frames}-{SIZE[0]}x{SIZE[1]}"
    if not (out / "agent_0" / "traj.txt").is_file():
        from cpslam.tools.synth import generate

        print(f"  rendering {spec['name']} ({frames} frames) into {out}", file=sys.stderr,
              flush=True)
        generate(out, scene=spec["kind"], frames=frames, width=SIZE[0], height=SIZE[1],
                 seed=spec["seed"], noise=spec["noise"], loop=spec["loop"], overwrite=True)
    return out / "agent_0"


def run_job(job: dict) -> dict:
    """One odometry run of a sequence (inside its own process: the thread count and CPU
    capability are the process's)."""
    import torch

    from cpslam.common.config import load_config
    from cpslam.common.datasets import open_sequence
    from cpslam.common.device import configure_torch, resolve_device

    seq_info = job["sequence"]
    cfg = load_config(job["preset"], overrides=[*job["overrides"], f"run.seed={job['seed']}",
                                                f"run.num_threads={job['threads']}"], env={})
    threads = configure_torch(cfg.run.num_threads, cfg.run.deterministic, 1)
    device = resolve_device(job["device"])
    seq = open_sequence(seq_info["path"], frames=slice(0, job["frames"]))
    real = seq_info["kind"] == "real"
    factor = cfg.camera.downscale if real else 1.0  # synthetic scenes are rendered at 320x240
    if job.get("loops", "off") == "on":
        out = run_with_loops(cfg, seq, factor, device, real)
    else:
        out = run_odometry(cfg, seq, factor, device, real, job.get("max_seconds"))
    cuda = device.startswith("cuda")
    out.update(torch_threads=threads, cpu_capability=os.environ.get("ATEN_CPU_CAPABILITY",
                                                                    "default"),
               # allocated: what the tensors held at the peak; reserved: what torch's caching
               # allocator took from the driver (nearer what nvidia-smi shows, less the context)
               peak_gpu_memory_mb=round(torch.cuda.max_memory_allocated(device) / 2**20, 1)
               if cuda else None,
               peak_gpu_reserved_mb=round(torch.cuda.max_memory_reserved(device) / 2**20, 1)
               if cuda else None)
    return out


def run_odometry(cfg, seq, factor: float, device: str, real: bool,
                 max_seconds: float | None = None) -> dict:
    """Track and map every frame, or the frames done when `max_seconds` (wall clock) ran out;
    accuracy against the ground truth, recovery events, time."""
    import torch

    from cpslam.agent.odometry import Odometry
    from cpslam.common.camera import resize_rgbd

    intrinsics = seq.intrinsics.scaled(factor) if factor != 1.0 else seq.intrinsics
    odometry = Odometry.from_config(cfg, intrinsics, device)
    results = []
    start, start_cpu, start_sys = time.perf_counter(), time.process_time(), os.times().system
    done, first_tracked = 0, None
    for i in range(len(seq)):
        if max_seconds and i >= MIN_FRAMES and time.perf_counter() - start > max_seconds:
            break
        done = i + 1
        frame = seq[i]
        if factor != 1.0:
            frame.rgb, frame.depth = resize_rgbd(frame.rgb, frame.depth, factor)
        results.append(odometry.step(frame))
        if device.startswith("cuda"):
            torch.cuda.synchronize(device)
        if i == 1:
            first_tracked = time.perf_counter() - start
    odometry.close()  # the mapping calls still running belong to the run
    total, total_cpu = time.perf_counter() - start, time.process_time() - start_cpu
    total_sys = os.times().system - start_sys
    stamps, poses = odometry.trajectory()
    out = {"frames": done, "frames_asked": len(seq),
           "resolution": f"{intrinsics.width}x{intrinsics.height}"}
    if real and done == len(seq):  # for the ground truth's own error (`agreement`)
        out["poses"] = np.round(poses, 7).tolist()
    try:
        out.update(accuracy(seq, stamps, poses, real, frames=done))
    except ValueError as error:  # too few frames for an alignment: keep the timings
        out["accuracy_error"] = str(error)
    out.update({
        "events": odometry.tracking_events(),
        **timings(results, total, first_tracked),
        # Process CPU time (every thread): comparable between runs that share the cores.
        "cpu_s_per_frame": round(total_cpu / done, 3),
        # The kernel's share of it (page faults, thread wake-ups), and the process's peak
        # resident memory (Linux reports ru_maxrss in KiB).
        "sys_s_per_frame": round(total_sys / done, 3),
        "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
        "points": len(odometry.point_map),
        "keyframes": len(odometry.keyframes),
        "schedule": odometry.schedule_stats(),
    })
    return out


def run_with_loops(cfg, seq, factor: float, device: str, real: bool) -> dict:
    """The standalone run with loop closure (`cpslam-agent --standalone`: `run_collab` with
    this one sequence, in a scratch folder): accuracy of the final pose-graph trajectory (and
    the ATE of the same run's odometry chain), the loops, the same timings as `run_odometry`
    (per frame, the back end's work included)."""
    import tempfile

    from cpslam.run import run_collab

    cfg = cfg.model_copy(update={"camera": cfg.camera.model_copy(update={"downscale": factor})})
    with tempfile.TemporaryDirectory(prefix="bench-loops-") as tmp:
        result = run_collab(cfg, [seq], Path(tmp), device, show_progress=False)
    node, final = result.nodes["0"], result.final.agents[0]
    loops = result.final.metrics.get("loops", {})
    out = {"frames": len(seq), "resolution": f"{node.intrinsics.width}x{node.intrinsics.height}"}
    out.update(accuracy(seq, final.stamps, final.T_group_cam, real))
    # The same run's frames chained from the odometry alone: tells the pose graph's effect
    # apart from that of the corrections the agent tracked against.
    stamps, poses = result.odometry["0"]
    out["odometry_in_run"] = {k: v for k, v in accuracy(seq, stamps, poses, real).items()
                              if k.startswith("ate_")}
    out.update({
        "loops_found": int(loops.get("found", 0)),
        "loops_accepted": int(loops.get("accepted", 0)),
        "events": node.odometry.tracking_events(),
        **timings(node.results, result.wall_s),
        "points": len(node.odometry.point_map),
        "keyframes": len(node.odometry.keyframes),
    })
    return out


def timings(results: list, wall_s: float, first_tracked_s: float | None = None) -> dict:
    """Seconds per frame (end to end, and after the first frame's mapping call), tracking per
    frame after the first, per mapping call and step, and the first call, from the frames'
    results (`FrameResult`) and the run's wall time. With `first_tracked_s` (the wall time
    until frame 1 was tracked, which is less than the first call when it publishes part way:
    `mapping.first_publish_every`), "after the first" counts from then, over frames 2 on."""
    # Calls finish in order: the first reported is frame 0's (reported with frame 0 in
    # lock-step, with a later frame when concurrent).
    reported = [r for r in results if r.map_steps]
    first = reported[0] if reported else None
    mapped = reported[1:]
    first_map = first.map_time_s if first is not None else 0.0
    n = max(len(results), 1)

    def mean(values: list[float], digits: int) -> float | None:
        return round(float(np.mean(values)), digits) if values else None

    after_first = ((wall_s - first_map) / max(n - 1, 1) if first_tracked_s is None
                   else (wall_s - first_tracked_s) / max(n - 2, 1))
    out = {
        "s_per_frame": round(wall_s / n, 3),
        "s_per_frame_after_first": round(after_first, 3),
        "tracking_s_per_frame": mean([r.track_time_s for r in results[1:]], 3),
        "mapping_s_per_call": mean([r.map_time_s for r in mapped], 3),
        "mapping_s_per_iter": mean([r.map_optimise_time_s / r.map_steps for r in mapped], 4),
        "first_mapping_s": round(first_map, 2),
        "first_mapping_s_per_iter": (round(first.map_optimise_time_s / first.map_steps, 4)
                                     if first is not None else None),
    }
    if first_tracked_s is not None:
        out["first_tracked_s"] = round(first_tracked_s, 2)
    return out


def accuracy(seq, stamps: np.ndarray, poses: np.ndarray, real: bool,
             frames: int | None = None) -> dict:
    """ATE (origin and se3 for synthetic, se3 and over the pieces for real), the largest
    position error after the alignment, and the RPE over 1, 10, 50 and 100 frames (the
    longer spans calibrate the pose graph's odometry edges); against the first `frames`
    ground-truth poses when given (a run stopped by its time budget)."""
    from cpslam.tools.eval import evaluate_ate, evaluate_rpe, reference_jumps, segmented_ate

    gt, gt_stamps = seq.gt_poses()[:frames], np.asarray(seq.timestamps)[:frames]
    out = {}
    aligns = ("se3",) if real else ("origin", "se3")
    for align in aligns:
        ate = evaluate_ate(gt_stamps, gt, stamps, poses, align=align)
        out[f"ate_{align}_cm"] = round(100 * ate.rmse, 3)
        if align == aligns[0]:
            out["max_error_cm"] = round(100 * float(ate.trans_err.max()), 2)
    if real:
        jumps = reference_jumps(gt)
        try:
            pieces = segmented_ate(gt_stamps, gt, stamps, poses, jumps, align="se3")
            out["ate_se3_pieces_cm"] = round(100 * pieces.rmse, 3)
        except ValueError:  # no piece long enough (a run stopped by its time budget)
            pass
        out["gt_jumps_after_frame"] = [int(j) for j in jumps]
    for delta in (d for d in (1, 10, 50, 100) if d < len(poses)):
        rpe = evaluate_rpe(gt_stamps, gt, stamps, poses, delta=delta)
        out[f"rpe{delta}_mm"] = round(1000 * rpe.trans_mean, 2)
        out[f"rpe{delta}_deg"] = round(rpe.rot_mean_deg, 3)
    return out


def open3d_available() -> bool:
    """Whether open3d can be imported (the GPU bench machine has none: the comparison is
    left out there)."""
    return importlib.util.find_spec("open3d") is not None


def open3d_odometry(seq_info: dict, frames: int) -> dict:
    """Open3D's RGB-D odometry (hybrid term, multi-scale, frame to frame, chained from the
    identity) on the sequence: at 320x240 and, for the 640x480 real frames, at full size."""
    from cpslam.common.config import load_config
    from cpslam.common.datasets import open_sequence

    seq = open_sequence(seq_info["path"], frames=slice(0, frames))
    real = seq_info["kind"] == "real"
    depth_max = load_config("cpu", env={}).camera.depth_max
    factors = sorted({SIZE[0] / seq.intrinsics.width, 1.0})
    out = {}
    for factor in factors:
        intr = seq.intrinsics.scaled(factor) if factor != 1.0 else seq.intrinsics
        poses, seconds, failures = open3d_chain(seq, intr, factor, depth_max)
        entry = accuracy(seq, seq.timestamps, poses, real)
        entry.update(failures=failures, s_per_frame=round(seconds / len(seq), 3))
        if real:
            entry["poses"] = np.round(poses, 7).tolist()
        out[f"{intr.width}x{intr.height}"] = entry
    return out


def open3d_chain(seq, intr, factor: float, depth_max: float):
    import open3d as o3d

    from cpslam.agent.recovery import open3d_pinhole, open3d_rgbd
    from cpslam.common.camera import resize_rgbd

    pinhole = open3d_pinhole(intr)
    option = o3d.pipelines.odometry.OdometryOption()
    option.depth_max = depth_max
    jacobian = o3d.pipelines.odometry.RGBDOdometryJacobianFromHybridTerm()
    poses, previous, failures = [np.eye(4)], None, 0
    start = time.perf_counter()
    for i in range(len(seq)):
        frame = seq[i]
        rgb, depth = frame.rgb, frame.depth
        if factor != 1.0:
            rgb, depth = resize_rgbd(rgb, depth, factor)
        image = open3d_rgbd(rgb, depth, depth_max)
        if previous is not None:
            ok, T_prev_cur, _ = o3d.pipelines.odometry.compute_rgbd_odometry(
                image, previous, pinhole, np.eye(4), jacobian, option)
            if not ok:
                failures += 1
                T_prev_cur = np.eye(4)
            poses.append(poses[-1] @ T_prev_cur)
        previous = image
    return np.stack(poses), time.perf_counter() - start, failures


def agreement(sequences: list[dict], runs: list[dict], open3d_full: dict, frames: int) -> dict:
    """Per real sequence, the three-cornered hat (`cpslam.tools.eval.hat`) of the ground
    truth, Open3D at full size (`open3d_full`: its entry per sequence name) and each of our
    runs without loop closure: their pairwise RMS differences and each one's estimated own
    error (ATE and RPE over 1, 10, 50 frames, mm), per run and averaged over the runs. Runs
    and Open3D carry their "poses" for this."""
    from cpslam.common.datasets import open_sequence
    from cpslam.tools.eval.hat import hat_table, pairwise_differences

    out = {}
    for info in (s for s in sequences if s["kind"] == "real"):
        full = open3d_full.get(info["name"]) or {}
        gt = open_sequence(info["path"], frames=slice(0, frames)).gt_poses()
        mine = [r for r in runs if r["sequence"] == info["name"] and "poses" in r
                and r.get("loops", "off") == "off" and len(r["poses"]) == len(gt)]
        if "poses" not in full or not mine:
            continue
        per_run = []
        for run in mine:
            pairs = pairwise_differences({"ground_truth": gt, "open3d": np.array(full["poses"]),
                                          "cpslam": np.array(run["poses"])})
            hat = hat_table(pairs, "ground_truth", "open3d", "cpslam")
            per_run.append({"seed": run["seed"], "threads": run["threads"],
                            "capability": run["capability"], "differences_mm": _mm(pairs),
                            "own_error_mm": _mm(hat)})
        metrics = per_run[0]["own_error_mm"]
        mean = {m: {src: round(float(np.mean([r["own_error_mm"][m][src] for r in per_run])), 2)
                    for src in metrics[m]} for m in metrics}
        out[info["name"]] = {"runs": per_run, "own_error_mean_mm": mean}
    return out


def _mm(table: dict[str, dict[str, float]]) -> dict[str, dict[str, float]]:
    """Metres to millimetres, keys "ate_m" -> "ate" (either level), rounded to 0.01 mm."""
    return {key.removesuffix("_m"): {k.removesuffix("_m"): round(1000 * v, 2)
                                     for k, v in row.items()}
            for key, row in table.items()}

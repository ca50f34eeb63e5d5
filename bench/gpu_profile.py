"""Where a tracking frame's time goes on a device: torch.profiler over a few frames of the
agent's odometry, the operators by device time and by host time, kernel launches and host
waits per frame, printed and written as JSON.

Runs `Odometry` on `--device` (default cuda) over the first `--frames` frames of a sequence
(at the preset's camera.downscale). The first frame (no tracking, the first mapping: shorten
it with ``--set mapping.iters_first=100``) runs unprofiled; the others are profiled, each
synchronised with the device. Tells a launch-bound step (host time per frame close to the
wall time, many small kernels, waits on ``aten::item`` / ``aten::_local_scalar_dense``) from
a compute-bound one (device time close to the wall time).

Usage: python bench/gpu_profile.py [--preset paper] [--frames 6] [--data PATH | --synthetic SEED]
       [--device cuda] [--set a.b=v ...] [--json PATH]
Example (the device tool, after bench/gpu_prepare.sh; see docs/gpu.md):
    python bench/gpu_profile.py --data .gpudata/7scenes-kitchen --set mapping.iters_first=100
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchinfo import bench_header  # noqa: E402
from odometry_runs import KITCHEN  # noqa: E402
from stage_profile import open_frames  # noqa: E402

WAITS = ("aten::item", "aten::_local_scalar_dense", "cudaStreamSynchronize",
         "cudaDeviceSynchronize", "cudaMemcpyAsync")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="paper")
    parser.add_argument("--frames", type=int, default=6, help="frames (the first unprofiled)")
    parser.add_argument("--data", type=Path, default=KITCHEN, help="sequence folder")
    parser.add_argument("--synthetic", type=int, default=None, metavar="SEED",
                        help="a synthetic scene (bench/odometry_runs.py) instead of --data")
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--threads", type=int, default=8, help="torch CPU threads")
    parser.add_argument("--set", nargs="*", default=[], help="config overrides a.b=value")
    parser.add_argument("--rows", type=int, default=20, help="operators listed per table")
    parser.add_argument("--json", type=Path, default=None, help="also write the JSON here")
    args = parser.parse_args()
    import torch
    from torch.profiler import ProfilerActivity, profile

    from cpslam.agent.odometry import Odometry
    from cpslam.common.config import load_config
    from cpslam.common.device import configure_torch

    cfg = load_config(args.preset, overrides=[f"run.num_threads={args.threads}", *args.set],
                      env={})
    configure_torch(cfg.run.num_threads, cfg.run.deterministic, 1)
    _, intrinsics, frames = open_frames(args, cfg)
    cuda = args.device.startswith("cuda")
    sync = torch.cuda.synchronize if cuda else (lambda: None)
    odometry = Odometry.from_config(cfg, intrinsics, args.device)
    t0 = time.perf_counter()
    odometry.step(frames[0])
    sync()
    first_s = time.perf_counter() - t0
    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if cuda else [])
    walls, track_iters = [], []
    with profile(activities=activities) as prof:
        for frame in frames[1:]:
            t = time.perf_counter()
            result = odometry.step(frame)
            sync()
            walls.append(time.perf_counter() - t)
            track_iters.append(result.track_iters)
    n = len(walls)
    odometry.close()  # a mapping call may still run on its thread
    events = prof.key_averages()
    device_attr = "self_device_time_total" if cuda else "self_cpu_time_total"

    def top(attr: str) -> list[dict]:
        rows = sorted(events, key=lambda e: getattr(e, attr, 0.0), reverse=True)[: args.rows]
        return [{"op": e.key, "calls_per_frame": e.count / n,
                 "self_host_ms_per_frame": e.self_cpu_time_total / 1e3 / n,
                 "self_device_ms_per_frame": getattr(e, device_attr, 0.0) / 1e3 / n}
                for e in rows]

    kernels = sum(e.count for e in events if e.key in ("cudaLaunchKernel", "cuLaunchKernel"))
    waits = {e.key: e.count / n for e in events if e.key in WAITS}
    host_ms = sum(e.self_cpu_time_total for e in events) / 1e3 / n
    device_ms = sum(getattr(e, device_attr, 0.0) for e in events) / 1e3 / n if cuda else None
    report = bench_header("gpu_profile", sys.argv)
    report.update(preset=args.preset, overrides=args.set, device=args.device,
                  frames=len(frames), first_frame_s=first_s,
                  wall_s_per_frame=sum(walls) / n, lm_iters_per_frame=sum(track_iters) / n,
                  host_ms_per_frame=host_ms, device_ms_per_frame=device_ms,
                  kernel_launches_per_frame=kernels / n, host_waits_per_frame=waits,
                  by_device_time=top(device_attr), by_host_time=top("self_cpu_time_total"))
    print(f"{args.preset} on {args.device}: first frame {first_s:.1f} s; frames 1..{n}: "
          f"{report['wall_s_per_frame']:.3f} s wall, {report['lm_iters_per_frame']:.1f} LM "
          f"iterations, {host_ms:.0f} ms host (self, all ops), "
          f"{'-' if device_ms is None else f'{device_ms:.0f} ms'} device, "
          f"{kernels / n:.0f} kernel launches, waits {waits} per frame")
    for title, rows in (("by device time", report["by_device_time"]),
                        ("by host time", report["by_host_time"])):
        print(f"\n{title} (per frame): op, calls, host ms, device ms")
        for r in rows:
            print(f"  {r['op'][:60]:<60} {r['calls_per_frame']:>8.1f} "
                  f"{r['self_host_ms_per_frame']:>9.2f} {r['self_device_ms_per_frame']:>9.2f}")
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(report, indent=1) + "\n")
        print(f"\nwrote {args.json}")


if __name__ == "__main__":
    main()

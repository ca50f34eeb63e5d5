"""How well the first mapping call fits its frame, step by step, from random decoder weights
and from a prior (`field.prior`), printed as a table and written as JSON.

For each frame (the shared kitchen frames at the preset's camera.downscale, and frame 0 of
synthetic scenes of bench/odometry_runs.py) and each setting, `Odometry` runs on that one
frame in lock-step, so its first mapping call is the whole run; the mean absolute depth
and colour (RGB in [0, 1]) errors of every step's training rays (before the step's update)
are recorded and reported as the mean over windows of `--window` steps. The last window's
figures are what the call leaves the tracker; lower is a better fit.

Usage: python bench/first_call.py [--preset cpu] [--kitchen-frames 0 150]
       [--synthetic 200 203] [--setting NAME=k=v,k=v ...] [--threads 2] [--json PATH]
Example: python bench/first_call.py --setting random600=field.prior=null,mapping.iters_first=600 \\
             --setting prior300= --json bench/results/first-call-prior.json
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchinfo import bench_header  # noqa: E402
from odometry_runs import KITCHEN, ensure_scene, scene_specs  # noqa: E402


def fit_one(preset: str, overrides: list[str], frame_spec: dict, threads: int,
            window: int) -> dict:
    """The first call on one frame: per-window mean depth error (cm) and its time."""
    import numpy as np

    from cpslam.agent import mapper as mapper_module
    from cpslam.agent.odometry import Odometry
    from cpslam.common.camera import resize_rgbd
    from cpslam.common.config import load_config
    from cpslam.common.datasets import open_sequence
    from cpslam.common.device import configure_torch

    cfg = load_config(preset, overrides=[*overrides, "run.schedule=lockstep",
                                         f"run.num_threads={threads}"], env={})
    configure_torch(cfg.run.num_threads, cfg.run.deterministic, 1)
    factor = cfg.camera.downscale if frame_spec["kind"] == "real" else 1.0
    index = frame_spec["frame"]
    seq = open_sequence(frame_spec["path"], frames=slice(index, index + 1))
    frame = seq[0]
    if factor != 1.0:
        frame.rgb, frame.depth = resize_rgbd(frame.rgb, frame.depth, factor)
    odometry = Odometry.from_config(cfg, seq.intrinsics.scaled(factor), "cpu")
    errors: list[float] = []
    color_errors: list[float] = []
    render, batch = mapper_module.render_rays, mapper_module._batch
    observed: dict = {}

    def batching(*args, **kwargs):
        rays = batch(*args, **kwargs)
        observed["color"] = rays[3]
        return rays

    def recording(*args, **kwargs):
        out = render(*args, **kwargs)
        if kwargs.get("features") is not None:  # a step's training rays, not point insertion
            errors.append(float((out["depth"].detach() - args[4]).abs().mean()))
            color_errors.append(float((out["color"].detach() - observed["color"]).abs().mean()))
        return out

    mapper_module.render_rays, mapper_module._batch = recording, batching
    try:
        start = time.perf_counter()
        odometry.step(frame)
        seconds = time.perf_counter() - start
    finally:
        mapper_module.render_rays, mapper_module._batch = render, batch
        odometry.close()
    e = np.asarray(errors) * 100.0
    c = np.asarray(color_errors)
    windows = [round(float(e[i:i + window].mean()), 3) for i in range(0, len(e), window)]
    color_windows = [round(float(c[i:i + window].mean()), 4) for i in range(0, len(c), window)]
    return {"steps": len(e), "seconds": round(seconds, 1), "window_l1_cm": windows,
            "final_l1_cm": windows[-1] if windows else None,
            "window_color_l1": color_windows,
            "final_color_l1": color_windows[-1] if color_windows else None}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="cpu")
    parser.add_argument("--kitchen-frames", type=int, nargs="*", default=[0, 150])
    parser.add_argument("--synthetic", type=int, nargs="*", default=[200, 203],
                        help="scene seeds (of bench/odometry_runs.py's room/apartment cycle "
                             "from 200)")
    parser.add_argument("--setting", action="append", default=[],
                        help="NAME=key=value,key=value (empty after NAME=: the preset)")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--window", type=int, default=50)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    settings = {}
    for text in args.setting or ["preset="]:
        name, _, rest = text.partition("=")
        settings[name] = [s for s in rest.split(",") if s]
    frames = [{"name": f"kitchen-{i}", "kind": "real", "path": str(KITCHEN), "frame": i}
              for i in args.kitchen_frames]
    specs = {s["seed"]: s for s in scene_specs(max(args.synthetic, default=200) - 199, 200)}
    for seed in args.synthetic:
        spec = specs[seed]
        frames.append({"name": spec["name"], "kind": "synthetic",
                       "path": str(ensure_scene(spec, 150)), "frame": 0})
    runs = []
    for frame_spec in frames:
        for name, overrides in settings.items():
            result = fit_one(args.preset, overrides, frame_spec, args.threads, args.window)
            runs.append({"frame": frame_spec["name"], "setting": name,
                         "overrides": overrides, **result})
            print(f"{frame_spec['name']:<22} {name:<12} {result['steps']:>4} steps "
                  f"{result['seconds']:>6.1f} s  L1 cm per {args.window} steps: "
                  + " ".join(f"{v:.2f}" for v in result["window_l1_cm"])
                  + "  colour L1: " + " ".join(f"{v:.3f}" for v in result["window_color_l1"]),
                  flush=True)
    report = {**bench_header("first_call", sys.argv), "preset": args.preset,
              "threads": args.threads, "window": args.window, "runs": runs}
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(report, indent=1))
        print(f"wrote {args.json}")


if __name__ == "__main__":
    main()

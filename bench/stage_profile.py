"""Per-stage CPU-time profile of the agent's odometry (tracking and mapping), printed as a table
and written as JSON.

Runs `Odometry` on the first `--frames` frames of a sequence (default
../shared/data/7scenes-kitchen-0-299 at the preset's camera.downscale; `--synthetic SEED` a
synthetic scene of bench/odometry_runs.py instead) in this process and charges the process's
CPU time (time.process_time: every torch thread counts) to stages:

- tracking: neighbour search, sample rendering (pair lists, compositing), decoder forward,
  Jacobian backward (LM), the reference-view image terms, LM algebra and the rest;
- mapping: point insertion, ray batching, ray sampling, neighbour search, sample rendering,
  decoder forward, backward, optimiser step and the rest;
- other: keyframes and whatever the odometry does between the two.

The odometry runs in lock-step (`run.schedule=lockstep`, whatever the preset or `--set` say),
so that tracking and mapping take turns on the process's threads and each stage's time is
its own.

Each stage gets its exclusive time: a nested stage's time is charged to it, not to the
stage around it. The stages come from wrapping the functions that do the work for the
duration of the run (nothing in the library changes, and nothing costs anything when this
script does not run). The first frame (no tracking, the long first mapping call) is reported
apart from the per-frame figures of the others. The timers add about a microsecond per call.

Usage: python bench/stage_profile.py [--preset cpu] [--frames 21] [--threads 2]
       [--synthetic SEED] [--data PATH] [--set a.b=v ...] [--json PATH]
Example: python bench/stage_profile.py --frames 21 --set mapping.iters_first=100 \\
             --json bench/results/profile-cpu.json
"""

from __future__ import annotations

import argparse
import functools
import json
import sys
import time
from collections import defaultdict
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchinfo import bench_header  # noqa: E402
from odometry_runs import KITCHEN, ensure_scene, scene_specs  # noqa: E402

# (phase, stage) rows in print order.
STAGES = {
    "tracking": ("search", "render", "decoder_forward", "jacobian_backward", "image_terms",
                 "lm_other"),
    "mapping": ("insert_points", "batch_rays", "sample_rays", "search", "render",
                "decoder_forward", "backward", "optimiser_step", "other"),
    "other": ("other",),
}


class StageClock:
    """Exclusive CPU time per (phase, stage): a stack of open stages, the time since the last
    event is charged to the innermost one."""

    def __init__(self) -> None:
        self.seconds: dict[tuple[str, str], float] = defaultdict(float)
        self.calls: dict[tuple[str, str], int] = defaultdict(int)
        self.stack: list[tuple[str, str]] = [("other", "other")]
        self.last = time.process_time()

    def _charge(self) -> None:
        now = time.process_time()
        self.seconds[self.stack[-1]] += now - self.last
        self.last = now

    def push(self, phase: str | None, stage: str) -> None:
        self._charge()
        key = (phase or self.stack[-1][0], stage)
        self.calls[key] += 1
        self.stack.append(key)

    def pop(self) -> None:
        self._charge()
        self.stack.pop()

    def reset(self) -> None:
        self._charge()
        self.seconds.clear()
        self.calls.clear()


def instrument(clock: StageClock) -> None:
    """Wrap the functions that make up the stages (for this process's lifetime)."""
    import torch

    from cpslam.agent import mapper as mapper_mod
    from cpslam.common.field import pose_lm, renderer, tracking
    from cpslam.common.field.decoders import Decoders
    from cpslam.common.field.sampler import RaySampler
    from cpslam.common.field.search import NeighbourIndex

    def wrap(owner, name: str, phase: str | None, stage: str, only_in: str | None = None):
        original = getattr(owner, name)

        @functools.wraps(original)
        def timed(*args, **kwargs):
            if only_in is not None and clock.stack[-1][0] != only_in:
                return original(*args, **kwargs)
            clock.push(phase, stage)
            try:
                return original(*args, **kwargs)
            finally:
                clock.pop()

        setattr(owner, name, timed)

    wrap(tracking.Tracker, "track", "tracking", "lm_other")
    wrap(tracking.Tracker, "_reference_points", None, "image_terms")
    wrap(pose_lm, "image_residuals", None, "image_terms")
    wrap(pose_lm._Problem, "_jacobian", None, "jacobian_backward")
    wrap(mapper_mod.Mapper, "add_points", "mapping", "insert_points")
    wrap(mapper_mod.Mapper, "optimise", "mapping", "other")
    wrap(mapper_mod, "_batch", None, "batch_rays")
    wrap(RaySampler, "__call__", None, "sample_rays", only_in="mapping")
    wrap(NeighbourIndex, "query", None, "search")
    wrap(renderer, "_render_chunk", None, "render")
    wrap(Decoders, "forward_pairs", None, "decoder_forward")
    wrap(torch.Tensor, "backward", None, "backward", only_in="mapping")
    wrap(torch.optim.Adam, "step", None, "optimiser_step", only_in="mapping")


def open_frames(args, cfg):
    from cpslam.common.camera import resize_rgbd
    from cpslam.common.datasets import open_sequence

    if args.synthetic is not None:
        spec = scene_specs(1, args.synthetic)[0]
        path, factor = ensure_scene(spec, args.frames), 1.0
    else:
        path, factor = args.data, cfg.camera.downscale
    seq = open_sequence(str(path), frames=slice(0, args.frames))
    frames = []
    for i in range(len(seq)):
        frame = seq[i]
        if factor != 1.0:
            frame.rgb, frame.depth = resize_rgbd(frame.rgb, frame.depth, factor)
        frames.append(frame)
    return str(path), seq.intrinsics.scaled(factor), frames


def table(clock: StageClock, n_frames: int) -> dict:
    """{phase: {stage: {s_per_frame, ms_per_call, calls, share_phase, share_total}}}."""
    total = sum(clock.seconds.values())
    out: dict = {}
    for phase, stages in STAGES.items():
        phase_total = sum(clock.seconds.get((phase, s), 0.0) for s in stages)
        rows = {}
        for stage in stages:
            sec, calls = clock.seconds.get((phase, stage), 0.0), clock.calls.get((phase, stage), 0)
            rows[stage] = {
                "s_per_frame": sec / max(n_frames, 1),
                "ms_per_call": 1e3 * sec / calls if calls else None,
                "calls_per_frame": calls / max(n_frames, 1),
                "share_phase": sec / phase_total if phase_total else 0.0,
                "share_total": sec / total if total else 0.0,
            }
        out[phase] = {"s_per_frame": phase_total / max(n_frames, 1), "stages": rows}
    out["total_s_per_frame"] = total / max(n_frames, 1)
    return out


def print_table(title: str, result: dict) -> None:
    print(f"\n{title}: {result['total_s_per_frame']:.3f} CPU s/frame")
    print(f"  {'stage':<28}{'s/frame':>9}{'ms/call':>9}{'calls/fr':>9}{'phase%':>8}"
          f"{'total%':>8}")
    for phase in STAGES:
        print(f"  {phase:<28}{result[phase]['s_per_frame']:>9.3f}")
        for stage, row in result[phase]["stages"].items():
            per_call = "-" if row["ms_per_call"] is None else f"{row['ms_per_call']:.2f}"
            print(f"    {stage:<26}{row['s_per_frame']:>9.4f}{per_call:>9}"
                  f"{row['calls_per_frame']:>9.1f}{100 * row['share_phase']:>7.1f}%"
                  f"{100 * row['share_total']:>7.1f}%")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="cpu")
    parser.add_argument("--frames", type=int, default=21, help="frames (the first is apart)")
    parser.add_argument("--threads", type=int, default=2, help="torch threads")
    parser.add_argument("--data", type=Path, default=KITCHEN, help="sequence folder")
    parser.add_argument("--synthetic", type=int, default=None, metavar="SEED",
                        help="a synthetic scene (bench/odometry_runs.py) instead of --data")
    parser.add_argument("--set", nargs="*", default=[], help="config overrides a.b=value")
    parser.add_argument("--json", type=Path, default=None, help="also write the JSON here")
    args = parser.parse_args()
    if args.frames < 2:
        parser.error("--frames must be >= 2 (the first frame is reported apart)")

    from cpslam.agent.odometry import Odometry
    from cpslam.common.config import load_config
    from cpslam.common.device import configure_torch

    # Lock-step whatever the preset says: the stage clock is one stack, and a mapping thread
    # beside the tracker would charge its stages to the tracker's and the other way round.
    cfg = load_config(args.preset, overrides=[f"run.num_threads={args.threads}", *args.set,
                                              "run.schedule=lockstep"], env={})
    configure_torch(cfg.run.num_threads, cfg.run.deterministic, 1)
    path, intrinsics, frames = open_frames(args, cfg)
    odometry = Odometry.from_config(cfg, intrinsics, "cpu")
    clock = StageClock()
    instrument(clock)

    clock.reset()
    odometry.step(frames[0])
    clock._charge()
    first = table(clock, 1)
    clock.reset()
    track_steps = map_steps = 0
    for frame in frames[1:]:
        result = odometry.step(frame)
        track_steps += result.track_iters
        map_steps += result.map_steps
    clock._charge()
    n = len(frames) - 1
    per_frame = table(clock, n)
    # The mapping thread may still be in a call: finish it (outside the tables) so the
    # interpreter does not exit under a running torch op.
    odometry.close()

    report = bench_header("stage_profile", sys.argv)
    report.update(preset=args.preset, overrides=args.set, threads=args.threads, data=path,
                  frames=len(frames), resolution=list(intrinsics.shape),
                  track_iters_per_frame=track_steps / n, map_steps_per_frame=map_steps / n,
                  first_frame=first, per_frame=per_frame)
    print_table("first frame", first)
    print_table(f"frames 1..{n} (per frame; {track_steps / n:.1f} LM solves, "
                f"{map_steps / n:.1f} mapping steps per frame)", per_frame)
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(report, indent=1) + "\n")
        print(f"\nwrote {args.json}")


if __name__ == "__main__":
    main()

"""Standalone agent: one sequence, no server — track, map, write the run folder.

The loop reads like the algorithm: read a frame, resize it to the processing resolution,
`odometry.step(frame)`, record. Everything the run produced is written at the end, also when
the user interrupts it (Ctrl-C or SIGTERM).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from cpslam.common.camera import Intrinsics, resize_rgbd
from cpslam.common.config import save_config
from cpslam.common.datasets import RGBDFrame, RGBDSequence, open_sequence
from cpslam.common.logs import make_progress
from cpslam.common.ply import write_ply
from cpslam.common.rundir import SCHEMA_VERSION, peak_rss_mb, write_json
from cpslam.common.trajectory import write_tum

if TYPE_CHECKING:
    from cpslam.agent.odometry import FrameResult, Odometry
    from cpslam.common.config import CpslamConfig

logger = logging.getLogger(__name__)

STATE_FILE = "state.pt"


@dataclass
class StandaloneResult:
    """What a standalone run did and where it wrote it."""

    agent_dir: Path
    frames_done: int
    frames_total: int
    interrupted: bool
    wall_time_s: float
    results: list[FrameResult] = field(default_factory=list)


def open_for_config(
    cfg: CpslamConfig, path: str | Path, fmt: str | None = None, frames: str | None = None,
    topics: Mapping[str, str] | None = None,
) -> RGBDSequence:
    """Open a sequence applying the config's camera overrides (intrinsics, depth scale);
    `topics` name a bag's topics (see `open_sequence`)."""
    cam = cfg.camera
    overrides = {
        key: getattr(cam, key)
        for key in ("fx", "fy", "cx", "cy", "width", "height", "depth_scale")
        if getattr(cam, key) is not None
    }
    return open_sequence(path, fmt=fmt, frames=frames, overrides=overrides or None,
                         topics=topics)


def processing_frames(
    seq: RGBDSequence, downscale: float, start: int = 0
) -> tuple[Intrinsics, Iterator[RGBDFrame]]:
    """Intrinsics at the processing resolution and the sequence's frames resized to it."""
    intrinsics = seq.intrinsics if downscale == 1.0 else seq.intrinsics.scaled(downscale)

    def frames() -> Iterator[RGBDFrame]:
        for i in range(start, len(seq)):
            frame = seq[i]
            if downscale != 1.0:
                rgb, depth = resize_rgbd(frame.rgb, frame.depth, downscale)
                frame = replace(frame, rgb=rgb, depth=depth)
            yield frame

    return intrinsics, frames()


def run_standalone(
    cfg: CpslamConfig,
    seq: RGBDSequence,
    run_dir: Path,
    device: str,
    agent_id: str = "0",
    resume: Path | None = None,
    show_progress: bool = True,
    stop: threading.Event | None = None,
    on_frame: Callable[[RGBDFrame, FrameResult, Odometry], None] | None = None,
) -> StandaloneResult:
    """Run the odometry over `seq` and write `run_dir/agent_<id>/…` and `run_dir/config.yaml`.

    `stop` (set by a signal handler: `common.cli.stop_on_signals`) ends the run after the
    frame in progress; what was done is written and the result says it was interrupted. A
    frame is never cut in half, so the trajectory, the map and the metrics agree. `on_frame`
    is called after each frame (a viewer's recorder: `run.rerun`)."""
    import torch

    from cpslam.agent.odometry import Odometry

    agent_dir = run_dir / f"agent_{agent_id}"
    agent_dir.mkdir(parents=True, exist_ok=True)
    save_config(cfg, run_dir / "config.yaml")
    torch.manual_seed(cfg.run.seed)
    intrinsics, _ = processing_frames(seq, cfg.camera.downscale)
    # The map's agent key is local to this process: the own agent is always 0.
    odometry = Odometry.from_config(cfg, intrinsics, device, agent_id=0)
    start = 0
    if resume is not None:
        odometry.load_state_dict(torch.load(resume, map_location=device, weights_only=True))
        done_stamps, _ = odometry.trajectory()
        start = int(np.searchsorted(seq.timestamps, done_stamps[-1], side="right")) if len(
            done_stamps
        ) else 0
        logger.info("resumed from %s: %d frames done, continuing at position %d",
                    resume, len(done_stamps), start)
    _, frames = processing_frames(seq, cfg.camera.downscale, start)

    results: list[FrameResult] = []
    interrupted = False
    t0 = time.perf_counter()
    with make_progress(disable=not show_progress) as bar:
        task = bar.add_task(f"agent {agent_id}", total=len(seq) - start, info="")
        for frame in frames:
            if stop is not None and stop.is_set():
                interrupted = True
                logger.warning("interrupted after %d frames: saving what exists", len(results))
                break
            result = odometry.step(frame)
            results.append(result)
            if on_frame is not None:
                on_frame(frame, result, odometry)
            fps = len(results) / max(time.perf_counter() - t0, 1e-9)
            bar.update(task, advance=1, info=f"frame {result.index}  {fps:.2f} fps  "
                       f"loss {result.track_loss:.4f}  points {result.n_points}")
    odometry.drain()  # the mapping calls still running belong to the run
    wall = time.perf_counter() - t0
    write_agent_outputs(odometry, agent_dir, results, wall, interrupted, device, seq)
    odometry.close()
    return StandaloneResult(agent_dir, start + len(results), len(seq), interrupted, wall, results)


def write_agent_outputs(
    odometry: Odometry,
    agent_dir: Path,
    results: list[FrameResult],
    wall_time_s: float,
    interrupted: bool,
    device: str,
    seq: RGBDSequence | None = None,
) -> None:
    """trajectory.tum, map.ply, state.pt and metrics.json of one agent; metrics.json names
    `seq` (where a report finds the ground truth), each written atomically."""
    from cpslam.common.durable import torch_save_atomic

    odometry.drain()
    stamps, poses = odometry.trajectory()
    if len(stamps):
        write_tum(agent_dir / "trajectory.tum", stamps, poses)
    pm = odometry.point_map
    if len(pm):
        write_ply(agent_dir / "map.ply", pm.xyz_world().detach().cpu().numpy(),
                  pm.color.cpu().numpy())
    torch_save_atomic(odometry.state_dict(), agent_dir / STATE_FILE)
    metrics = {"schema_version": SCHEMA_VERSION,
               **frame_metrics(odometry, results, wall_time_s, interrupted, device)}
    if seq is not None:
        metrics["sequence"] = {"path": str(seq.path.resolve()), "format": seq.format,
                               "frames": len(seq)}
    write_json(agent_dir / "metrics.json", metrics)
    logger.info("wrote %s (%d frames, %d points)", agent_dir, len(stamps), len(pm))


def frame_metrics(
    odometry: Odometry, results: list[FrameResult], wall_time_s: float, interrupted: bool,
    device: str,
) -> dict:
    """Timings, memory and sizes of a run, per frame and summarised."""
    import torch

    track = np.array([r.track_time_s for r in results], dtype=float)
    mapped = [r for r in results if r.map_steps > 0]
    # Per optimisation step: the steps' own time, without adding points and co-visibility.
    per_step = np.array([r.map_optimise_time_s / r.map_steps for r in mapped], dtype=float)
    gpu_peak = (torch.cuda.max_memory_allocated() / 2**20
                if device.startswith("cuda") and torch.cuda.is_available() else None)
    n = max(len(results), 1)
    return {
        "frames": len(results),
        "interrupted": interrupted,
        "wall_time_s": wall_time_s,
        "mean_time_per_frame_s": wall_time_s / n,
        "tracking_time_per_frame_s": float(track.mean()) if len(track) else None,
        "mapping_calls": len(mapped),
        "mapping_time_per_step_s": float(per_step.mean()) if len(per_step) else None,
        "mapping_time_per_call_s": (float(np.mean([r.map_time_s for r in mapped]))
                                    if mapped else None),
        "mapping_time_total_s": float(sum(r.map_time_s for r in mapped)),
        "mapping_optimise_time_total_s": float(sum(r.map_optimise_time_s for r in mapped)),
        "peak_cpu_memory_mb": peak_rss_mb(),
        "peak_gpu_memory_mb": gpu_peak,
        "points": len(odometry.point_map),
        "keyframes": sum(1 for r in results if r.is_keyframe),
        # Frames the recovery found suspect, recovered and lost (empty with recovery off).
        "tracking_events": odometry.tracking_events(),
        # Concurrent schedule: mapping calls run, mapping frames skipped, waits for keyframes.
        "mapping_schedule": odometry.schedule_stats(),
        "decoder_parameters": sum(p.numel() for p in odometry.decoders.parameters()),
        "device": device,
        "torch_threads": torch.get_num_threads(),
        "per_frame": [
            {"index": r.index, "timestamp": r.timestamp, "track_time_s": r.track_time_s,
             "track_iters": r.track_iters, "track_loss": r.track_loss,
             "track_event": r.track_event, "track_inlier_ratio": _finite(r.track_inlier_ratio),
             "track_residual_m": _finite(r.track_residual_m), "map_time_s": r.map_time_s,
             "map_optimise_time_s": r.map_optimise_time_s,
             "map_steps": r.map_steps, "points": r.n_points,
             "keyframe": r.is_keyframe}
            for r in results
        ],
    }


def _finite(value: float) -> float | None:
    """JSON has no NaN: a figure that was not measured is null."""
    return float(value) if np.isfinite(value) else None

"""The odometry's mapping calls: the `MapJob` a frame hands to the schedule, the co-visible
views a call optimises on, and the re-fit after the server changed the map. How a job runs,
in lock-step or on the mapping thread, is `cpslam.agent.schedule`'s. A part of the odometry
split out for size: it reads the odometry whole.
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING

import numpy as np
import torch

from cpslam.agent.mapper import View
from cpslam.agent.schedule import MapJob, torch_threads

if TYPE_CHECKING:
    from cpslam.agent.odometry import Odometry
    from cpslam.agent.recovery import Frame

__all__ = ["covisible_views", "mapping_job", "refit"]

# The odometry's log: a re-fit is one of its steps, reported beside its frames.
logger = logging.getLogger("cpslam.agent.odometry")


def mapping_job(odo: Odometry, current: Frame, T_world_cam: np.ndarray, kf_id: int | None,
                optimise: bool, count: int, generator: torch.Generator) -> MapJob:
    """The mapping call of this frame: register keyframe kf_id (when made here), then,
    with `optimise`, add points anchored to the latest keyframe and optimise on this
    frame and its co-visible keyframes. The pose is refined with the map when
    mapping.pose_lr > 0 and the frame is not a keyframe (a keyframe's pose anchors points
    and enters the pose table, so it stays as tracked)."""
    anchor = odo.keyframes.latest
    assert anchor is not None  # frame 0 is always a keyframe
    job = MapJob(count, current.index, np.asarray(T_world_cam, np.float64), anchor.kf_id,
                 kf_id, optimise)
    if not optimise:
        return job
    if count == 0:
        job.iters, job.n_pixels = odo.iters_first, odo.n_pixels_first
        job.publish_every = odo.first_publish_every
        job.waited_for = job.publish_every == 0
        job.lr_scale = odo.lr_scale_first
    else:
        job.iters = odo.iters_after_fusion if odo.fused else odo.iters
        job.n_pixels = odo.n_pixels
    odo.fused = False
    job.rgb, job.depth = current.rgb, current.depth
    job.views = covisible_views(odo, current.rgb_t, current.depth_t, T_world_cam,
                                exclude=() if kf_id is None else (kf_id,))
    job.pose_lr = odo.pose_lr if kf_id is None else 0.0
    # Lock-step continues the frame's stream after tracking; the mapping thread gets a
    # stream of its own (tracking's draws must not depend on when mapping runs).
    job.generator = generator if not odo.maps.concurrent else torch.Generator(
        device="cpu").manual_seed((odo.seed * 1_000_003 + current.index) * 2)
    return job


def covisible_views(odo: Odometry, rgb_t: torch.Tensor, depth_t: torch.Tensor,
                    T_world_cam: np.ndarray, exclude: tuple[int, ...] = ()) -> list[View]:
    """The frame and its co-visible keyframes (their stored small copies)."""
    views = [View(rgb_t, depth_t, T_world_cam, odo.intrinsics)]
    for other in odo.keyframes.covisible(T_world_cam, odo.intrinsics,
                                         odo.covisible_keyframes, exclude=exclude):
        kf = odo.keyframes.get(other)
        views.append(View(
            torch.from_numpy(kf.rgb_small).to(odo.device).float() / 255.0,
            torch.from_numpy(kf.depth_small).to(odo.device),
            kf.T_world_cam, odo.keyframes.intrinsics_small,
        ))
    return views


def refit(odo: Odometry, generator: torch.Generator) -> tuple[int, float]:
    """`mapping.iters_after_fusion` steps on the last frame (at its pose, which follows
    the server's corrections) and its co-visible keyframes; steps and seconds. The
    mapping thread is idle (drained) when this runs."""
    last = odo._last_frame
    if last is None or not len(odo.frames):
        return 0, 0.0  # nothing to fit on (resumed): the next mapping call does it
    odo.fused = False
    work = odo.maps.work
    with torch_threads(odo.all_threads):  # the tracker waits for it
        result = odo.mapper.optimise(work.point_map, work.decoders,
                                     covisible_views(odo, last.rgb_t, last.depth_t,
                                                     odo.frames.poses[-1]),
                                     odo.iters_after_fusion, odo.n_pixels, generator)
    odo.maps.republish()
    logger.debug("re-fit after a change from the server: %d steps, loss %.4f -> %.4f",
                 result.steps, result.loss_first, result.loss_last)
    return result.steps, result.seconds

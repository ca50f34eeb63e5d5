"""The per-agent SLAM front end: track every frame, map every `mapping.every` frames, make a
keyframe every `keyframes.every` frames.

Order within one frame: (1) clip depth to [camera.depth_min, camera.depth_max]; (2) track
against the map (the first frame defines the agent's world: identity) and, with the
`recovery` section enabled, check the result and re-track a suspect frame from other guesses
(`cpslam.agent.recovery`); (3) on a keyframe frame, store the keyframe and enter its pose in
the map's pose table; (4) on a mapping frame, add unexplained points and optimise on this frame
plus the co-visible keyframes. A frame whose tracking was lost is neither mapped nor made a
keyframe: both wait for the next frame that tracks (keyframes come every `keyframes.every`
frames, mapping every `mapping.every` frames, counted from the last one made).

Anchoring: new points are anchored to the LATEST keyframe (the first frame is always keyframe
0, so there is one). Between two keyframes the camera moves little, so points stay close to
their anchor's view, and all points created in one keyframe window move together when the
server corrects that keyframe; the keyframe records their ids.

Schedule (`run.schedule`, `cpslam.agent.schedule`): "lockstep" runs (3) and (4) inline, so a
CPU run repeats bit for bit; "concurrent" hands them to a mapping thread and tracks the next
frame at once, against the map the mapping thread published last. Then a frame's result
reports the mapping calls that finished while it was processed, and a mapping frame's
refined pose replaces its tracked one in the trajectory when its call finishes. Whatever
changes the map from outside (the server's corrections, foreign points, shared decoders)
goes through `editing()`, which first lets every handed-over call finish.

Ground truth (`frame.gt_pose`) is never read here. Random draws (pixels, ray jitter) come
from a torch.Generator seeded with (run.seed, frame index), so a lock-step CPU run is
reproducible.

Parts split out for size: the frame check (`cpslam.agent.frames`), the mapping call of a frame
and the re-fit (`cpslam.agent.jobs`), and the saved state (`cpslam.agent.snapshot`).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from contextlib import AbstractContextManager
from typing import TYPE_CHECKING

import numpy as np
import torch

from cpslam.agent.frames import FrameLog, FrameResult, checked_rgbd
from cpslam.agent.jobs import mapping_job, refit
from cpslam.agent.keyframes import KeyframeStore
from cpslam.agent.mapper import Mapper
from cpslam.agent.motion import MOTION_MODELS, motion_guesses
from cpslam.agent.recovery import Frame, Recovery
from cpslam.agent.schedule import (
    MapJob,
    MapOutcome,
    MapSchedule,
    MapState,
    run_map_job,
    split_threads,
)
from cpslam.agent.snapshot import FORMAT_VERSION as FORMAT_VERSION  # re-exported
from cpslam.agent.snapshot import odometry_state, restore_odometry
from cpslam.common.camera import Intrinsics
from cpslam.common.datasets import RGBDFrame
from cpslam.common.field import Decoders, FeatureCNN, NeuralPointMap
from cpslam.common.field.image_terms import ReferenceImage
from cpslam.common.field.tracking import Tracker, TrackResult
from cpslam.common.field_config import (
    field_spec,
    mapper_args_from_config,
    tracker_args_from_config,
)

if TYPE_CHECKING:
    from cpslam.common.config import CpslamConfig

logger = logging.getLogger(__name__)

__all__ = ["FrameResult", "Odometry"]


class Odometry:
    """Tracking, mapping and keyframes of one agent.

    Build it with `from_config`. The intrinsics are those of the PROCESSED images: the caller
    resizes frames by `camera.downscale` and passes matching intrinsics; Odometry never
    resizes.
    """

    def __init__(
        self,
        intrinsics: Intrinsics,
        point_map: NeuralPointMap,
        decoders: Decoders,
        cnn: FeatureCNN,
        tracker: Tracker,
        mapper: Mapper,
        keyframes: KeyframeStore,
        *,
        map_every: int,
        kf_every: int,
        iters_first: int,
        iters: int,
        iters_after_fusion: int,
        n_pixels_first: int,
        lr_scale_first: float,
        n_pixels: int,
        covisible_keyframes: int,
        pose_lr: float,
        init: str,
        depth_min: float,
        depth_max: float,
        seed: int,
        agent_id: int,
        recovery: Recovery | None,
        schedule: str = "lockstep",
        max_pending_keyframes: int = 2,
        mapping_threads: int | None = None,
        all_threads: int | None = None,
        first_publish_every: int = 0,
        previous_reference: float = 0.0,
    ) -> None:
        if init not in MOTION_MODELS:
            raise ValueError(f"Odometry: init must be zero_motion or constant_velocity, "
                             f"got {init!r}")
        if map_every < 1 or kf_every < 1:
            raise ValueError(f"Odometry: map_every and kf_every must be >= 1, got "
                             f"{map_every}, {kf_every}")
        self.intrinsics = intrinsics
        self.cnn = cnn
        self.maps = MapSchedule(MapState(point_map, decoders), self._run_job,
                                schedule=schedule, max_pending_keyframes=max_pending_keyframes,
                                threads=mapping_threads, solo_threads=all_threads)
        self.all_threads = all_threads
        self._unreported: list[MapOutcome] = []  # finished outside `step`, reported next
        self.tracker, self.mapper, self.keyframes = tracker, mapper, keyframes
        self.map_every, self.kf_every = map_every, kf_every
        self.iters_first, self.iters, self.iters_after_fusion = iters_first, iters, \
            iters_after_fusion
        self.n_pixels_first, self.n_pixels = n_pixels_first, n_pixels
        self.lr_scale_first = lr_scale_first
        self.first_publish_every = first_publish_every
        self.covisible_keyframes = covisible_keyframes
        self.pose_lr = pose_lr
        self.init = init
        self.depth_min, self.depth_max = depth_min, depth_max
        self.seed, self.agent_id = seed, agent_id
        self.device = point_map.device
        self.recovery = recovery
        self.fused = False
        self._last_frame: Frame | None = None  # for `_refit`
        self._last_tracked: Frame | None = None  # the recovery's RGB-D odometry starts here
        self._last_kf_count: int | None = None
        # The latest keyframe's full-size images for tracking.reference_weight.
        self._reference: tuple[int, ReferenceImage] | None = None
        self.previous_reference = previous_reference
        self._last_map_count: int | None = None
        self.frames = FrameLog()

    @classmethod
    def from_config(
        cls, cfg: CpslamConfig, intrinsics: Intrinsics, device: str, agent_id: int = 0
    ) -> Odometry:
        """Everything from the config's field, tracking, mapping, keyframes, camera and run
        sections, on `device`."""
        tr, mp = cfg.tracking, cfg.mapping
        seed = cfg.run.seed
        spec = field_spec(cfg.field)
        concurrent = cfg.run.schedule == "concurrent"
        all_threads = torch.get_num_threads() if concurrent else None
        return cls(
            intrinsics,
            spec.point_map(agent_id, device),
            spec.decoders(seed).to(device),
            spec.cnn(seed).to(device),
            Tracker(intrinsics, spec, **tracker_args_from_config(tr)),
            Mapper(spec, **mapper_args_from_config(mp)),
            KeyframeStore(intrinsics, cfg.keyframes.image_downscale),
            map_every=mp.every, kf_every=cfg.keyframes.every, iters_first=mp.iters_first,
            iters=mp.iters, iters_after_fusion=mp.iters_after_fusion,
            n_pixels_first=mp.n_pixels_first, n_pixels=mp.n_pixels,
            lr_scale_first=mp.lr_scale_first,
            covisible_keyframes=mp.covisible_keyframes, pose_lr=mp.pose_lr, init=tr.init,
            depth_min=cfg.camera.depth_min, depth_max=cfg.camera.depth_max,
            seed=seed, agent_id=agent_id,
            recovery=Recovery.from_config(cfg.recovery, tr.iters) if cfg.recovery.enabled
            else None,
            schedule=cfg.run.schedule, max_pending_keyframes=mp.max_pending_keyframes,
            mapping_threads=split_threads() if concurrent else None, all_threads=all_threads,
            first_publish_every=mp.first_publish_every,
            previous_reference=tr.previous_reference,
        )

    # ---------------------------------------------------------------------------- per frame

    def step(self, frame: RGBDFrame) -> FrameResult:
        """Process the next frame (processed resolution) and return what happened."""
        rgb, depth = checked_rgbd(frame, self.intrinsics, self.depth_min, self.depth_max)
        count = len(self.frames)
        generator = torch.Generator(device="cpu").manual_seed(
            self.seed * 1_000_003 + int(frame.index))
        finished, self._unreported = self._unreported + self._recorded(self.maps.collect()), []

        # The server changed the map or the decoders since the last frame: fit them to each
        # other before tracking leans on them (tracking against freshly averaged decoders
        # lost an agent of a two-agent run within ten frames of its merge: docs/odometry.md).
        refit_steps, refit_time = 0, 0.0
        if self.fused:
            finished += self._drain_worker()
            refit_steps, refit_time = refit(self, generator)
        if count > 0 and len(self.maps.published.point_map) == 0:
            self.maps.wait_for_map()  # nothing to track against before the first publish
        state = self.maps.published

        t0 = time.perf_counter()
        current = Frame.from_arrays(frame.index, rgb, depth, self.device)
        track_iters, track_loss, event = 0, 0.0, ""
        inliers = residual = float("nan")
        if count == 0:
            T_world_cam = np.eye(4)
        else:
            result, event = self._track(state, current, generator)
            T_world_cam, track_iters, track_loss = result.T_world_cam, result.iters, result.loss
            inliers, residual = result.inlier_ratio, result.residual_m
        track_time = time.perf_counter() - t0

        kf_id = None
        healthy = event != "lost"
        if healthy and (self._last_kf_count is None
                        or count - self._last_kf_count >= self.kf_every):
            kf = self.keyframes.add(frame.index, frame.timestamp, T_world_cam, rgb, depth)
            kf_id, self._last_kf_count = kf.kf_id, count
            self._set_reference(kf.kf_id)
        mapping = healthy and (self._last_map_count is None
                               or count - self._last_map_count >= self.map_every)
        self.frames.append(frame.timestamp, frame.index, T_world_cam, healthy)
        if mapping or kf_id is not None:
            t1 = time.perf_counter()
            job = mapping_job(self, current, T_world_cam, kf_id, mapping, count, generator)
            if mapping:
                self._last_map_count = count
            for outcome in self._recorded(self.maps.submit(job)):  # lock-step: done now
                outcome.seconds = time.perf_counter() - t1  # with the co-visibility
                finished.append(outcome)
        self._last_frame = current
        if healthy:
            self._last_tracked = current

        mapped = [o for o in finished if o.steps > 0]
        map_steps = refit_steps + sum(o.steps for o in mapped)
        map_time = refit_time + sum(o.seconds for o in mapped)
        optimise_time = refit_time + sum(o.optimise_s for o in mapped)
        logger.debug("frame %d: track %d it loss %.4f (%.2f s), map %d steps (%.2f s), %d pts",
                     frame.index, track_iters, track_loss, track_time, map_steps, map_time,
                     len(self.point_map))
        return FrameResult(
            index=int(frame.index), timestamp=float(frame.timestamp),
            T_world_cam=self.frames.poses[-1].copy(), track_time_s=track_time,
            track_iters=track_iters, track_loss=track_loss, map_time_s=map_time,
            map_steps=map_steps, map_optimise_time_s=optimise_time,
            n_points=len(self.point_map), is_keyframe=kf_id is not None, kf_id=kf_id,
            track_event=event, track_inlier_ratio=float(inliers),
            track_residual_m=float(residual),
        )

    @property
    def point_map(self) -> NeuralPointMap:
        """The map as tracking sees it (inside `editing()`: the one mapping works on)."""
        return self.maps.visible.point_map

    @property
    def decoders(self) -> Decoders:
        """The decoders as tracking sees them (inside `editing()`: mapping's)."""
        return self.maps.visible.decoders

    def editing(self) -> AbstractContextManager[MapState]:
        """Change the map, decoders, keyframe poses or trajectory from outside (between
        frames): waits for every handed-over mapping call, makes `point_map` and `decoders`
        the mapping side's, and publishes them when the block ends."""
        return self.maps.editing(lambda done: self._unreported.extend(self._recorded(done)))

    def drain(self) -> None:
        """Wait for every handed-over mapping call (at the end of a stream, before saving)."""
        self._unreported += self._drain_worker()

    def close(self) -> None:
        """Finish the handed-over mapping calls and stop the mapping thread (idempotent)."""
        self.drain()
        self.maps.close()

    def schedule_stats(self) -> dict[str, object]:
        """`MapSchedule.stats`: the schedule, mapping calls run, skipped, waits."""
        return self.maps.stats()

    def trajectory(self) -> tuple[np.ndarray, np.ndarray]:
        """Stamps [N] float64 and T_world_cam [N, 4, 4] of every frame so far."""
        return self.frames.trajectory()

    def set_frame_poses(self, T_world_cam: np.ndarray | list[np.ndarray]) -> None:
        """Replace every frame's pose [N, 4, 4] (a world or pose-graph correction from the
        server): the next frame is tracked from the last ones, so they must follow."""
        self.frames.set_poses(T_world_cam)

    @property
    def n_frames(self) -> int:
        """Frames processed so far."""
        return len(self.frames)

    def mark_fused(self) -> None:
        """The map or the decoders changed under the odometry (another agent's points joined,
        shared decoders were loaded): before the next frame is tracked, features and decoders
        are fitted for `mapping.iters_after_fusion` steps on the last frame and its co-visible
        keyframes (after a resume, which keeps no frame, the next mapping call runs them)."""
        self.fused = True

    # ---------------------------------------------------------------------------- internals

    def tracking_events(self) -> dict[str, int]:
        """Counts of the recovery: frames found suspect, recovered, lost (empty when off)."""
        if self.recovery is None:
            return {}
        return {k: int(self.recovery.counts.get(k, 0)) for k in ("suspect", "recovered", "lost")}

    def _set_reference(self, kf_id: int) -> None:
        """Make keyframe kf_id the view frames are compared with (tracking.reference_weight).

        Built from the keyframe's stored images (depth quantised as stored), so that a run
        resumed from `state_dict` compares with exactly the same view."""
        if self.tracker.reference_weight <= 0:
            return
        rgb, depth = self.keyframes.full_rgbd(kf_id)
        self._reference = (kf_id, ReferenceImage.from_rgbd(
            torch.from_numpy(rgb).to(self.device), torch.from_numpy(depth).to(self.device),
            self.keyframes.get(kf_id).T_world_cam, self.intrinsics.pinhole))

    def _reference_views(self) -> list[ReferenceImage]:
        """The views a frame is compared with (tracking.reference_weight): the latest
        keyframe and, with tracking.previous_reference (its weight), the previous frame at
        its tracked pose if it was tracked (a sharp view one frame away, for the scatter from
        frame to frame)."""
        views = []
        if self._reference is not None and self._reference[0] in self.keyframes:
            kf_id, view = self._reference
            view.T_world_ref = self.keyframes.get(kf_id).T_world_cam  # corrections
            views.append(view)
        previous = self._last_tracked
        if self.previous_reference > 0 and previous is not None and self.frames.tracked[-1] \
                and self.tracker.reference_weight > 0:
            views.append(ReferenceImage.from_rgbd(previous.rgb_t, previous.depth_t,
                                                  self.frames.poses[-1], self.intrinsics.pinhole,
                                                  weight=self.previous_reference))
        return views

    def _guesses(self) -> dict[str, np.ndarray]:
        return motion_guesses(self.frames.poses, self.frames.tracked)

    def _initial_pose(self) -> np.ndarray:
        guesses = self._guesses()
        return guesses.get(self.init, guesses["zero_motion"])

    def _track(self, state: MapState, current: Frame,
               generator: torch.Generator) -> tuple[TrackResult, str]:
        """Track the frame from the configured guess; check and recover it (recovery on)."""
        T_init = self._initial_pose()
        # The recovery draws its pixels from a seed of its own (leaving `generator` to the
        # mapping that follows, as without recovery).
        seed = (self.seed * 1_000_003 + current.index) * 2 + 1
        reference = self._reference_views()
        result = self.tracker.track(state.point_map, state.decoders, current.rgb_t,
                                    current.depth_t, T_init, generator, reference=reference)
        if self.recovery is None:
            return result, ""
        guesses = self._guesses()
        T_predicted = guesses.get("constant_velocity", guesses["zero_motion"])
        reason = self.recovery.check(result, T_predicted)
        if not reason:
            self.recovery.accept(result)
            return result, ""
        outcome = self.recovery.recover(
            self.tracker, state.point_map, state.decoders, current, result, reason, guesses,
            self._last_tracked, guesses["zero_motion"], self.intrinsics, self.keyframes, seed,
            reference)
        return outcome.result, outcome.event

    def _run_job(self, job: MapJob, state: MapState,
                 checkpoint: Callable[[], None] | None) -> MapOutcome:
        return run_map_job(job, state, self.mapper, self.cnn, self.intrinsics, self.agent_id,
                           checkpoint)

    def _recorded(self, outcomes: list[MapOutcome]) -> list[MapOutcome]:
        """Record finished mapping calls (the points they anchored, the refined poses)."""
        for outcome in outcomes:
            if len(outcome.point_ids) and outcome.anchor_kf in self.keyframes:
                self.keyframes.add_point_ids(outcome.anchor_kf, outcome.point_ids)
            if outcome.T_world_cam is not None and outcome.count < len(self.frames):
                self.frames.poses[outcome.count] = np.asarray(outcome.T_world_cam, np.float64)
        return outcomes

    def _drain_worker(self) -> list[MapOutcome]:
        """Wait for the mapping thread (concurrent) and record what it finished."""
        return self._recorded(self.maps.drain())

    # ---------------------------------------------------------------------------- save/load

    def state_dict(self) -> dict:
        """Everything needed to render or resume (plain tensors, numbers, strings, lists and
        dicts: loadable with torch.load(weights_only=True)); waits for the mapping thread
        (`cpslam.agent.snapshot`)."""
        return odometry_state(self)

    def load_state_dict(self, state: dict) -> None:
        """Restore what `state_dict` wrote (same config and processing resolution)."""
        restore_odometry(self, state)

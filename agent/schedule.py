"""How tracking and mapping share the map: in lock-step, or concurrently with mapping on its
own thread (`run.schedule`).

Lock-step: every mapping call runs inline, right after the frame that asked for it was
tracked, on the one map the tracker reads; a CPU run repeats bit for bit.

Concurrent: the tracker hands each mapping call over as a `MapJob` and goes on with the next
frame; a `MappingWorker` runs the jobs in order on its working copy of the map and decoders
and, after each call, publishes a copy of them (`MapState`). The tracker reads the latest
published state, swapped in as one reference between mapping calls, so it never sees
features or decoders half way through an optimiser step. On CUDA the worker runs on its own
stream and synchronises it before publishing.

Back-pressure (the worker falls behind): at most one frame that is only a mapping frame waits
for the worker; a newer one replaces it and the older is skipped (counted and logged: the
newer frame sees the same surroundings, one step further). A keyframe's job is never dropped;
when `max_pending_keyframes` of them already wait, the tracker waits for room (counted too).

A job with `publish_every` > 0 (the first mapping call) also publishes a copy every that many
steps, so tracking starts from the map as it is then instead of waiting for the whole call.

Threads: the worker runs with its own share of the process's torch threads, the tracker with
the rest. A job the tracker waits for whole (`MapJob.waited_for`: the first call, when it is
not published part way) runs with all of them, the tracker's share idling meanwhile.
"""

from __future__ import annotations

import copy
import logging
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from contextlib import contextmanager, nullcontext
from dataclasses import dataclass, field

import numpy as np
import torch

from cpslam.agent.mapper import Mapper, View
from cpslam.common.camera import Intrinsics
from cpslam.common.field import Decoders, FeatureCNN, NeuralPointMap

logger = logging.getLogger(__name__)

__all__ = ["SCHEDULES", "MapJob", "MapOutcome", "MapSchedule", "MapState", "MappingWorker",
           "run_map_job", "split_threads", "torch_threads"]

SCHEDULES = ("concurrent", "lockstep")


@dataclass(frozen=True)
class MapState:
    """A map and the decoders that render it, read together."""

    point_map: NeuralPointMap
    decoders: Decoders

    def copy(self) -> MapState:
        """An independent copy (tensors cloned), for publishing."""
        everything = torch.ones(len(self.point_map), dtype=torch.bool,
                                device=self.point_map.device)
        return MapState(self.point_map.subset(everything), copy.deepcopy(self.decoders))


@dataclass
class MapJob:
    """One mapping call handed over by the tracker (frame `count` of the trajectory).

    register_kf: a keyframe made at this frame, entered in the map's pose table at
    T_world_cam before anything else; with `optimise` False the job does only that.
    views: the frame (views[0]) and its co-visible keyframes' small copies.
    """

    count: int
    index: int
    T_world_cam: np.ndarray  # [4, 4] float64
    anchor_kf: int
    register_kf: int | None
    optimise: bool
    rgb: np.ndarray | None = None  # uint8 [H, W, 3]
    depth: np.ndarray | None = None  # float32 [H, W]
    views: list[View] = field(default_factory=list)
    iters: int = 0
    n_pixels: int = 0
    pose_lr: float = 0.0
    generator: torch.Generator | None = None
    publish_every: int = 0  # concurrent: also publish every this many steps (0: at the end)
    waited_for: bool = False  # the tracker waits for its end: it may use every thread
    lr_scale: float = 1.0  # times the mapper's learning rates

    @property
    def droppable(self) -> bool:
        """Only a mapping frame (not a keyframe): may be skipped when mapping falls behind."""
        return self.optimise and self.register_kf is None


@dataclass
class MapOutcome:
    """What a job did: points added (anchored to anchor_kf), optimisation steps and seconds,
    the whole call's seconds, and the frame's refined pose (None when not refined)."""

    count: int
    index: int
    anchor_kf: int
    point_ids: torch.Tensor
    steps: int
    optimise_s: float
    seconds: float
    T_world_cam: np.ndarray | None


def run_map_job(job: MapJob, state: MapState, mapper: Mapper, cnn: FeatureCNN,
                intrinsics: Intrinsics, agent_id: int,
                checkpoint: Callable[[], None] | None = None) -> MapOutcome:
    """Register the keyframe, add the frame's unexplained points, optimise (in this order);
    `checkpoint` publishes the state mid-way, every `job.publish_every` steps."""
    start = time.perf_counter()
    pm, decoders = state.point_map, state.decoders
    if job.register_kf is not None:
        pm.set_keyframe_poses(job.register_kf, job.T_world_cam, agent_id)
    if not job.optimise:
        return MapOutcome(job.count, job.index, job.anchor_kf, torch.zeros(0, dtype=torch.int64),
                          0, 0.0, time.perf_counter() - start, None)
    assert job.rgb is not None and job.depth is not None and job.generator is not None
    ids = mapper.add_points(pm, decoders, cnn, job.rgb, job.depth, intrinsics, job.T_world_cam,
                            job.anchor_kf, job.generator)
    result = mapper.optimise(pm, decoders, job.views, job.iters, job.n_pixels, job.generator,
                             pose_lr=job.pose_lr, checkpoint_every=job.publish_every,
                             lr_scale=job.lr_scale,
                             checkpoint=checkpoint)
    return MapOutcome(job.count, job.index, job.anchor_kf, ids, result.steps, result.seconds,
                      time.perf_counter() - start, result.T_world_cam)


def split_threads() -> int:
    """Torch threads of the mapping thread; the calling (tracking) thread keeps the rest, so
    the two together use what `run.num_threads` gave the process (at least one each)."""
    total = torch.get_num_threads()
    mapping = max(1, total // 2)
    torch.set_num_threads(max(1, total - mapping))
    return mapping


@contextmanager
def torch_threads(n: int | None) -> Iterator[None]:
    """This thread's torch CPU threads set to n (None: unchanged) for the block, then restored."""
    before = torch.get_num_threads()
    if n is not None and n != before:
        torch.set_num_threads(n)
    try:
        yield
    finally:
        if torch.get_num_threads() != before:
            torch.set_num_threads(before)


class MappingWorker:
    """Runs `MapJob`s in order on a thread of its own (see the module docstring).

    Args:
        run: runs one job on the working state (`run_map_job` bound to it); its second
            argument publishes a snapshot mid-way.
        snapshot: a copy of the working state (taken on this thread after each job that
            optimised).
        publish: makes a snapshot the tracker's (once its copies are complete on CUDA).
        max_pending_keyframes: keyframe jobs that may wait before `submit` blocks.
        threads: torch CPU threads of the worker (None = torch's default for a new thread).
        solo_threads: its threads for a job with `waited_for` set (None = `threads`).
        device: the map's device; on CUDA the worker uses a stream of its own.
    """

    def __init__(self, run: Callable[[MapJob, Callable[[], None]], MapOutcome],
                 snapshot: Callable[[], MapState],
                 publish: Callable[[MapState], None], *,
                 max_pending_keyframes: int, threads: int | None,
                 device: torch.device, solo_threads: int | None = None) -> None:
        if max_pending_keyframes < 1:
            raise ValueError(f"MappingWorker: max_pending_keyframes must be >= 1, got "
                             f"{max_pending_keyframes}")
        self._run, self._snapshot, self._publish = run, snapshot, publish
        self.max_pending_keyframes = max_pending_keyframes
        self.threads, self.device = threads, device
        self.solo_threads = solo_threads if solo_threads is not None else threads
        self.counts = {"jobs": 0, "skipped": 0, "waits": 0, "checkpoints": 0}
        self.wait_s = 0.0
        self._jobs: deque[MapJob] = deque()
        self._done: list[MapOutcome] = []
        self._busy = False
        self._stop = False
        self._error: BaseException | None = None
        self._stream: torch.cuda.Stream | None = None
        self._cond = threading.Condition()
        self._thread = threading.Thread(target=self._loop, name="cpslam-mapping", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------ the tracker's side

    def submit(self, job: MapJob) -> None:
        """Queue a job; skips a waiting mapping-only frame, waits when keyframes pile up."""
        with self._cond:
            self._raise_error()
            if job.droppable:
                for old in [j for j in self._jobs if j.droppable]:
                    self._jobs.remove(old)
                    self.counts["skipped"] += 1
                    logger.info("mapping falls behind: skipped mapping frame %d for frame %d",
                                old.index, job.index)
            else:
                start = time.perf_counter()
                waited = False
                while sum(not j.droppable for j in self._jobs) >= self.max_pending_keyframes:
                    waited = True
                    self._cond.wait()
                    self._raise_error()
                if waited:
                    self.counts["waits"] += 1
                    self.wait_s += time.perf_counter() - start
            self._jobs.append(job)
            self._cond.notify_all()

    def collect(self) -> list[MapOutcome]:
        """Outcomes of the jobs finished since the last call (never waits)."""
        with self._cond:
            self._raise_error()
            done, self._done = self._done, []
            return done

    def drain(self) -> list[MapOutcome]:
        """Wait until every queued job ran; their outcomes and earlier uncollected ones."""
        with self._cond:
            while (self._jobs or self._busy) and self._error is None:
                self._cond.wait()
            self._raise_error()
            done, self._done = self._done, []
            return done

    def wait_published(self, ready: Callable[[], bool]) -> None:
        """Wait until `ready()` holds, re-checked after every publish, or nothing is left to
        run (the caller then sees what the last job left)."""
        with self._cond:
            while not ready() and (self._jobs or self._busy) and self._error is None:
                self._cond.wait()
            self._raise_error()

    @property
    def idle(self) -> bool:
        """No job waiting or running."""
        with self._cond:
            return not self._jobs and not self._busy

    def close(self) -> None:
        """Run what is queued, then stop the thread (idempotent)."""
        with self._cond:
            self._stop = True
            self._cond.notify_all()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join()

    # ------------------------------------------------------------------ the worker's side

    def _loop(self) -> None:
        if self.threads is not None:
            torch.set_num_threads(self.threads)  # this thread's own OpenMP team size
        stream = torch.cuda.Stream(self.device) if self.device.type == "cuda" else None
        self._stream = stream
        while True:
            with self._cond:
                while not self._jobs and not self._stop:
                    self._cond.wait()
                if not self._jobs:
                    return
                job = self._jobs.popleft()
                self._busy = True
                self._cond.notify_all()  # a tracker waiting for room may go on
            try:
                with torch.cuda.stream(stream) if stream is not None else nullcontext(), \
                        torch_threads(self.solo_threads if job.waited_for else None):
                    outcome = self._run(job, self._checkpoint)
                    snapshot = self._snapshot() if job.optimise else None
                if stream is not None:
                    stream.synchronize()
                if snapshot is not None:
                    self._publish(snapshot)
            except BaseException as exc:  # handed to the tracker's thread, never swallowed
                logger.exception("mapping thread failed on frame %d", job.index)
                with self._cond:
                    self._error, self._busy = exc, False
                    self._jobs.clear()
                    self._cond.notify_all()
                return
            with self._cond:
                self._done.append(outcome)
                self.counts["jobs"] += 1
                self._busy = False
                self._cond.notify_all()

    def _checkpoint(self) -> None:
        """Publish a copy of the working state in the middle of a job (worker thread)."""
        snapshot = self._snapshot()
        if self._stream is not None:
            self._stream.synchronize()
        self._publish(snapshot)
        with self._cond:
            self.counts["checkpoints"] += 1
            self._cond.notify_all()

    def _raise_error(self) -> None:
        if self._error is not None:
            raise RuntimeError(f"the mapping thread failed: {self._error!r}") from self._error


class MapSchedule:
    """Who holds the map: the mapping side's working state, the state tracking reads, and
    the mapping thread between them (concurrent) or nothing between them (lock-step).

    Args:
        state: the map and decoders to start from.
        run: runs one job on a state (`run_map_job` with the odometry's mapper bound); its
            third argument publishes mid-way (None in lock-step, where nobody reads meanwhile).
        schedule: "concurrent" or "lockstep".
        max_pending_keyframes, threads, solo_threads: the `MappingWorker`'s (concurrent only).
    """

    def __init__(self, state: MapState,
                 run: Callable[[MapJob, MapState, Callable[[], None] | None], MapOutcome], *,
                 schedule: str, max_pending_keyframes: int, threads: int | None,
                 solo_threads: int | None = None) -> None:
        if schedule not in SCHEDULES:
            raise ValueError(f"schedule must be one of {SCHEDULES}, got {schedule!r}")
        self.schedule = schedule
        self.work = state
        # Lock-step: the same objects; concurrent: never the ones the worker writes.
        self.published = state if schedule == "lockstep" else state.copy()
        self._run = run
        self._editing = 0
        self._worker = None if schedule == "lockstep" else MappingWorker(
            lambda job, checkpoint: run(job, self.work, checkpoint), lambda: self.work.copy(),
            self._publish,
            max_pending_keyframes=max_pending_keyframes, threads=threads,
            device=state.point_map.device, solo_threads=solo_threads)

    @property
    def concurrent(self) -> bool:
        return self._worker is not None

    @property
    def visible(self) -> MapState:
        """What callers outside see: the published state, the working one while editing."""
        return self.work if self._editing else self.published

    def submit(self, job: MapJob) -> list[MapOutcome]:
        """Lock-step: run the job now and return its outcome; concurrent: hand it over."""
        if self._worker is None:
            return [self._run(job, self.work, None)]
        self._worker.submit(job)
        return []

    def collect(self) -> list[MapOutcome]:
        """Outcomes finished since the last call (never waits)."""
        return self._worker.collect() if self._worker is not None else []

    def drain(self) -> list[MapOutcome]:
        """Wait for every handed-over job; their outcomes and earlier uncollected ones."""
        return self._worker.drain() if self._worker is not None else []

    def wait_for_map(self) -> None:
        """Wait until the published map has points (the first call's first publish), or
        until nothing handed over is left to run."""
        if self._worker is not None:
            self._worker.wait_published(lambda: len(self.published.point_map) > 0)

    @contextmanager
    def editing(self, drained: Callable[[list[MapOutcome]], None]) -> Iterator[MapState]:
        """Drain (`drained` gets the outcomes), hand out the working state, republish."""
        drained(self.drain())
        self._editing += 1  # nests: a server update may load the decoders it carries
        try:
            yield self.work
        finally:
            self._editing -= 1
            if not self._editing:
                self.republish()

    def republish(self) -> None:
        """Publish the working state after a change made outside the mapping thread (which
        must be idle: drained)."""
        if self._worker is not None:
            self.published = self.work.copy()

    def stats(self) -> dict[str, object]:
        """The schedule and, when concurrent, the mapping thread's counts: jobs run, mapping
        frames skipped because it fell behind, times tracking waited for it and how long."""
        out: dict[str, object] = {"schedule": self.schedule}
        if self._worker is not None:
            out.update(self._worker.counts, wait_s=round(self._worker.wait_s, 3))
        return out

    def close(self) -> None:
        if self._worker is not None:
            self._worker.close()

    def _publish(self, state: MapState) -> None:
        self.published = state  # one reference: tracking takes it whole or not at all

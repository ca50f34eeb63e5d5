"""The schedule of tracking and mapping (`cpslam.agent.schedule`): what tracking reads is
never half written, the back-pressure policy, errors reach the tracker, lock-step runs
inline."""

from __future__ import annotations

import threading

import numpy as np
import pytest
import torch

from cpslam.agent.schedule import MapJob, MapOutcome, MapSchedule, MapState, torch_threads
from tests.unit.spec_helpers import spec

N_POINTS = 64


def _state(n_points: int = N_POINTS) -> MapState:
    s = spec("tiny")
    point_map = s.point_map(0, "cpu")
    point_map.set_keyframe_poses(0, np.eye(4), 0)
    if n_points:
        point_map.add_points(torch.rand(n_points, 3), 0, torch.zeros(n_points, s.feature_dim),
                             torch.zeros(n_points, 3, dtype=torch.uint8))
    return MapState(point_map, s.decoders(0))


def _job(count: int, keyframe: bool = False, optimise: bool = True) -> MapJob:
    return MapJob(count, count, np.eye(4), 0, count if keyframe else None, optimise)


def _outcome(job: MapJob, steps: int = 1) -> MapOutcome:
    return MapOutcome(job.count, job.index, job.anchor_kf, torch.zeros(0, dtype=torch.int64),
                      steps, 0.0, 0.0, None)


def _values(state: MapState) -> set[float]:
    """Every distinct value held by the features and the decoders' parameters."""
    tensors = [state.point_map.features.detach(), *(p.detach() for p in
                                                    state.decoders.parameters())]
    return set(torch.cat([t.reshape(-1) for t in tensors]).unique().tolist())


def test_tracking_never_reads_a_half_written_map() -> None:
    """A mapping job writes features and decoders in many small in-place steps, as an
    optimiser does; a reader hammering the published state must see one value throughout."""
    jobs = 60

    def run(job: MapJob, state: MapState, checkpoint: object) -> MapOutcome:
        value = float(job.count + 1)
        with torch.no_grad():
            features = state.point_map.features
            for row in range(0, len(features), 8):
                features[row:row + 8] = value
            for parameter in state.decoders.parameters():
                parameter.fill_(value)
        return _outcome(job)

    state = _state()
    with torch.no_grad():
        for parameter in state.decoders.parameters():
            parameter.zero_()
    maps = MapSchedule(state, run, schedule="concurrent", max_pending_keyframes=1000,
                       threads=1)
    seen: list[set[float]] = []
    stop = threading.Event()

    def reader() -> None:
        while not stop.is_set():
            seen.append(_values(maps.published))

    thread = threading.Thread(target=reader)
    thread.start()
    try:
        for count in range(jobs):
            maps.submit(_job(count, keyframe=True))  # keyframe jobs: none is skipped
        assert len(maps.drain()) == jobs
    finally:
        stop.set()
        thread.join()
        maps.close()
    assert seen and all(len(values) == 1 for values in seen), \
        [v for v in seen if len(v) != 1][:3]
    assert _values(maps.published) == {float(jobs)}
    # The reader saw states in order: publication never goes back.
    order = [next(iter(v)) for v in seen]
    assert order == sorted(order)


def _blocking_schedule(max_pending_keyframes: int) -> tuple[MapSchedule, threading.Event,
                                                             list[int]]:
    release, ran = threading.Event(), []

    def run(job: MapJob, state: MapState, checkpoint: object) -> MapOutcome:
        release.wait()
        ran.append(job.count)
        return _outcome(job)

    maps = MapSchedule(_state(), run, schedule="concurrent",
                       max_pending_keyframes=max_pending_keyframes, threads=1)
    return maps, release, ran


def test_mapping_frames_are_skipped_keyframes_never() -> None:
    maps, release, ran = _blocking_schedule(max_pending_keyframes=10)
    try:
        maps.submit(_job(0, keyframe=True))  # runs (and blocks) at once
        maps.submit(_job(1))
        maps.submit(_job(2, keyframe=True))
        maps.submit(_job(3))  # replaces 1, which waits
        maps.submit(_job(4))  # replaces 3
        release.set()
        done = maps.drain()
    finally:
        release.set()
        maps.close()
    assert ran[0] == 0 and sorted(ran) == [0, 2, 4], ran
    assert sorted(o.count for o in done) == [0, 2, 4]
    stats = maps.stats()
    assert stats["skipped"] == 2 and stats["jobs"] == 3 and stats["waits"] == 0


def test_tracking_waits_when_keyframes_pile_up() -> None:
    maps, release, ran = _blocking_schedule(max_pending_keyframes=1)
    submitted = threading.Event()
    try:
        maps.submit(_job(0, keyframe=True))  # running
        maps.submit(_job(1, keyframe=True))  # waits: the one allowed
        late = threading.Thread(target=lambda: (maps.submit(_job(2, keyframe=True)),
                                                submitted.set()))
        late.start()
        # The third keyframe cannot be queued while two are ahead of it (the worker is
        # blocked, so no timing can let it through).
        assert not submitted.wait(0.3)
        release.set()
        late.join()
        maps.drain()
    finally:
        release.set()
        maps.close()
    assert ran == [0, 1, 2]
    assert maps.stats()["waits"] >= 1  # 2 when job 1 came before the worker took job 0


def test_a_failed_mapping_call_reaches_the_tracker() -> None:
    def run(job: MapJob, state: MapState, checkpoint: object) -> MapOutcome:
        raise ValueError("boom")

    maps = MapSchedule(_state(), run, schedule="concurrent", max_pending_keyframes=2,
                       threads=1)
    maps.submit(_job(0, keyframe=True))
    with pytest.raises(RuntimeError, match="mapping thread failed.*boom"):
        maps.drain()
    with pytest.raises(RuntimeError, match="mapping thread failed"):
        maps.submit(_job(1))
    maps.close()


def test_lockstep_runs_inline_on_the_one_state() -> None:
    calls = []

    def run(job: MapJob, state: MapState, checkpoint: object) -> MapOutcome:
        calls.append(state)
        return _outcome(job, steps=3)

    state = _state()
    maps = MapSchedule(state, run, schedule="lockstep", max_pending_keyframes=1, threads=None)
    out = maps.submit(_job(0))
    assert [o.steps for o in out] == [3] and calls == [state]
    assert maps.published is maps.work is state
    assert maps.collect() == [] and maps.drain() == []
    assert maps.stats() == {"schedule": "lockstep"}


def test_editing_drains_then_publishes_once() -> None:
    state = _state()

    def run(job: MapJob, s: MapState, checkpoint: object) -> MapOutcome:
        with torch.no_grad():
            s.point_map.features.fill_(1.0)
        return _outcome(job)

    maps = MapSchedule(state, run, schedule="concurrent", max_pending_keyframes=2, threads=1)
    drained: list[MapOutcome] = []
    try:
        maps.submit(_job(0, keyframe=True))
        with maps.editing(drained.extend) as work:
            assert work is maps.work and maps.visible is work
            assert [o.count for o in drained] == [0]
            with maps.editing(drained.extend):  # nested: publishes at the outer end only
                with torch.no_grad():
                    work.point_map.features.fill_(2.0)
            assert maps.visible is work
            assert not bool((maps.published.point_map.features == 2.0).any())
        assert maps.visible is maps.published and maps.published is not work
        assert bool((maps.published.point_map.features == 2.0).all())
    finally:
        maps.close()


def test_a_checkpoint_lets_tracking_start_before_the_call_ends() -> None:
    """The first call publishes mid-way: `wait_for_map` returns on the first publish while
    the call still runs, and the tracker sees the map as it was then."""
    state = _state(n_points=0)  # the first call starts from an empty map
    release = threading.Event()
    checkpoints: list[bool] = []

    def run(job: MapJob, s: MapState, checkpoint) -> MapOutcome:
        s.point_map.add_points(torch.rand(N_POINTS, 3), 0,
                               torch.ones(N_POINTS, s.point_map.feature_dim),
                               torch.zeros(N_POINTS, 3, dtype=torch.uint8))
        checkpoints.append(checkpoint is not None)
        checkpoint()
        release.wait()
        with torch.no_grad():
            s.point_map.features.fill_(2.0)
        return _outcome(job)

    maps = MapSchedule(state, run, schedule="concurrent", max_pending_keyframes=2, threads=1)
    try:
        assert len(maps.published.point_map) == 0
        maps.submit(_job(0, keyframe=True))
        maps.wait_for_map()  # would hang here if it waited for the whole call
        # The call cannot have ended: it waits for `release`, set only below.
        assert len(maps.published.point_map) == len(maps.work.point_map) > 0
        assert bool((maps.published.point_map.features == 1.0).all())
        release.set()
        maps.drain()
        assert bool((maps.published.point_map.features == 2.0).all())
        assert maps.stats()["checkpoints"] == 1 and checkpoints == [True]
    finally:
        release.set()
        maps.close()


def test_wait_for_map_returns_when_nothing_is_left_to_run() -> None:
    maps = MapSchedule(_state(n_points=0), lambda job, s, checkpoint: _outcome(job),
                       schedule="concurrent", max_pending_keyframes=2, threads=1)
    try:
        maps.wait_for_map()  # no job and an empty map: returns, nothing to wait for
    finally:
        maps.close()


def test_unknown_schedule_is_refused() -> None:
    with pytest.raises(ValueError, match="schedule must be one of"):
        MapSchedule(_state(), lambda job, s, checkpoint: _outcome(job), schedule="async",
                    max_pending_keyframes=1, threads=None)


def test_a_job_the_tracker_waits_for_runs_with_every_thread() -> None:
    """`waited_for` jobs get the worker's solo thread count, the others its own share; the
    worker's count is its own share again after a solo job."""
    seen: list[tuple[int, int]] = []

    def run(job: MapJob, s: MapState, checkpoint: object) -> MapOutcome:
        seen.append((job.count, torch.get_num_threads()))
        return _outcome(job)

    tracker_threads = torch.get_num_threads()
    maps = MapSchedule(_state(), run, schedule="concurrent", max_pending_keyframes=2,
                       threads=1, solo_threads=3)
    try:
        first = _job(0, keyframe=True)
        first.waited_for = True
        for job in (first, _job(1), _job(2, keyframe=True)):
            maps.submit(job)
            maps.drain()  # one at a time: none is skipped
    finally:
        maps.close()
    assert seen == [(0, 3), (1, 1), (2, 1)]
    assert torch.get_num_threads() == tracker_threads  # the tracker's own count is untouched


def test_torch_threads_restores_the_count_after_an_error() -> None:
    before = torch.get_num_threads()
    with pytest.raises(RuntimeError), torch_threads(before + 1):
        assert torch.get_num_threads() == before + 1
        raise RuntimeError("inside")
    assert torch.get_num_threads() == before
    with torch_threads(None):
        assert torch.get_num_threads() == before

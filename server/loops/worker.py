"""Loop verification on a background thread, so that registering a candidate pair (image
pulls, RANSAC + ICP, rendering refinement: up to seconds each) never holds up the server's
poll loop, its acknowledgements or its status replies.

The poll loop hands the worker one candidate at a time (`submit`, only when it is `idle`, so
the queue stays in the loop's hands and a pair that can merge two groups still goes first)
and collects what it found (`finished`); the pipeline's `conclude` then records it on the
loop's thread. What the refinement reads of the back end's state is read at `submit`
(`LoopPipeline.refiner(eager=True)`), so the worker never sees a half-applied message.
"""

from __future__ import annotations

import logging
import threading
from typing import TYPE_CHECKING

from cpslam.server.loops.pipeline import Assessment

if TYPE_CHECKING:
    from cpslam.server.loops.candidates import Candidate
    from cpslam.server.loops.pipeline import LoopPipeline

__all__ = ["VerifyWorker"]

logger = logging.getLogger(__name__)


class VerifyWorker:
    """One thread assessing one candidate at a time for `pipeline` (module docstring)."""

    def __init__(self, pipeline: LoopPipeline) -> None:
        self.pipeline = pipeline
        self._cond = threading.Condition()
        self._job: tuple[Candidate, object] | None = None  # waiting for the thread
        self._running: Candidate | None = None
        self._done: list[Assessment] = []
        self._closed = False
        self._thread = threading.Thread(target=self._work, name="loop-verify", daemon=True)
        self._thread.start()

    @property
    def idle(self) -> bool:
        """No candidate is waiting or being assessed (finished ones may wait to be collected)."""
        with self._cond:
            return self._job is None and self._running is None

    def in_flight(self) -> list[Candidate]:
        """Candidates handed over and not yet collected (kept by a state snapshot)."""
        with self._cond:
            pending = [self._job[0]] if self._job is not None else []
            running = [self._running] if self._running is not None else []
            return [*pending, *running, *(a.cand for a in self._done)]

    def submit(self, cand: Candidate) -> None:
        """Hand `cand` over (the worker must be `idle`); its refinement's inputs are read now."""
        refine = self.pipeline.refiner(cand, eager=True)
        with self._cond:
            if self._closed:
                raise RuntimeError("the loop verification worker is closed")
            if self._job is not None or self._running is not None:
                raise RuntimeError("the loop verification worker is busy")
            self._job = (cand, refine)
            self._cond.notify_all()

    def finished(self) -> list[Assessment]:
        """The assessments completed since the last call, in order."""
        with self._cond:
            done, self._done = self._done, []
            return done

    def wait_idle(self, timeout_s: float | None = None) -> bool:
        """Wait until the worker is idle (at most `timeout_s`); whether it is."""
        with self._cond:
            return self._cond.wait_for(lambda: self._job is None and self._running is None,
                                       timeout_s)

    def drain(self, timeout_s: float | None = None) -> list[Assessment]:
        """Wait until the worker is idle (at most `timeout_s`) and return what it finished."""
        self.wait_idle(timeout_s)
        return self.finished()

    def close(self) -> None:
        """Stop the thread after the candidate it is on (idempotent)."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()
        if self._thread is not threading.current_thread():
            self._thread.join()

    def _work(self) -> None:
        while True:
            with self._cond:
                self._cond.wait_for(lambda: self._job is not None or self._closed)
                if self._job is None:
                    return
                (cand, refine), self._job = self._job, None
                self._running = cand
            try:
                done = self.pipeline.assess(cand, refine)
            except BaseException:  # noqa: BLE001 - assess catches its own; this is a bug
                logger.exception("loop verification worker failed on %s/%d - %s/%d",
                                 cand.agent_a, cand.kf_a, cand.agent_b, cand.kf_b)
                done = Assessment(cand, None, "verification worker error", False, 0.0)
            with self._cond:
                self._done.append(done)
                self._running = None
                self._cond.notify_all()

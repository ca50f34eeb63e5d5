"""The loop pipeline: candidates from the descriptor database, each pair registered, refined
and verified once, the verdicts as `LoopRecord`s.

Per new keyframe: descriptor query -> candidates (fine/coarse, `candidates`) -> `LoopBook`
(`book`: each pair verified once; one whose images could not be pulled is tried again
``retry_after_s`` later, up to ``loop.max_attempts`` tries) -> both images pulled (cached) ->
coarse registration (`registration`: RANSAC + ICP, or the identity with ``loop.coarse_method:
none``, the paper) -> optional rendering-based refinement (``refine_pose``, `refinement`) ->
accept/reject by overlap and residual (`verification`). What an accepted loop then does
(merge, pose graph) is the back end's business (`cpslam.server.backend`).
"""

from __future__ import annotations

import logging
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from cpslam.server.loops.book import LoopBook
from cpslam.server.loops.candidates import (
    Candidate,
    DescriptorDatabase,
    LoopCandidate,
    LoopDatabase,
)
from cpslam.server.loops.registration import coarse_register
from cpslam.server.loops.verification import LoopRecord, judge, loop_record

if TYPE_CHECKING:
    from cpslam.common.config.collab import LoopConfig
    from cpslam.protocol import KeyframeImage
    from cpslam.server.loops.worker import VerifyWorker

__all__ = ["Assessment", "LoopPipeline"]

logger = logging.getLogger(__name__)

RECENT_LOOPS = 200
"""Verified loop pairs listed in the status summary (the newest; keeps the reply small)."""


@dataclass
class Assessment:
    """What `LoopPipeline.assess` found for a candidate, before `conclude` records it."""

    cand: Candidate
    reg: Any  # the registration used (None: none ran)
    reason: str  # empty: accepted
    unavailable: bool  # an image could not be pulled: the pair is tried again later
    seconds: float


class LoopPipeline:
    """Loop candidates queued, verified and recorded (see the module docstring).

    Args:
        loop: the config section (candidates per query, thresholds, coarse method, tries).
        fetch_image: ``(agent_id, kf_id) -> KeyframeImage | None``; images are cached (64,
            and at most `image_cache_bytes` of decoded pixels; the oldest go first).
        now: monotonic clock (s); t_start: its value that record stamps count from.
        refine_pose: optional ``(candidate, T_a_b_init, image_a, image_b) -> Registration |
            None`` refining a coarse loop pose (a `PoseRefiner`); None uses the coarse one.
        database: loop database (default: `cpslam.server.loops.DescriptorDatabase`).
        register: ``(src_image_b, dst_image_a) -> Registration``, the coarse stage (default:
            `register_rgbd`, or with ``loop.coarse_method`` "none" the identity, verified).
        seed: of the registration's RANSAC.
        retry_after_s: a candidate whose keyframe images could not be pulled is tried again
            this many seconds later (``loop.max_attempts`` tries in all).
        image_cache_bytes: bytes of images the cache holds (``limits.image_cache_mb``);
            None: only the count bounds it.
    """

    def __init__(
        self,
        loop: LoopConfig,
        fetch_image: Callable[[str, int], KeyframeImage | None],
        now: Callable[[], float],
        t_start: float,
        refine_pose: Callable[..., Any] | None = None,
        database: LoopDatabase | None = None,
        register: Callable[[KeyframeImage, KeyframeImage], Any] | None = None,
        seed: int = 0,
        retry_after_s: float = 5.0,
        image_cache_bytes: int | None = None,
    ) -> None:
        self.loop_cfg, self.fetch_image = loop, fetch_image
        self.now, self.t_start = now, t_start
        self.refine_pose = refine_pose
        self.database = database if database is not None else DescriptorDatabase.from_config(loop)
        self.register = register or coarse_register(loop, seed)
        self.retry_after_s = retry_after_s
        self.image_cache_bytes = image_cache_bytes
        self._image_bytes = 0
        self.book = LoopBook(max_attempts=loop.max_attempts)
        self.records: list[LoopRecord] = []
        self._accepted: dict[tuple[str, str], list[LoopRecord]] = {}  # by `_agents`
        self.skipped = 0
        """Candidates not verified: an accepted or waiting pair lies near (``loop.spacing``)."""
        self.queue: list[Candidate] = []  # selected by the book, waiting for verification
        self.retry: list[tuple[float, Candidate]] = []  # (due time, candidate)
        self._images: OrderedDict[tuple[str, int], KeyframeImage | None] = OrderedDict()
        self._images_lock = threading.Lock()  # the verification worker pulls images too
        self._warned_refine = False
        self.worker: VerifyWorker | None = None  # `start_worker`
        if loop.coarse_method == "none" and not loop.refine:
            logger.warning("loop.coarse_method none without loop.refine: a loop is accepted only "
                           "where its two keyframes align at the identity")

    @property
    def found(self) -> int:
        """Distinct candidate pairs offered for verification."""
        return self.book.found

    def query(self, agent: str, kf: int, descriptor: np.ndarray, group_id: str) -> None:
        """Queue the new keyframe's candidates (pairs already verified are skipped) and add
        it to the database."""
        try:
            candidates = list(self.database.query(agent, kf, descriptor))
            self.database.add(agent, kf, descriptor, group_id)
        except Exception:  # noqa: BLE001
            logger.exception("loop database failed on keyframe %s/%d", agent, kf)
            return
        fresh = [c for c in candidates[: self.loop_cfg.max_candidates]
                 if not (c.agent_a == c.agent_b and c.kf_a == c.kf_b)]
        if self.loop_cfg.spacing > 1:
            waiting = [*self.pending(), *(c for _, c in self.retry)]
            kept: list[Candidate] = []
            for c in fresh:
                if self._covered(c, waiting + kept):
                    self.skipped += 1
                else:
                    kept.append(c)
            fresh = kept
        self.queue += self.book.select(fresh)

    def _covered(self, cand: Candidate, waiting: list[Candidate]) -> bool:
        """Whether a pair of the same two agents, accepted (and not found an outlier) or
        waiting for verification, has a keyframe fewer than ``loop.spacing`` keyframes from
        `cand`'s keyframe of the same agent: the graph already ties that stretch of one
        agent's track to the other's, and the pair would cost up to two image pulls. A fine
        candidate is covered only by a fine pair, so a coarse edge never holds back a merge."""
        spacing = self.loop_cfg.spacing
        agents = _agents(cand)
        near = [*(lp for lp in self._accepted.get(agents, ()) if not lp.outlier),
                *(c for c in waiting if _agents(c) == agents)]
        mine = {(cand.agent_a, int(cand.kf_a)), (cand.agent_b, int(cand.kf_b))}
        for other in near:
            if cand.kind == "fine" and other.kind != "fine":
                continue
            for agent, kf in ((other.agent_a, int(other.kf_a)), (other.agent_b, int(other.kf_b))):
                if any(agent == a and abs(kf - k) < spacing for a, k in mine):
                    return True
        return False

    def _index(self, record: LoopRecord) -> None:
        if record.accepted:
            self._accepted.setdefault(_agents(record), []).append(record)

    def regroup(self, agent: str, group_id: str) -> None:
        """The agent's keyframes now belong to `group_id` (a database may not care)."""
        if hasattr(self.database, "regroup"):
            self.database.regroup(agent, group_id)

    def release_due(self) -> None:
        """Queue the retries whose time has come."""
        now = self.now()
        due = [c for t, c in self.retry if t <= now]
        self.retry = [(t, c) for t, c in self.retry if t > now]
        self.queue += self.book.select(due)

    def last_chance(self) -> None:
        """Every retry is due now (finalisation does not wait ``retry_after_s``)."""
        self.retry = [(-np.inf, c) for _, c in self.retry]

    def verify(self, cand: Candidate) -> LoopRecord | None:
        """Pull both images, register, refine, judge; the record (also in `records`), or None
        when an image was unavailable and the pair will be tried again."""
        return self.conclude(self.assess(cand, self.refiner(cand, eager=False)))

    # ------------------------------------------------------- verification off the caller

    def start_worker(self) -> None:
        """Verify on a background thread from now on (`feed`, `collect`); see `worker`."""
        from cpslam.server.loops.worker import VerifyWorker

        if self.worker is None:
            self.worker = VerifyWorker(self)

    def feed(self) -> None:
        """Hand the first queued candidate to the worker when it is idle."""
        if self.worker is not None and self.queue and self.worker.idle:
            self.worker.submit(self.queue.pop(0))

    def collect(self, wait: bool = False) -> list[LoopRecord]:
        """Records of the worker's finished verifications (`wait`: the one it is on too)."""
        if self.worker is None:
            return []
        done = self.worker.drain() if wait else self.worker.finished()
        return [r for r in map(self.conclude, done) if r is not None]

    def stop_worker(self) -> None:
        """Finish (and record) the candidate in hand, stop the thread, verify inline from
        now on."""
        if self.worker is None:
            return
        self.collect(wait=True)
        self.worker.close()
        self.worker = None

    def pending(self) -> list[Candidate]:
        """Candidates waiting: queued, then with the worker."""
        return [*self.queue, *(self.worker.in_flight() if self.worker is not None else [])]

    def refiner(self, cand: Candidate, eager: bool) -> Callable[..., Any] | None:
        """``(T_a_b, image_a, image_b) -> Registration | None`` refining `cand`'s coarse pose,
        or None without refinement. `eager`: what it reads of the back end's state is read
        now (a refiner with ``bind``), so a worker thread can run it while the state moves."""
        refine = self.refine_pose
        if refine is None:
            return None
        if eager and hasattr(refine, "bind"):
            return refine.bind(cand)
        return lambda T_a_b, img_a, img_b: refine(cand, T_a_b, img_a, img_b)

    def assess(self, cand: Candidate, refine: Callable[..., Any] | None) -> Assessment:
        """Pull both images, register, refine, judge; touches no state but the image cache,
        so it may run on a worker thread (`conclude` records the outcome)."""
        t0 = time.perf_counter()
        img_a, img_b = self.image(cand.agent_a, cand.kf_a), self.image(cand.agent_b, cand.kf_b)
        if img_a is None or img_b is None or img_a.depth is None or img_b.depth is None:
            return Assessment(cand, None, "", True, time.perf_counter() - t0)
        reg, reason = None, ""
        try:
            reg = self.register(img_b, img_a)
            if refine is None:
                if not self._warned_refine:
                    logger.info("no rendering-based refinement: coarse loop poses are used")
                    self._warned_refine = True
            elif reg.success or self.loop_cfg.coarse_method == "none":
                # Without a coarse stage the refinement starts at the identity, which
                # rarely verifies by itself: refine every pair.
                refined = refine(reg.T_dst_src, img_a, img_b)
                reg = refined if refined is not None else reg
            reason = judge(reg, self.loop_cfg)
        except Exception as exc:  # noqa: BLE001 - a failing registration rejects the pair
            logger.exception("registration of %s failed", _pair(cand))
            reason = f"registration error: {exc}"
        return Assessment(cand, reg, reason, False, time.perf_counter() - t0)

    def conclude(self, done: Assessment) -> LoopRecord | None:
        """Record an `assess` outcome: the record (also in `records`), or None when an image
        was unavailable and the pair will be tried again."""
        cand, reg, reason = done.cand, done.reg, done.reason
        if done.unavailable:
            # Says nothing about the pair (agent busy or gone): try again later, a few times.
            self.book.record(cand, accepted=False, retry=True)
            tries = self.book.attempts(cand)
            if self.book.status(cand) == "failed":
                with self._images_lock:
                    for key in ((cand.agent_a, int(cand.kf_a)), (cand.agent_b, int(cand.kf_b))):
                        if key in self._images and self._images[key] is None:
                            del self._images[key]  # fetch it again at the next try (0 bytes)
                self.retry.append((self.now() + self.retry_after_s, cand))
                logger.info("loop %s/%d - %s/%d: keyframe image unavailable (try %d of %d), "
                            "retried in %.0f s", cand.agent_a, cand.kf_a, cand.agent_b,
                            cand.kf_b, tries, self.book.max_attempts, self.retry_after_s)
                return None
            reason = f"keyframe image unavailable ({tries} tries)"
        record = loop_record(len(self.records), cand, reg, reason, self.now() - self.t_start,
                             done.seconds, self.loop_cfg.information_scale)
        self.records.append(record)
        self._index(record)
        if not done.unavailable:  # (an unavailable pair's last try was recorded above)
            self.book.record(cand, accepted=record.accepted)
        logger.info("loop %s/%d - %s/%d (%s, %.3f): %s", cand.agent_a, cand.kf_a, cand.agent_b,
                    cand.kf_b, cand.kind, cand.score, "accepted" if not reason else reason)
        return record

    def image(self, agent: str, kf: int) -> KeyframeImage | None:
        """The keyframe's image, pulled once (None when it could not be). Thread-safe: the
        pull itself runs outside the cache's lock."""
        key = (agent, int(kf))
        with self._images_lock:
            if key in self._images:
                return self._images[key]
        try:
            image = self.fetch_image(agent, int(kf))
        except Exception:  # noqa: BLE001 - an unreachable agent is a missing image
            logger.exception("fetching keyframe image %s/%d failed", agent, kf)
            image = None
        with self._images_lock:
            if key in self._images:  # pulled by the other thread meanwhile
                return self._images[key]
            self._images[key] = image
            self._image_bytes += _image_nbytes(image)
            budget = self.image_cache_bytes
            # The newest stays even alone over the budget: the caller is about to use it.
            while len(self._images) > 1 and (len(self._images) > 64 or (
                    budget is not None and self._image_bytes > budget)):
                self._image_bytes -= _image_nbytes(self._images.popitem(last=False)[1])
        return image

    def cached(self, agent: str, kf: int) -> bool:
        """Whether the keyframe's image is in the cache (`image` pulls nothing for it)."""
        with self._images_lock:
            return self._images.get((agent, int(kf))) is not None

    def status(self) -> dict:
        """The loop counts of the status summary and, as ``recent``, the last RECENT_LOOPS
        verified pairs (what a live view draws as loop edges)."""
        recent = [{"loop_id": lp.loop_id, "agent_a": lp.agent_a, "kf_a": lp.kf_a,
                   "agent_b": lp.agent_b, "kf_b": lp.kf_b, "score": float(lp.score),
                   "kind": lp.kind, "accepted": bool(lp.accepted)}
                  for lp in self.records[-RECENT_LOOPS:]]
        return {"found": self.found, "skipped": self.skipped,
                "accepted": sum(lp.accepted for lp in self.records),
                "rejected": sum(not lp.accepted for lp in self.records),
                "pending": len(self.pending()), "retrying": len(self.retry), "recent": recent}

    def state_dict(self) -> dict:
        """The back end state's ``loops``, ``loop_book`` and ``queued`` entries."""
        return {
            "loops": [asdict(lp) for lp in self.records],
            "loop_book": self.book.state_dict(),
            "loops_skipped": self.skipped,
            # Queued and retrying candidates are verified after a reload (the book keeps no
            # pending pairs, and the queries that found them do not run again).
            "queued": [[c.agent_a, int(c.kf_a), c.agent_b, int(c.kf_b), float(c.score),
                        str(c.kind)] for c in [*self.pending(), *(c for _, c in self.retry)]],
        }

    def load_state_dict(self, state: dict) -> None:
        """Restore from a back end state (its ``loops``, ``loop_book``, ``queued``)."""
        self.records = [LoopRecord(**lp) for lp in state["loops"]]
        self._accepted = {}
        for lp in self.records:
            self._index(lp)
        self.book = LoopBook(max_attempts=self.book.max_attempts)
        if "loop_book" in state:
            self.book.load_state_dict(state["loop_book"])
        else:  # saved before the back end kept a LoopBook: the loop records hold the verdicts
            for lp in self.records:
                if self.book.select([lp]):
                    self.book.record(lp, accepted=lp.accepted)
        self.skipped = int(state.get("loops_skipped", 0))
        self.retry = []
        self.queue = self.book.select([
            LoopCandidate(str(a), int(ka), str(b), int(kb), float(score), kind)
            for a, ka, b, kb, score, kind in state.get("queued", [])])


def _agents(c: Any) -> tuple[str, str]:
    """The two agents of a candidate or record, in a canonical order."""
    return (c.agent_a, c.agent_b) if c.agent_a <= c.agent_b else (c.agent_b, c.agent_a)


def _pair(c: Candidate) -> tuple[str, int, str, int]:
    a, b = (c.agent_a, int(c.kf_a)), (c.agent_b, int(c.kf_b))
    return (*min(a, b), *max(a, b))


def _image_nbytes(image: KeyframeImage | None) -> int:
    """Bytes of a cached image's decoded pixels (0 for a miss)."""
    if image is None:
        return 0
    return sum(a.nbytes for a in (image.rgb, image.depth) if a is not None)

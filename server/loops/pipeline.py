"""The back end's loop pipeline: candidates from the descriptor database, each pair verified
once, the verdicts as `LoopRecord`s.

Per new keyframe: descriptor query -> candidates (fine/coarse) -> `LoopBook` (each pair
verified once; one whose images could not be pulled is tried again ``retry_after_s`` later, up
to ``loop.max_attempts`` tries) -> both images pulled (cached) -> coarse registration
(RANSAC + ICP, or the identity with ``loop.coarse_method: none``, the paper) -> optional
rendering-based refinement (``refine_pose``) -> accept/reject by overlap and residual. What
an accepted loop then does (merge, pose graph) is the back end's business (`backend`).
"""

from __future__ import annotations

import logging
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from cpslam.common.camera import Intrinsics
from cpslam.server.loops.candidates import LoopBook, LoopCandidate

if TYPE_CHECKING:
    from cpslam.common.config.collab import LoopConfig
    from cpslam.protocol import KeyframeImage

__all__ = ["Candidate", "LoopDatabase", "LoopRecord", "LoopVerifier"]

logger = logging.getLogger(__name__)


class Candidate(Protocol):
    """What the loop database returns (`cpslam.server.loops.LoopCandidate`)."""

    agent_a: str
    kf_a: int
    agent_b: str
    kf_b: int
    score: float
    kind: str


class LoopDatabase(Protocol):
    def add(self, agent_id: str, kf_id: int, descriptor: np.ndarray, group: str) -> Any: ...
    def query(self, agent_id: str, kf_id: int, descriptor: np.ndarray) -> list[Candidate]: ...


@dataclass
class LoopRecord:
    """One verified candidate, accepted or rejected."""

    loop_id: int
    agent_a: str
    kf_a: int
    agent_b: str
    kf_b: int
    score: float
    kind: str
    accepted: bool
    reason: str
    T_a_b: list | None
    fitness: float
    rmse: float
    stamp: float
    seconds: float
    merged: bool = False
    outlier: bool = False
    method: str = ""  # how T_a_b was found: "ransac+icp", "render" (refined), "coarse" (kept)
    refinement: dict | None = None  # what `PoseRefiner` did (JSON-able)
    # Information [6, 6] of T_a_b (right perturbation, translation first): the registration's
    # times loop.information_scale; None when the registration gave none (sigmas from
    # overlap and residual then).
    information: list | None = None


class LoopVerifier:
    """Loop candidates queued, verified and recorded (see the module docstring).

    Args:
        loop: the config section (candidates per query, thresholds, coarse method, tries).
        fetch_image: ``(agent_id, kf_id) -> KeyframeImage | None``; images are cached (64).
        now: monotonic clock (s); t_start: its value that record stamps count from.
        refine_pose: optional ``(candidate, T_a_b_init, image_a, image_b) -> Registration |
            None`` refining a coarse loop pose (a `PoseRefiner`); None uses the coarse one.
        database: loop database (default: `cpslam.server.loops.DescriptorDatabase`).
        register: ``(src_image_b, dst_image_a) -> Registration``, the coarse stage (default:
            `register_rgbd`, or with ``loop.coarse_method`` "none" the identity, verified).
        seed: of the registration's RANSAC.
        retry_after_s: a candidate whose keyframe images could not be pulled is tried again
            this many seconds later (``loop.max_attempts`` tries in all).
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
    ) -> None:
        self.loop_cfg, self.fetch_image = loop, fetch_image
        self.now, self.t_start = now, t_start
        self.refine_pose = refine_pose
        self.database = database if database is not None else _default_database(loop)
        self.register = register or _default_register(loop, seed)
        self.retry_after_s = retry_after_s
        self.book = LoopBook(max_attempts=loop.max_attempts)
        self.records: list[LoopRecord] = []
        self.queue: list[Candidate] = []  # selected by the book, waiting for verification
        self.retry: list[tuple[float, Candidate]] = []  # (due time, candidate)
        self._images: OrderedDict[tuple[str, int], KeyframeImage | None] = OrderedDict()
        self._warned_refine = False
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
        self.queue += self.book.select(fresh)

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
        t0 = time.perf_counter()
        img_a, img_b = self.image(cand.agent_a, cand.kf_a), self.image(cand.agent_b, cand.kf_b)
        reg, reason = None, ""
        unavailable = img_a is None or img_b is None or img_a.depth is None or img_b.depth is None
        if unavailable:
            # Says nothing about the pair (agent busy or gone): try again later, a few times.
            self.book.record(cand, accepted=False, retry=True)
            tries = self.book.attempts(cand)
            if self.book.status(cand) == "failed":
                for key in ((cand.agent_a, int(cand.kf_a)), (cand.agent_b, int(cand.kf_b))):
                    if key in self._images and self._images[key] is None:
                        del self._images[key]  # fetch it again at the next try
                self.retry.append((self.now() + self.retry_after_s, cand))
                logger.info("loop %s/%d - %s/%d: keyframe image unavailable (try %d of %d), "
                            "retried in %.0f s", cand.agent_a, cand.kf_a, cand.agent_b,
                            cand.kf_b, tries, self.book.max_attempts, self.retry_after_s)
                return None
            reason = f"keyframe image unavailable ({tries} tries)"
        else:
            try:
                reg = self.register(img_b, img_a)
                if self.refine_pose is None:
                    if not self._warned_refine:
                        logger.info("no rendering-based refinement: coarse loop poses are used")
                        self._warned_refine = True
                elif reg.success or self.loop_cfg.coarse_method == "none":
                    # Without a coarse stage the refinement starts at the identity, which
                    # rarely verifies by itself: refine every pair.
                    refined = self.refine_pose(cand, reg.T_dst_src, img_a, img_b)
                    reg = refined if refined is not None else reg
                reason = _judge(reg, self.loop_cfg)
            except Exception as exc:  # noqa: BLE001 - a failing registration rejects the pair
                logger.exception("registration of %s failed", _pair(cand))
                reason = f"registration error: {exc}"
        record = LoopRecord(
            loop_id=len(self.records), agent_a=cand.agent_a, kf_a=int(cand.kf_a),
            agent_b=cand.agent_b, kf_b=int(cand.kf_b), score=float(cand.score),
            kind=str(cand.kind), accepted=not reason, reason=reason,
            T_a_b=None if reg is None else np.asarray(reg.T_dst_src, np.float64).tolist(),
            fitness=float(reg.fitness) if reg is not None else 0.0,
            rmse=float(reg.inlier_rmse) if reg is not None and np.isfinite(reg.inlier_rmse)
            else -1.0,
            stamp=self.now() - self.t_start, seconds=time.perf_counter() - t0,
            method=getattr(reg, "method", ""),
            refinement=(getattr(reg, "details", None) or {}).get("refinement"),
            information=_information(reg, self.loop_cfg.information_scale),
        )
        self.records.append(record)
        if not unavailable:  # (an unavailable pair's last try was recorded above)
            self.book.record(cand, accepted=record.accepted)
        logger.info("loop %s/%d - %s/%d (%s, %.3f): %s", cand.agent_a, cand.kf_a, cand.agent_b,
                    cand.kf_b, cand.kind, cand.score, "accepted" if not reason else reason)
        return record

    def image(self, agent: str, kf: int) -> KeyframeImage | None:
        """The keyframe's image, pulled once (None when it could not be)."""
        key = (agent, int(kf))
        if key not in self._images:
            try:
                self._images[key] = self.fetch_image(agent, int(kf))
            except Exception:  # noqa: BLE001 - an unreachable agent is a missing image
                logger.exception("fetching keyframe image %s/%d failed", agent, kf)
                self._images[key] = None
            while len(self._images) > 64:
                self._images.popitem(last=False)
        return self._images[key]

    def status(self) -> dict:
        """The loop counts of the status summary."""
        return {"found": self.found,
                "accepted": sum(lp.accepted for lp in self.records),
                "rejected": sum(not lp.accepted for lp in self.records),
                "pending": len(self.queue), "retrying": len(self.retry)}

    def state_dict(self) -> dict:
        """The back end state's ``loops``, ``loop_book`` and ``queued`` entries."""
        return {
            "loops": [asdict(lp) for lp in self.records],
            "loop_book": self.book.state_dict(),
            # Queued and retrying candidates are verified after a reload (the book keeps no
            # pending pairs, and the queries that found them do not run again).
            "queued": [[c.agent_a, int(c.kf_a), c.agent_b, int(c.kf_b), float(c.score),
                        str(c.kind)] for c in [*self.queue, *(c for _, c in self.retry)]],
        }

    def load_state_dict(self, state: dict) -> None:
        """Restore from a back end state (its ``loops``, ``loop_book``, ``queued``)."""
        self.records = [LoopRecord(**lp) for lp in state["loops"]]
        self.book = LoopBook(max_attempts=self.book.max_attempts)
        if "loop_book" in state:
            self.book.load_state_dict(state["loop_book"])
        else:  # saved before the back end kept a LoopBook: the loop records hold the verdicts
            for lp in self.records:
                if self.book.select([lp]):
                    self.book.record(lp, accepted=lp.accepted)
        self.retry = []
        self.queue = self.book.select([
            LoopCandidate(str(a), int(ka), str(b), int(kb), float(score), kind)
            for a, ka, b, kb, score, kind in state.get("queued", [])])


def _pair(c: Candidate) -> tuple[str, int, str, int]:
    a, b = (c.agent_a, int(c.kf_a)), (c.agent_b, int(c.kf_b))
    return (*min(a, b), *max(a, b))


def _information(reg: Any, scale: float) -> list | None:
    """The registration's information matrix times `scale`, when it is positive definite."""
    info = getattr(reg, "information", None)
    if info is None or not getattr(reg, "success", False):
        return None
    info = scale * np.asarray(info, dtype=np.float64)
    info = 0.5 * (info + info.T)
    if not np.all(np.isfinite(info)) or np.linalg.eigvalsh(info).min() <= 0:
        return None
    return info.tolist()


def _judge(reg: Any, cfg: LoopConfig) -> str:
    """Empty when the registration passes the thresholds, else why not."""
    if not reg.success:
        return reg.reason or "registration failed"
    if not reg.inlier_rmse <= cfg.verify_max_residual:
        return f"residual {reg.inlier_rmse:.4f} m > {cfg.verify_max_residual}"
    if not reg.fitness >= cfg.verify_min_overlap:
        return f"overlap {reg.fitness:.3f} < {cfg.verify_min_overlap}"
    return ""


def _default_database(loop: LoopConfig) -> LoopDatabase:
    from cpslam.server.loops.candidates import DescriptorDatabase

    return DescriptorDatabase.from_config(loop)


def _default_register(loop: LoopConfig, seed: int) -> Callable[[KeyframeImage, KeyframeImage],
                                                                Any]:
    def register(src: KeyframeImage, dst: KeyframeImage) -> Any:
        from cpslam.common.registration import RegistrationParams, register_rgbd, verify

        params = RegistrationParams.from_config(loop, seed)
        if loop.coarse_method == "none":
            # The paper: no coarse stage, the loop keyframe starts at the other keyframe's
            # pose (identity relative pose) and only the rendering refinement moves it.
            result = verify(_rgbd(src), _rgbd(dst), _intrinsics(src), np.eye(4), params,
                            dst_intrinsics=_intrinsics(dst))
            result.method = "identity"
            return result
        return register_rgbd(_rgbd(src), _rgbd(dst), _intrinsics(src), params,
                             dst_intrinsics=_intrinsics(dst))

    return register


def _rgbd(img: KeyframeImage) -> tuple[np.ndarray, np.ndarray]:
    depth = img.depth_metres()
    rgb = img.rgb if img.rgb is not None else np.zeros((*depth.shape, 3), np.uint8)
    return rgb, depth


def _intrinsics(img: KeyframeImage) -> Intrinsics:
    return Intrinsics(img.fx, img.fy, img.cx, img.cy, img.width, img.height)

"""The server back end: agents' messages in, loops, merges, rounds and corrections out.

No transport and no threads: the daemon calls `handle` for every decoded agent message, `step`
regularly (it runs the pending work), `agent_left` when an agent's liveliness goes, `status`
for the status query and `finalise` at the end; each returns the messages to send
(`Outgoing`). Time comes from the injected ``now`` and keyframe images from ``fetch_image``
(the server pulls images only for loop candidates and fine-tuning), so tests drive it fully.

Loop pipeline per new keyframe: descriptor query -> candidates (fine/coarse) -> `LoopBook`
(each pair verified once; one whose images could not be pulled is tried again later, up to
``loop.max_attempts`` tries) -> both images pulled -> coarse registration (RANSAC + ICP, or
the identity with ``loop.coarse_method: none``, the paper) -> optional rendering-based
refinement (``refine_pose``) -> accept/reject by overlap and residual -> a fine loop between
two groups merges them (align, fuse, average and fine-tune the decoders) -> pose graph of the
group -> `ServerUpdate` to every member (alignment, corrected keyframe poses, other members'
points) and, after a merge, a `GroupDecoder`. See docs/server.md.
"""

from __future__ import annotations

import logging
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
import torch

from cpslam.common.camera import Intrinsics
from cpslam.common.geometry import compose, invert
from cpslam.protocol import GroupDecoder, KeyframeImage, Message, ServerUpdate
from cpslam.server.federation import FederatedRound, fedavg
from cpslam.server.fusion import ForeignTracker, MemberMap, View, finetune_decoders, fuse
from cpslam.server.groups import Group, Groups
from cpslam.server.loops import LoopBook, LoopCandidate
from cpslam.server.pose_graph import PoseGraph, loop_sigmas
from cpslam.server.registry import Registry
from cpslam.server.result import FinalResult, finalise_backend
from cpslam.server.tracks import agent_trajectory, group_kf_poses

if TYPE_CHECKING:
    from cpslam.common.config import CpslamConfig
    from cpslam.common.config.collab import (
        FederationConfig,
        LoopConfig,
        PoseGraphConfig,
        RefinementConfig,
    )
    from cpslam.common.field import Decoders

__all__ = ["Backend", "LoopRecord", "Outgoing"]

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class Outgoing:
    """A message to publish: to one agent (``scope`` "agent") or to a group's decoder key."""

    target: str
    message: Message
    scope: str = "agent"


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


class Backend:
    """The collaborative back end (see the module docstring).

    Args:
        loop, federation, pose_graph, refinement: the config sections.
        feature_dim, cell_size, k, radius: the neural field's point width, grid cell (m),
            neighbours and radius (m).
        fetch_image: ``(agent_id, kf_id) -> KeyframeImage | None`` (a Zenoh get in the daemon).
        now: monotonic clock (s).
        refine_pose: optional ``(candidate, T_a_b_init, image_a, image_b) -> Registration |
            None`` refining a coarse loop pose (`from_config`: a `PoseRefiner` unless
            ``loop.refine`` is false); None uses the coarse estimate.
        database: loop database (default: `cpslam.server.loops.DescriptorDatabase`).
        register: ``(src_image_b, dst_image_a) -> Registration``, the coarse stage (default:
            `register_rgbd`, or with ``loop.coarse_method`` "none" the identity, verified).
        decoders_factory: builds fresh `Decoders` to load averaged weights into for
            fine-tuning; None skips fine-tuning.
        sampler: ray sampler of the fine-tunes (default: the paper's).
        finetune_lr, finetune_lr_features: Adam learning rates of decoders / point features.
        finetune_views: most keyframe images pulled for one fine-tune.
        share_every_s: how often merged groups get the other members' new points.
        seed: seed of every fine-tune.
        verify_budget_s: a step stops verifying candidates after this many (wall-clock)
            seconds and leaves the rest for the next step, so a daemon stays responsive (acks,
            updates) while a backlog is worked off. None (lock-step runs): no limit, so the
            work done per step does not depend on the machine's speed.
        retry_after_s: a candidate whose keyframe images could not be pulled is tried again
            this many seconds later (``loop.max_attempts`` tries in all).
    """

    def __init__(
        self,
        loop: LoopConfig,
        federation: FederationConfig,
        pose_graph: PoseGraphConfig,
        refinement: RefinementConfig,
        fetch_image: Callable[[str, int], KeyframeImage | None],
        feature_dim: int = 32,
        cell_size: float = 0.14,
        k: int = 8,
        radius: float = 0.15,
        now: Callable[[], float] = time.monotonic,
        refine_pose: Callable[..., Any] | None = None,
        database: LoopDatabase | None = None,
        register: Callable[[KeyframeImage, KeyframeImage], Any] | None = None,
        decoders_factory: Callable[[], Decoders] | None = None,
        sampler: Any = None,
        finetune_lr: float = 0.003,
        finetune_lr_features: float = 0.005,
        finetune_views: int = 8,
        share_every_s: float = 10.0,
        seed: int = 0,
        verify_budget_s: float | None = None,
        retry_after_s: float = 5.0,
    ) -> None:
        self.verify_budget_s, self.retry_after_s = verify_budget_s, retry_after_s
        self.loop_cfg, self.fed_cfg = loop, federation
        self.pg_cfg, self.refine_cfg = pose_graph, refinement
        self.fetch_image, self.now = fetch_image, now
        self.feature_dim, self.cell_size, self.k, self.radius = feature_dim, cell_size, k, radius
        self.refine_pose = refine_pose
        self.database = database if database is not None else _default_database(loop)
        self.register = register or _default_register(loop, seed)
        self.decoders_factory = decoders_factory
        self.sampler = sampler
        self.finetune_lr, self.finetune_lr_features = finetune_lr, finetune_lr_features
        self.finetune_views, self.share_every_s, self.seed = finetune_views, share_every_s, seed
        shapes = None
        if decoders_factory is not None:
            shapes = {n: tuple(t.shape) for n, t in decoders_factory().state_dict().items()}
        self.registry = Registry(feature_dim, shapes)
        self.groups = Groups()
        self.foreign = ForeignTracker()
        self.loops: list[LoopRecord] = []
        self.corrected: dict[tuple[str, int], np.ndarray] = {}
        self.rounds: dict[str, FederatedRound] = {}
        self.rounds_closed: list[dict] = []
        self.merges: list[dict] = []
        self.pose_graph_runs: list[dict] = []
        self.update_seq: dict[str, int] = {}
        self.book = LoopBook(max_attempts=loop.max_attempts)
        self._candidates: list[Candidate] = []
        self._retry: list[tuple[float, Candidate]] = []  # (due time, candidate)
        self._images: OrderedDict[tuple[str, int], KeyframeImage | None] = OrderedDict()
        self._last_share: dict[str, tuple[float, tuple]] = {}
        self._warned_refine = False
        self.t_start = now()
        if loop.coarse_method == "none" and not loop.refine:
            logger.warning("loop.coarse_method none without loop.refine: a loop is accepted only "
                           "where its two keyframes align at the identity")

    @classmethod
    def from_config(cls, cfg: CpslamConfig, fetch_image: Callable[[str, int], KeyframeImage |
                    None], **kwargs: Any) -> Backend:
        """A back end with the settings of a whole config (``kwargs`` override/add)."""
        from cpslam.common.field_config import decoders_from_config, sampler_from_config

        f = cfg.field
        args: dict[str, Any] = {
            "feature_dim": f.feature_dim, "cell_size": f.grid_size, "k": f.k_neighbors,
            "radius": f.radius, "seed": cfg.run.seed,
            "decoders_factory": lambda: decoders_from_config(f, cfg.run.seed),
            "sampler": sampler_from_config(f),
            "finetune_lr": cfg.mapping.lr_decoders,
            "finetune_lr_features": cfg.mapping.lr_features,
        }
        args.update(kwargs)
        backend = cls(cfg.loop, cfg.federation, cfg.pose_graph, cfg.refinement, fetch_image, **args)
        if cfg.loop.refine and "refine_pose" not in kwargs:  # the paper's rendering refinement
            from cpslam.server.refine import PoseRefiner
            backend.refine_pose = PoseRefiner.from_config(cfg, backend.registry)
        return backend

    # ------------------------------------------------------------------------------ input

    def handle(self, msg: Message, nbytes: int = 0) -> list[Outgoing]:
        """Take one agent message (cheap; the work happens in `step`). Returns its `Ack`."""
        try:
            acks = self.registry.handle(msg, nbytes)
        except Exception:  # noqa: BLE001 - a bad message must never stop the server
            logger.exception("internal error handling %s", type(msg).__name__)
            self.registry.dropped["internal error"] += 1
            return []
        agent = getattr(msg, "agent_id", None)
        if agent in self.registry.agents:
            self.groups.add_agent(agent)
        return [Outgoing(a.agent_id, a) for a in acks]

    def agent_left(self, agent_id: str) -> None:
        """The agent vanished: no round waits for it any more; its data stays."""
        if agent_id in self.registry.agents:
            self.registry.agents[agent_id].alive = False
        for rnd in self.rounds.values():
            rnd.drop(agent_id)
        # No log line: the caller (the node watching liveliness) reports the leave once.

    # ------------------------------------------------------------------------------- work

    def step(self) -> list[Outgoing]:
        """Run the pending work: loop queries and verification, merges, pose graphs,
        federated rounds, point sharing. Returns the messages to send."""
        out: list[Outgoing] = []
        for agent, kf in self.registry.take_new_keyframes():
            self._query(agent, kf)
        now = self.now()
        due = [c for t, c in self._retry if t <= now]
        self._retry = [(t, c) for t, c in self._retry if t > now]
        self._candidates += self.book.select(due)
        dirty: dict[str, bool] = {}
        # Pairs that can merge two groups go first: a merge changes what every agent does.
        self._candidates.sort(key=lambda c: (self.groups.same_group(c.agent_a, c.agent_b)
                                             or c.kind != "fine"))
        t0 = time.perf_counter()
        while self._candidates:
            if (self.verify_budget_s is not None
                    and time.perf_counter() - t0 > self.verify_budget_s):
                break
            cand = self._candidates.pop(0)
            record = self._verify(cand)
            if record is None or not record.accepted:
                continue
            if not self.groups.same_group(cand.agent_a, cand.agent_b):
                if cand.kind != "fine":
                    continue  # a coarse pair only becomes an edge once its groups merge
                out += self._merge(record)
                record.merged = True
                dirty[self.groups.group_of(cand.agent_a).group_id] = True
                break  # publish the merge now; the remaining candidates wait for next step
            dirty[self.groups.group_of(cand.agent_a).group_id] = True
        for gid in dirty:
            if gid in self.groups.groups:
                self._optimise(self.groups.groups[gid])
                out += self._updates(self.groups.groups[gid])
        for agent, msg in self.registry.take_new_decoders():
            self._submit(agent, msg)
        out += self._close_rounds()
        out += self._share()
        return out

    def _query(self, agent: str, kf: int) -> None:
        descriptor = self.registry.agents[agent].keyframes[kf].descriptor
        try:
            candidates = list(self.database.query(agent, kf, descriptor))
            self.database.add(agent, kf, descriptor, self.groups.group_of(agent).group_id)
        except Exception:  # noqa: BLE001
            logger.exception("loop database failed on keyframe %s/%d", agent, kf)
            return
        fresh = [c for c in candidates[: self.loop_cfg.max_candidates]
                 if not (c.agent_a == c.agent_b and c.kf_a == c.kf_b)]
        self._candidates += self.book.select(fresh)  # pairs already verified are skipped

    @property
    def loops_found(self) -> int:
        """Distinct candidate pairs offered for verification."""
        return self.book.found

    def _verify(self, cand: Candidate) -> LoopRecord | None:
        t0 = time.perf_counter()
        img_a, img_b = self._image(cand.agent_a, cand.kf_a), self._image(cand.agent_b, cand.kf_b)
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
                self._retry.append((self.now() + self.retry_after_s, cand))
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
            loop_id=len(self.loops), agent_a=cand.agent_a, kf_a=int(cand.kf_a),
            agent_b=cand.agent_b, kf_b=int(cand.kf_b), score=float(cand.score),
            kind=str(cand.kind), accepted=not reason, reason=reason,
            T_a_b=None if reg is None else np.asarray(reg.T_dst_src, np.float64).tolist(),
            fitness=float(reg.fitness) if reg is not None else 0.0,
            rmse=float(reg.inlier_rmse) if reg is not None and np.isfinite(reg.inlier_rmse)
            else -1.0,
            stamp=self.now() - self.t_start, seconds=time.perf_counter() - t0,
            method=getattr(reg, "method", ""),
            refinement=(getattr(reg, "details", None) or {}).get("refinement"),
        )
        self.loops.append(record)
        if not unavailable:  # (an unavailable pair's last try was recorded above)
            self.book.record(cand, accepted=record.accepted)
        logger.info("loop %s/%d - %s/%d (%s, %.3f): %s", cand.agent_a, cand.kf_a, cand.agent_b,
                    cand.kf_b, cand.kind, cand.score, "accepted" if not reason else reason)
        return record

    def _image(self, agent: str, kf: int) -> KeyframeImage | None:
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

    # ----------------------------------------------------------------------------- groups

    def kf_poses(self, agent: str) -> dict[int, np.ndarray]:
        """Best current keyframe poses of an agent in its group's frame."""
        group = self.groups.group_of(agent)
        corrected = {k: T for (a, k), T in self.corrected.items() if a == agent}
        return group_kf_poses(self.registry.agents[agent], group.T_group_agent[agent], corrected)

    def member_maps(self, group: Group) -> list[MemberMap]:
        """Each member's sub-map with keyframes at their group-frame poses."""
        out = []
        for m in group.members:
            rec = self.registry.agents[m]
            pm = rec.points.to_point_map(rec.index, self.kf_poses(m), self.feature_dim,
                                         self.cell_size)
            out.append(MemberMap(m, rec.index, pm))
        return out

    def _merge(self, loop: LoopRecord) -> list[Outgoing]:
        a, b = loop.agent_a, loop.agent_b
        ga, gb = self.groups.group_of(a), self.groups.group_of(b)
        # Keep the older group (anchor joined first) so frames change as little as possible.
        if self.registry.agents[gb.anchor].index < self.registry.agents[ga.anchor].index:
            ga, gb = gb, ga
        survivor = a if ga.group_id == self.groups.group_of(a).group_id else b
        other = b if survivor == a else a
        T_s_o = np.asarray(loop.T_a_b) if survivor == a else invert(np.asarray(loop.T_a_b))
        kf_s = loop.kf_a if survivor == a else loop.kf_b
        kf_o = loop.kf_b if survivor == a else loop.kf_a
        T_ga_gb = compose(self.kf_poses(survivor)[kf_s], T_s_o, invert(self.kf_poses(other)[kf_o]))
        old = {m: gb.T_group_agent[m] for m in gb.members}
        T_world = compose(invert(ga.T_group_agent[survivor]), T_ga_gb,
                          gb.T_group_agent[other])
        for rnd in (self.rounds.pop(ga.group_id, None), self.rounds.pop(gb.group_id, None)):
            if rnd is not None:
                logger.info("round %s#%d abandoned by a merge", rnd.group_id, rnd.round)
        group = self.groups.merge(survivor, other, T_world)
        if hasattr(self.database, "regroup"):
            for m in old:
                self.database.regroup(m, group.group_id)
        for m in old:  # corrected poses of the joining members move into the new frame
            for key in [key for key in self.corrected if key[0] == m]:
                self.corrected[key] = compose(T_ga_gb, self.corrected[key])
        self.merges.append({"time": self.now() - self.t_start, "group": group.group_id,
                            "joined": sorted(old), "members": group.members,
                            "loop_id": loop.loop_id})
        return self._merge_decoders(group)

    def _merge_decoders(self, group: Group) -> list[Outgoing]:
        recs = [self.registry.agents[m] for m in group.members]
        have = [r for r in recs if r.decoder is not None]
        if not have:
            logger.info("group %s: no decoder weights yet, nothing to average", group.group_id)
            return []
        try:
            samples = [r.decoder_samples for r in have]
            uniform = self.fed_cfg.weighting == "uniform" or not sum(samples)
            weights = [1] * len(have) if uniform else samples
            avg = fedavg([r.decoder for r in have], weights)
            avg = self._finetune(group, avg, self.fed_cfg.finetune_iters, lr_features=0.0)
        except ValueError as exc:
            logger.error("group %s: decoders cannot be averaged: %s", group.group_id, exc)
            return []
        group.decoder, group.decoder_samples = avg, int(sum(samples))
        group.round += 1
        return [self._group_decoder(group, [r.agent_id for r in have])]

    def _finetune(self, group: Group, state: dict[str, np.ndarray], iters: int,
                  lr_features: float, point_map: Any = None) -> dict[str, np.ndarray]:
        if self.decoders_factory is None or iters <= 0:
            return state
        decoders = self.decoders_factory()
        decoders.load_state_dict({k: torch.as_tensor(v) for k, v in state.items()})
        if point_map is None:
            point_map = fuse(self.member_maps(group), self.feature_dim, self.cell_size)
        views = self._views(group)
        finetune_decoders(decoders, point_map, views, iters, self.finetune_lr, self.seed,
                          self.sampler, k=self.k, radius=self.radius, lr_features=lr_features)
        return {k: v.detach().cpu().numpy().astype(np.float32)
                for k, v in decoders.state_dict().items()}

    def _views(self, group: Group) -> list[View]:
        keys = [(m, kf) for m in group.members for kf in self.registry.agents[m].kf_ids]
        if not keys:
            return []
        pick = np.unique(np.linspace(0, len(keys) - 1, min(self.finetune_views, len(keys))
                                     ).round().astype(int))
        views = []
        for i in pick:
            agent, kf = keys[i]
            img = self._image(agent, kf)
            if img is None or img.depth is None or img.rgb is None:
                continue
            intr = Intrinsics(img.fx, img.fy, img.cx, img.cy, img.width, img.height)
            views.append(View(img.rgb, img.depth_metres(), self.kf_poses(agent)[kf], intr))
        return views

    def _optimise(self, group: Group) -> None:
        t0 = time.perf_counter()
        graph = PoseGraph.from_config(self.pg_cfg)
        for m in group.members:
            traj = agent_trajectory(self.registry.agents[m])
            if traj is not None:
                graph.add_trajectory(m, traj, group.T_group_agent[m])
        loops = [lp for lp in self.loops if lp.accepted and lp.agent_a in group.T_group_agent
                 and lp.agent_b in group.T_group_agent]
        for lp in loops:
            sig_t, sig_r = loop_sigmas(self.pg_cfg.loop_sigma_t, self.pg_cfg.loop_sigma_r,
                                       max(lp.rmse, 0.0), min(max(lp.fitness, 1e-3), 1.0))
            graph.add_loop(lp.agent_a, lp.kf_a, lp.agent_b, lp.kf_b, np.asarray(lp.T_a_b),
                           sigma_t=sig_t, sigma_r=sig_r, loop_id=lp.loop_id)
        if graph.num_nodes == 0:
            return
        result = graph.optimize()
        for (agent, kf), T in result.poses.items():
            self.corrected[(agent, kf)] = T
        for lp in loops:
            lp.outlier = lp.loop_id in result.outlier_loops
        self.pose_graph_runs.append({
            "group": group.group_id, "nodes": graph.num_nodes, "loops": len(loops),
            "error_before": result.error_before, "error_after": result.error_after,
            "outliers": len(result.outlier_loops), "seconds": time.perf_counter() - t0})

    def _updates(self, group: Group) -> list[Outgoing]:
        """A `ServerUpdate` for every member of the group."""
        maps = self.member_maps(group)
        out = []
        for mm in maps:
            agent = mm.agent_id
            others = [o for o in maps if o.agent_id != agent]
            versions = {o.agent_id: self.registry.agents[o.agent_id].points.seq for o in others}
            blocks = self.foreign.blocks(mm, others, versions, self.cell_size)
            poses = self.kf_poses(agent)
            kfs = sorted(poses)
            epoch = group.agent_epoch[agent]
            self.registry.set_alignment(agent, epoch, group.T_group_agent[agent])
            self.update_seq[agent] = self.update_seq.get(agent, 0) + 1
            msg = ServerUpdate(
                agent_id=agent, seq=self.update_seq[agent], epoch=epoch,
                group_id=group.group_id, group_members=group.members,
                T_group_agent=group.T_group_agent[agent],
                kf_ids=np.asarray(kfs, np.int32),
                T_group_kf=np.stack([poses[k] for k in kfs]) if kfs else np.zeros((0, 4, 4)),
                foreign=blocks)
            out.append(Outgoing(agent, msg))
        self._last_share[group.group_id] = (self.now(), self._signature(group))
        return out

    def _signature(self, group: Group) -> tuple:
        return tuple((m, len(self.registry.agents[m].points),
                      int(self.registry.agents[m].points.seq.max(initial=-1)),
                      len(self.registry.agents[m].keyframes)) for m in group.members)

    def _share(self) -> list[Outgoing]:
        out = []
        for group in list(self.groups.groups.values()):
            if len(group.members) < 2:
                continue
            last, sig = self._last_share.get(group.group_id, (-np.inf, ()))
            if self.now() - last >= self.share_every_s and self._signature(group) != sig:
                out += self._updates(group)
        return out

    # ------------------------------------------------------------------------- federation

    def _submit(self, agent: str, msg: Any) -> None:
        group = self.groups.group_of(agent)
        if not self.fed_cfg.enabled or len(group.members) < 2:
            return
        # Before the group's first average any member's local weights count (agents may not
        # have applied the merge yet); afterwards only answers to the latest round do.
        first = group.decoder is None
        if not first and (msg.group_id != group.group_id or int(msg.round) != group.round):
            self.registry.dropped["decoder weights for a past round or group"] += 1
            logger.debug("round: %s sent weights for %s#%d, group is at %s#%d", agent,
                        msg.group_id, msg.round, group.group_id, group.round)
            return
        rnd = self.rounds.get(group.group_id)
        if rnd is None:
            alive = [m for m in group.members if self.registry.agents[m].alive]
            rnd = FederatedRound(group.group_id, group.round + 1, alive or [agent],
                                 self.now() + self.fed_cfg.round_timeout_s,
                                 self.fed_cfg.weighting)
            self.rounds[group.group_id] = rnd
            logger.info("round %s#%d opened (%s)", rnd.group_id, rnd.round, sorted(rnd.members))
        if agent in rnd.members:
            rnd.submit(agent, self.registry.agents[agent].decoder, int(msg.n_samples))

    def _close_rounds(self) -> list[Outgoing]:
        out = []
        now = self.now()
        for gid, rnd in list(self.rounds.items()):
            if rnd.expired(now):
                del self.rounds[gid]
                continue
            if not rnd.is_complete(now):
                continue
            del self.rounds[gid]
            avg, contributors = rnd.result()
            group = self.groups.groups[gid]
            if group.decoder is None:  # the group's first shared decoder: fine-tune it too
                avg = self._finetune(group, avg, self.fed_cfg.finetune_iters, lr_features=0.0)
            group.decoder, group.round = avg, rnd.round
            group.decoder_samples = int(sum(self.registry.agents[a].decoder_samples
                                            for a in contributors))
            timed_out = bool(rnd.pending)
            self.rounds_closed.append({"group": gid, "round": rnd.round, "time": now - self.t_start,
                                       "contributors": contributors, "timed_out": timed_out})
            out.append(self._group_decoder(group, contributors))
        return out

    def _group_decoder(self, group: Group, contributors: list[str]) -> Outgoing:
        msg = GroupDecoder(group_id=group.group_id, round=group.round, members=contributors,
                           n_samples=group.decoder_samples, tensors=group.decoder)
        return Outgoing(group.group_id, msg, scope="group")

    # ----------------------------------------------------------------------------- output

    def finalise(self) -> FinalResult:
        """Final pose graph over everything, refined fused maps, trajectories, metrics."""
        self._retry = [(-np.inf, c) for _, c in self._retry]  # last chance: not in 5 s
        self.step()
        self.registry.drop_unresolved()
        return finalise_backend(self)

    def status(self) -> dict:
        """JSON summary for the status query: agents, groups, loops, rounds."""
        return {
            "agents": {
                a: {"index": r.index, "alive": r.alive, "keyframes": len(r.keyframes),
                    "frames": len(r.frames), "points": len(r.points),
                    "pending": len(r.pending_points) + len(r.pending_frames),
                    "messages": r.messages, "bytes": r.bytes, "acked_seq": r.seq_floor,
                    "dropped": dict(r.dropped)}
                for a, r in self.registry.agents.items()},
            "groups": {g.group_id: {"members": g.members, "epoch": g.epoch, "round": g.round}
                       for g in self.groups.groups.values()},
            "loops": {"found": self.loops_found,
                      "accepted": sum(lp.accepted for lp in self.loops),
                      "rejected": sum(not lp.accepted for lp in self.loops),
                      "pending": len(self._candidates), "retrying": len(self._retry)},
            "rounds": {"closed": len(self.rounds_closed), "open": sorted(self.rounds)},
            "merges": len(self.merges),
            "dropped": dict(self.registry.dropped),
        }

    def state_dict(self) -> dict:
        """Everything accepted, as python data and tensors (``torch.save``-able, loadable with
        ``weights_only=True``). Open federated rounds are not kept: agents resubmit."""
        return {
            "registry": self.registry.state_dict(), "groups": self.groups.state_dict(),
            "foreign": self.foreign.state_dict(),
            "loops": [asdict(lp) for lp in self.loops],
            "corrected": [[a, k, torch.from_numpy(T.copy())] for (a, k), T in
                          self.corrected.items()],
            "rounds_closed": self.rounds_closed, "merges": self.merges,
            "pose_graph_runs": self.pose_graph_runs, "update_seq": dict(self.update_seq),
            "loop_book": self.book.state_dict(),
            # Queued and retrying candidates are verified after a reload (the book keeps no
            # pending pairs, and the queries that found them do not run again).
            "queued": [[c.agent_a, int(c.kf_a), c.agent_b, int(c.kf_b), float(c.score),
                        str(c.kind)] for c in [*self._candidates, *(c for _, c in self._retry)]],
        }

    def load_state_dict(self, state: dict) -> None:
        """Restore a `state_dict`; the loop database is refilled from the keyframes."""
        self.registry.load_state_dict(state["registry"])
        self.groups.load_state_dict(state["groups"])
        self.foreign.load_state_dict(state["foreign"])
        self.loops = [LoopRecord(**lp) for lp in state["loops"]]
        self.corrected = {(a, int(k)): T.numpy().copy() for a, k, T in state["corrected"]}
        self.rounds_closed, self.merges = list(state["rounds_closed"]), list(state["merges"])
        self.pose_graph_runs = list(state["pose_graph_runs"])
        self.update_seq = {str(a): int(s) for a, s in state["update_seq"].items()}
        self.book = LoopBook(max_attempts=self.book.max_attempts)
        if "loop_book" in state:
            self.book.load_state_dict(state["loop_book"])
        else:  # saved before the back end kept a LoopBook: the loop records hold the verdicts
            for lp in self.loops:
                if self.book.select([lp]):
                    self.book.record(lp, accepted=lp.accepted)
        self.rounds, self._retry = {}, []
        self._candidates = self.book.select([
            LoopCandidate(str(a), int(ka), str(b), int(kb), float(score), kind)
            for a, ka, b, kb, score, kind in state.get("queued", [])])
        new = set(self.registry.new_keyframes)
        for agent, rec in self.registry.agents.items():
            for kf in rec.kf_ids:
                if (agent, kf) not in new:
                    self.database.add(agent, kf, rec.keyframes[kf].descriptor,
                                      self.groups.group_of(agent).group_id)


def _pair(c: Candidate) -> tuple[str, int, str, int]:
    a, b = (c.agent_a, int(c.kf_a)), (c.agent_b, int(c.kf_b))
    return (*min(a, b), *max(a, b))


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
    from cpslam.server.loops import DescriptorDatabase

    return DescriptorDatabase.from_config(loop)


def _default_register(loop: LoopConfig, seed: int) -> Callable[[KeyframeImage, KeyframeImage],
                                                                Any]:
    def register(src: KeyframeImage, dst: KeyframeImage) -> Any:
        from cpslam.server.registration import RegistrationParams, register_rgbd, verify

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

"""The server back end: agents' messages in, loops, merges, rounds and corrections out.

No transport and no threads: the daemon calls `handle` for every decoded agent message, `step`
regularly (it runs the pending work), `agent_left` when an agent's liveliness goes, `status`
for the status query and `finalise` at the end; each returns the messages to send (`Outgoing`,
defined in `outgoing`). Time comes from the injected ``now`` and keyframe images from
``fetch_image`` (the server pulls images only for loop candidates and fine-tuning), so tests
drive it fully.

Per new keyframe the loop pipeline (`loops`: candidates, image pulls, registration,
refinement, verification, retries) verifies candidate pairs; a fine loop between two groups
merges them (`merges`; `groups`: alignment of the two frames) and the `Federator`
(`federation`) averages and fine-tunes their decoders; then the group's pose graph is
optimised (`tracks`) and every member gets a `ServerUpdate` (`sharing`: alignment, corrected
keyframe poses, other members' points) and, after a merge, a `GroupDecoder`. `finalise` runs
the last pose graph, the map refinement (`refinement`) and gathers the `FinalResult`
(`result`). `from_config` reads its arguments from a whole config (`settings`). See
docs/server.md.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from cpslam.protocol import KeyframeImage, Message
from cpslam.server.federation import Federator
from cpslam.server.final import final_result
from cpslam.server.fusion import MemberMap
from cpslam.server.groups import Group, Groups
from cpslam.server.loops import Candidate, LoopBook, LoopDatabase, LoopPipeline, LoopRecord
from cpslam.server.merges import add_stages, merge_groups, merge_record
from cpslam.server.outgoing import Outgoing, to_groups
from cpslam.server.pose_graph import PoseGraph, PoseGraphResult
from cpslam.server.registry import Registry
from cpslam.server.result import FinalResult
from cpslam.server.settings import backend_args
from cpslam.server.sharing import MemberUpdates
from cpslam.server.state import backend_state, new_state_id, restore_backend
from cpslam.server.tracks import group_kf_poses, optimise_groups

if TYPE_CHECKING:
    from cpslam.common.config import CpslamConfig
    from cpslam.common.config.collab import (
        FederationConfig,
        LoopConfig,
        PoseGraphConfig,
        RefinementConfig,
    )
    from cpslam.common.field import Decoders, FieldSpec
    from cpslam.server.federation import FederatedRound

__all__ = ["Backend", "LoopRecord", "Outgoing", "new_state_id"]

logger = logging.getLogger(__name__)


class Backend:
    """The collaborative back end (see the module docstring).

    Args:
        loop, federation, pose_graph, refinement: the config sections.
        fetch_image: ``(agent_id, kf_id) -> KeyframeImage | None`` (a Zenoh get in the daemon).
        spec: the neural field (point width, grid cell, rendering of the fine-tunes).
        now: monotonic clock (s).
        refine_pose, database, register, retry_after_s: the loop pipeline's (`LoopPipeline`;
            `from_config` makes `refine_pose` a `PoseRefiner` unless ``loop.refine`` is false).
        decoders_factory, finetune_lr, color_weight, seed: the decoder fine-tunes' (`Federator`;
            no factory, no fine-tune); finetune_lr_features: point features' rate in the
            final one.
        share_every_s: how often merged groups get the other members' new points.
        registry_args: `Registry`'s caps and expected shapes (`registry_args`; None: none).
        image_cache_bytes: bytes of keyframe images the loop pipeline caches.
        update_resend_after_s, update_max_points: an unacknowledged update is repaired after
            this long; an update with more foreign points is split (`MemberUpdates`).
        verify_budget_s: a step stops verifying candidates after this many (wall-clock)
            seconds and leaves the rest for the next step, so a daemon stays responsive (acks,
            updates) while a backlog is worked off. None (lock-step runs): no limit, so the
            work done per step does not depend on the machine's speed.
        verify_in_background: verify loop candidates on a worker thread (`loops.worker`), one
            at a time, so a step never waits for a registration (the daemon); False
            (lock-step runs, tests): inline, within `verify_budget_s`.
    """

    def __init__(
        self,
        loop: LoopConfig,
        federation: FederationConfig,
        pose_graph: PoseGraphConfig,
        refinement: RefinementConfig,
        fetch_image: Callable[[str, int], KeyframeImage | None],
        spec: FieldSpec,
        *,
        finetune_lr: float,
        finetune_lr_features: float,
        color_weight: float,
        seed: int,
        decoders_factory: Callable[[], Decoders] | None = None,
        now: Callable[[], float] = time.monotonic,
        refine_pose: Callable[..., Any] | None = None,
        database: LoopDatabase | None = None,
        register: Callable[[KeyframeImage, KeyframeImage], Any] | None = None,
        share_every_s: float = 10.0,
        verify_budget_s: float | None = None,
        retry_after_s: float = 5.0,
        registry_args: dict[str, Any] | None = None,
        image_cache_bytes: int | None = None,
        update_resend_after_s: float = 5.0,
        update_max_points: int = 200_000,
        verify_in_background: bool = False,
    ) -> None:
        self.verify_budget_s = verify_budget_s
        self.state_id = new_state_id()
        """Names what this back end holds (kept by a restore): agents compare it across a
        server restart to learn whether their acknowledged data survived."""
        self.loop_cfg, self.fed_cfg = loop, federation
        self.pg_cfg, self.refine_cfg = pose_graph, refinement
        self.now = now
        self.spec = spec
        self.finetune_lr_features = finetune_lr_features
        shapes = None
        if decoders_factory is not None:
            shapes = {n: tuple(t.shape) for n, t in decoders_factory().state_dict().items()}
        self.registry = Registry(spec.feature_dim, shapes, **(registry_args or {}))
        self.groups = Groups()
        self.corrected: dict[tuple[str, int], np.ndarray] = {}
        self.merges: list[dict] = []
        self._open_merges: dict[str, dict] = {}  # made this step; `_merge_timed` completes them
        self._finishing = False  # `finalise` runs: verify everything left, without a budget
        self.pose_graph_runs: list[dict] = []
        self.t_start = now()
        self.pipeline = LoopPipeline(loop, fetch_image, now, self.t_start, refine_pose, database,
                                     register, seed, retry_after_s, image_cache_bytes)
        self.federator = Federator(
            federation, self.registry, self.groups, self.pipeline.image, self.kf_poses,
            self.member_maps, now, self.t_start, spec, decoders_factory=decoders_factory,
            finetune_lr=finetune_lr, color_weight=color_weight, seed=seed,
            cached=self.pipeline.cached)
        self.sharing = MemberUpdates(self.registry, self.kf_poses, spec.grid_size, share_every_s,
                                     now, update_resend_after_s, update_max_points)
        if verify_in_background:
            self.pipeline.start_worker()

    def close(self) -> None:
        """Stop the verification worker, if any, after the candidate it is on (idempotent)."""
        self.pipeline.stop_worker()

    @classmethod
    def from_config(cls, cfg: CpslamConfig, fetch_image: Callable[[str, int], KeyframeImage |
                    None], **kwargs: Any) -> Backend:
        """A back end with the settings of a whole config (`backend_args`; ``kwargs``
        override/add)."""
        spec, args = backend_args(cfg)
        args.update(kwargs)
        backend = cls(cfg.loop, cfg.federation, cfg.pose_graph, cfg.refinement, fetch_image, spec,
                      **args)
        if cfg.loop.refine and "refine_pose" not in kwargs:  # the paper's rendering refinement
            from cpslam.server.loops import PoseRefiner
            backend.refine_pose = PoseRefiner.from_config(cfg, backend.registry)
        return backend

    # The loop pipeline's and the federator's state, under the back end's own names.

    @property
    def loops(self) -> list[LoopRecord]:
        """Every verified candidate, in order."""
        return self.pipeline.records

    @property
    def loops_found(self) -> int:
        """Distinct candidate pairs offered for verification."""
        return self.pipeline.found

    @property
    def book(self) -> LoopBook:
        return self.pipeline.book

    @property
    def database(self) -> LoopDatabase:
        return self.pipeline.database

    @property
    def refine_pose(self) -> Callable[..., Any] | None:
        return self.pipeline.refine_pose

    @refine_pose.setter
    def refine_pose(self, refine: Callable[..., Any] | None) -> None:
        self.pipeline.refine_pose = refine

    @property
    def _candidates(self) -> list[Candidate]:
        return self.pipeline.queue  # queued for verification

    @property
    def rounds(self) -> dict[str, FederatedRound]:
        """Open federated rounds by group."""
        return self.federator.rounds

    @property
    def rounds_closed(self) -> list[dict]:
        return self.federator.rounds_closed

    # ------------------------------------------------------------------------------ input

    def handle(self, msg: Message, nbytes: int = 0) -> list[Outgoing]:
        """Take one agent message (cheap; the work happens in `step`). Returns its `Ack`."""
        try:
            acks = self.registry.handle(msg, nbytes)
        except Exception:  # noqa: BLE001 - a bad message must never stop the server
            logger.exception("internal error handling %s", type(msg).__name__)
            self.registry.dropped.add("internal error")
            return []
        agent = getattr(msg, "agent_id", None)
        if agent in self.registry.agents:
            self.groups.add_agent(agent)
        return [Outgoing(a.agent_id, a) for a in acks]

    def update_acked(self, agent_id: str, incarnation: int, update_seq: int) -> bool:
        """The agent applied update `update_seq` (`UpdateAck`); one from an unknown agent or
        another incarnation is ignored. True when it confirmed foreign points."""
        rec = self.registry.agents.get(agent_id)
        if rec is None or rec.incarnation != int(incarnation):
            logger.warning("agent %s: ignoring update ack of incarnation %d (known: %s)",
                           agent_id, incarnation, None if rec is None else rec.incarnation)
            return False
        return self.sharing.acked(agent_id, int(update_seq))

    def agent_left(self, agent_id: str) -> None:
        """The agent vanished: no round waits for it any more; its data stays."""
        if agent_id in self.registry.agents:
            self.registry.agents[agent_id].alive = False
        self.federator.agent_left(agent_id)
        # No log line: the caller (the node watching liveliness) reports the leave once.

    # ------------------------------------------------------------------------------- work

    def step(self) -> list[Outgoing]:
        """Run the pending work: loop queries and verification, merges, pose graphs,
        federated rounds, point sharing. Returns the messages to send."""
        for agent, kf in self.registry.take_new_keyframes():
            self.pipeline.query(agent, kf, self.registry.agents[agent].keyframes[kf].descriptor,
                                self.groups.group_of(agent).group_id)
        self.pipeline.release_due()
        # Pairs that can merge two groups go first: a merge changes what every agent does.
        self.pipeline.queue.sort(key=lambda c: (self.groups.same_group(c.agent_a, c.agent_b)
                                                or c.kind != "fine"))
        dirty: dict[str, bool] = {}  # groups whose pose graph changed, in order
        out: list[Outgoing] = []
        if self.pipeline.worker is not None:
            for record in self.pipeline.collect(wait=self._finishing):
                out += self._accepted(record, dirty)
            if self._finishing:  # the rest is verified here, without a budget
                self.pipeline.stop_worker()
            else:
                self.pipeline.feed()
        if self.pipeline.worker is None:
            out += self._verify_inline(dirty, None if self._finishing else self.verify_budget_s)
        for gid in dirty:
            if gid in self.groups.groups:
                t0 = time.perf_counter()
                self._optimise_group(self.groups.groups[gid])
                t1 = time.perf_counter()
                out += self._updates(self.groups.groups[gid])
                self._merge_timed(gid, {"pose_graph_s": t1 - t0,
                                        "push_s": time.perf_counter() - t1})
        for agent, msg in self.registry.take_new_decoders():
            self.federator.submit(agent, msg)
        out += to_groups(self.federator.close_rounds())
        out += self._share()
        return out

    def _verify_inline(self, dirty: dict[str, bool], budget_s: float | None) -> list[Outgoing]:
        """Verify queued candidates on this thread until the queue is empty, a merge is made
        (published at once; the rest wait for the next step) or `budget_s` is spent."""
        queue, out = self.pipeline.queue, []
        t0 = time.perf_counter()
        while queue:
            if budget_s is not None and time.perf_counter() - t0 > budget_s:
                break
            record = self.pipeline.verify(queue.pop(0))
            out += self._accepted(record, dirty)
            if record is not None and record.merged:
                break
        return out

    def _accepted(self, record: LoopRecord | None, dirty: dict[str, bool]) -> list[Outgoing]:
        """Act on a verified pair: an accepted loop inside a group marks the group's pose graph
        for optimisation; a fine one between two groups merges them."""
        if record is None or not record.accepted:
            return []
        a, b = record.agent_a, record.agent_b
        out = []
        if not self.groups.same_group(a, b):
            if record.kind != "fine":
                return []  # a coarse pair only becomes an edge once its groups merge
            out = self._merge(record)
            record.merged = True
        dirty[self.groups.group_of(a).group_id] = True
        return out

    def _merge_timed(self, group_id: str, stages: dict[str, float]) -> None:
        """Add the pose graph's and push's times to the merge this step made into the group."""
        merge = self._open_merges.pop(group_id, None)
        if merge is not None:
            add_stages(merge, stages)

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
            pm = rec.points.to_point_map(rec.index, self.kf_poses(m), self.spec.feature_dim,
                                         self.spec.grid_size)
            out.append(MemberMap(m, rec.index, pm))
        return out

    def _merge(self, loop: LoopRecord) -> list[Outgoing]:
        group, joined, decoders, stages = merge_groups(
            loop, self.groups, self.pipeline, self.federator, self.corrected, self.kf_poses,
            lambda agent: self.registry.agents[agent].index)
        # The step adds the pose graph's and the push's stages (`_merge_timed`).
        merge = merge_record(self.now() - self.t_start, group, joined, loop, stages)
        self.merges.append(merge)
        self._open_merges[group.group_id] = merge
        return to_groups(decoders)

    def optimise(self, groups: list[Group]) -> tuple[PoseGraph, PoseGraphResult | None,
                                                       list[LoopRecord], dict[str, Any]]:
        """Optimise the pose graph of these groups (every member's odometry in its group frame,
        the accepted loops between members of one group); keyframe corrections and loop
        outliers are kept. Returns the graph, its result (None for an empty graph), its loops
        and the members' trajectories (`optimise_groups`)."""
        return optimise_groups(self.pg_cfg, self.registry, groups, self.loops, self.corrected)

    def _optimise_group(self, group: Group) -> None:
        t0 = time.perf_counter()
        graph, result, loops, _ = self.optimise([group])
        if result is not None:
            self.pose_graph_runs.append({
                "group": group.group_id, "nodes": graph.num_nodes, "loops": len(loops),
                "error_before": result.error_before, "error_after": result.error_after,
                "outliers": len(result.outlier_loops), "seconds": time.perf_counter() - t0})

    def _updates(self, group: Group) -> list[Outgoing]:
        """A `ServerUpdate` for every member of the group."""
        return [Outgoing(u.agent_id, u) for u in self.sharing.updates(group,
                                                                       self.member_maps(group))]

    def _share(self) -> list[Outgoing]:
        return [o for g in self.sharing.due(list(self.groups.groups.values()))
                for o in self._updates(g)]

    # ----------------------------------------------------------------------------- output

    def finalise(self) -> FinalResult:
        """Final pose graph over everything, refined fused maps, trajectories, metrics."""
        self.pipeline.last_chance()  # retries are due now, not in retry_after_s
        self._finishing = True
        self.step()
        while self.pipeline.queue:  # a step stops after a merge; nothing queued is left out
            self.step()
        self.registry.drop_unresolved()
        return final_result(self)

    def status(self) -> dict:
        """JSON summary for the status query: agents, groups, loops, rounds."""
        return {
            "state_id": self.state_id,
            "agents": {a: r.status() for a, r in self.registry.agents.items()},
            "groups": {g.group_id: {"members": g.members, "epoch": g.epoch, "round": g.round}
                       for g in self.groups.groups.values()},
            "loops": self.pipeline.status(),
            "rounds": {"closed": len(self.rounds_closed), "open": sorted(self.rounds)},
            "merges": len(self.merges),
            "dropped": dict(self.registry.dropped),
        }

    def state_dict(self) -> dict:
        """Everything accepted, as python data and tensors (``torch.save``-able, loadable with
        ``weights_only=True``; `cpslam.server.state`)."""
        return backend_state(self)

    def load_state_dict(self, state: dict) -> None:
        """Restore a `state_dict`; the loop database is refilled from the keyframes."""
        restore_backend(self, state)

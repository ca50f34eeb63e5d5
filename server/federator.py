"""Group merges and the groups' shared decoders: averaged and fine-tuned at a merge, then
federated rounds.

A verified fine loop between two groups merges them (`merge`): the group whose anchor joined
first keeps its id and frame, the other's members are re-aligned into it. At a merge the
members' latest local weights are averaged (`fedavg`, weighted by sample counts unless
``federation.weighting`` is "uniform") and fine-tuned on a few keyframe images: the group's
round r+1. If no member has sent weights yet, the first weights arriving open that first
round. Later a round opens with the first `DecoderWeights` answering the group's current round
and closes when every alive member answered or after ``federation.round_timeout_s``. A merge
abandons the open rounds of both groups. Messages come back as `GroupDecoder`s; the back end
addresses them.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from cpslam.common.camera import Intrinsics
from cpslam.common.geometry import compose, invert
from cpslam.protocol import GroupDecoder
from cpslam.server.federation import FederatedRound, fedavg
from cpslam.server.fusion import MemberMap, View, finetune_decoders, fuse

if TYPE_CHECKING:
    from cpslam.common.config.collab import FederationConfig
    from cpslam.common.field import Decoders
    from cpslam.protocol import DecoderWeights, KeyframeImage
    from cpslam.server.groups import Group, Groups
    from cpslam.server.loops.pipeline import LoopRecord
    from cpslam.server.registry import Registry

__all__ = ["Federator"]

logger = logging.getLogger(__name__)


class Federator:
    """Group merges, the groups' decoders and federated rounds (see the module docstring).

    Args:
        federation: the config section.
        registry, groups: the back end's (read; a group's decoder and round are written).
        image: ``(agent_id, kf_id) -> KeyframeImage | None`` (the loop pipeline's cache).
        kf_poses: ``agent -> {kf_id: T_group_kf}``, best current keyframe poses.
        member_maps: ``group -> [MemberMap]``, the members' sub-maps in the group frame.
        now, t_start: monotonic clock (s) and its value that round times count from.
        decoders_factory: builds fresh `Decoders` to load averaged weights into for
            fine-tuning; None skips fine-tuning.
        sampler: ray sampler of the fine-tunes (default: the paper's).
        feature_dim, cell_size, k, radius: the neural field's point width, grid cell (m),
            neighbours and radius (m).
        finetune_lr: Adam learning rate of the decoders.
        finetune_views: most keyframe images pulled for one fine-tune.
        seed: seed of every fine-tune.
    """

    def __init__(
        self,
        federation: FederationConfig,
        registry: Registry,
        groups: Groups,
        image: Callable[[str, int], KeyframeImage | None],
        kf_poses: Callable[[str], dict[int, np.ndarray]],
        member_maps: Callable[[Group], list[MemberMap]],
        now: Callable[[], float],
        t_start: float,
        decoders_factory: Callable[[], Decoders] | None = None,
        sampler: Any = None,
        feature_dim: int = 32,
        cell_size: float = 0.14,
        k: int = 8,
        radius: float = 0.15,
        finetune_lr: float = 0.003,
        finetune_views: int = 8,
        seed: int = 0,
    ) -> None:
        self.fed_cfg, self.registry, self.groups = federation, registry, groups
        self.image, self.kf_poses, self.member_maps = image, kf_poses, member_maps
        self.now, self.t_start = now, t_start
        self.decoders_factory, self.sampler = decoders_factory, sampler
        self.feature_dim, self.cell_size, self.k, self.radius = feature_dim, cell_size, k, radius
        self.finetune_lr, self.finetune_views, self.seed = finetune_lr, finetune_views, seed
        self.rounds: dict[str, FederatedRound] = {}  # open, by group
        self.rounds_closed: list[dict] = []

    def merge(self, loop: LoopRecord) -> tuple[Group, np.ndarray, list[str]]:
        """Merge the groups of a verified fine loop and drop their open rounds. Returns the
        merged group, ``T_new_old`` (the joining group's frame into the merged one) and the
        members that changed frame."""
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
        joined = sorted(gb.members)
        T_world = compose(invert(ga.T_group_agent[survivor]), T_ga_gb,
                          gb.T_group_agent[other])
        self.abandon(ga.group_id)
        self.abandon(gb.group_id)
        return self.groups.merge(survivor, other, T_world), T_ga_gb, joined

    def merged(self, group: Group) -> list[GroupDecoder]:
        """The merged group's first shared decoder (none while no member sent weights)."""
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
            avg = self.finetune(group, avg, self.fed_cfg.finetune_iters, lr_features=0.0)
        except ValueError as exc:
            logger.error("group %s: decoders cannot be averaged: %s", group.group_id, exc)
            return []
        group.decoder, group.decoder_samples = avg, int(sum(samples))
        group.round += 1
        return [self._group_decoder(group, [r.agent_id for r in have])]

    def abandon(self, group_id: str) -> None:
        """The group merges: its open round is dropped."""
        rnd = self.rounds.pop(group_id, None)
        if rnd is not None:
            logger.info("round %s#%d abandoned by a merge", rnd.group_id, rnd.round)

    def agent_left(self, agent_id: str) -> None:
        """No round waits for the agent any more."""
        for rnd in self.rounds.values():
            rnd.drop(agent_id)

    def submit(self, agent: str, msg: DecoderWeights) -> None:
        """The agent's new local weights (already in the registry) answer a round."""
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

    def close_rounds(self) -> list[GroupDecoder]:
        """Close the complete rounds (drop the expired ones); their shared decoders."""
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
                avg = self.finetune(group, avg, self.fed_cfg.finetune_iters, lr_features=0.0)
            group.decoder, group.round = avg, rnd.round
            group.decoder_samples = int(sum(self.registry.agents[a].decoder_samples
                                            for a in contributors))
            timed_out = bool(rnd.pending)
            self.rounds_closed.append({"group": gid, "round": rnd.round, "time": now - self.t_start,
                                       "contributors": contributors, "timed_out": timed_out})
            out.append(self._group_decoder(group, contributors))
        return out

    def finetune(self, group: Group, state: dict[str, np.ndarray], iters: int,
                 lr_features: float, point_map: Any = None) -> dict[str, np.ndarray]:
        """Decoder weights `state` fine-tuned on the group's map (fused from the members' when
        `point_map` is None) and up to ``finetune_views`` keyframe images."""
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
            img = self.image(agent, kf)
            if img is None or img.depth is None or img.rgb is None:
                continue
            intr = Intrinsics(img.fx, img.fy, img.cx, img.cy, img.width, img.height)
            views.append(View(img.rgb, img.depth_metres(), self.kf_poses(agent)[kf], intr))
        return views

    def _group_decoder(self, group: Group, contributors: list[str]) -> GroupDecoder:
        return GroupDecoder(group_id=group.group_id, round=group.round, members=contributors,
                            n_samples=group.decoder_samples, tensors=group.decoder)

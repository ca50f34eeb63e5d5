"""Federated decoder rounds: the groups' shared decoders, averaged and fine-tuned at a merge,
then averaged again round after round.

``fedavg`` is the pure weighted average of parameter dicts; ``FederatedRound`` keeps the
bookkeeping of one round: who is expected, who sent what, and when the round may close.
`Federator` runs them for every group: when two groups merge (`cpslam.server.groups`) the
members' latest local weights are averaged (`fedavg`, weighted by sample counts unless
``federation.weighting`` is "uniform") and fine-tuned on a few keyframe images: the group's
round r+1. If no member has sent weights yet, the first weights arriving open that first
round. Later a round opens with the first `DecoderWeights` answering the group's current round
and closes when every alive member answered or after ``federation.round_timeout_s``. A merge
abandons the open rounds of both groups. No transport here: messages come back as
`GroupDecoder`s, which the back end addresses.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
import torch

from cpslam.common.camera import Intrinsics
from cpslam.protocol import GroupDecoder
from cpslam.server.fusion import MemberMap, View, finetune_decoders, fuse

if TYPE_CHECKING:
    from cpslam.common.config.collab import FederationConfig
    from cpslam.common.field import Decoders, FieldSpec
    from cpslam.protocol import DecoderWeights, KeyframeImage
    from cpslam.server.groups import Group, Groups
    from cpslam.server.registry import Registry

__all__ = ["FederatedRound", "Federator", "fedavg"]

logger = logging.getLogger(__name__)

Tensor = np.ndarray | torch.Tensor
State = Mapping[str, Tensor]


def fedavg(states: Sequence[State], weights: Sequence[float]) -> dict[str, Tensor]:
    """Weighted average ``sum_i w_i state_i / sum_i w_i`` of parameter dicts.

    All states must have the same keys and, per key, the same shape and kind (all numpy or
    all torch). Weights are >= 0 and not all zero. The result is float32, numpy for numpy
    input and torch (on the first state's device) for torch input, keys in the order of the
    first state. Averaging runs in float64.
    """
    if len(states) == 0:
        raise ValueError("fedavg: no states to average")
    if len(weights) != len(states):
        raise ValueError(f"fedavg: {len(weights)} weights for {len(states)} states")
    w = np.asarray(weights, dtype=np.float64)
    if not np.all(np.isfinite(w)) or np.any(w < 0):
        raise ValueError(f"fedavg: weights must be finite and >= 0, got {list(weights)}")
    if w.sum() <= 0:
        raise ValueError("fedavg: weights are all zero")
    w = w / w.sum()

    keys = list(states[0])
    for i, state in enumerate(states[1:], start=1):
        missing, extra = set(keys) - set(state), set(state) - set(keys)
        if missing or extra:
            if missing:
                raise ValueError(f"fedavg: agent #{i} lacks key {sorted(missing)[0]!r} of agent #0")
            raise ValueError(f"fedavg: agent #{i} has key {sorted(extra)[0]!r} unknown to agent #0")
    return {key: _average([s[key] for s in states], w, key) for key in keys}


def _average(values: list[Tensor], w: np.ndarray, key: str) -> Tensor:
    first = values[0]
    is_torch = isinstance(first, torch.Tensor)
    for i, v in enumerate(values):
        if isinstance(v, torch.Tensor) != is_torch or not isinstance(v, np.ndarray | torch.Tensor):
            raise ValueError(
                f"fedavg: key {key!r} of agent #{i} is {type(v).__name__}, agent #0 has "
                f"{type(first).__name__}; all must be numpy arrays or all torch tensors"
            )
        if tuple(v.shape) != tuple(first.shape):
            raise ValueError(
                f"fedavg: key {key!r} of agent #{i} has shape {tuple(v.shape)}, "
                f"agent #0 has {tuple(first.shape)}"
            )
    if is_torch:
        device = first.device
        with torch.no_grad():
            stacked = torch.stack([v.detach().to(device, torch.float64) for v in values])
            coeff = torch.as_tensor(w, dtype=torch.float64, device=device)
            return torch.tensordot(coeff, stacked, dims=1).to(torch.float32)
    stacked_np = np.stack([np.asarray(v, dtype=np.float64) for v in values])
    return np.tensordot(w, stacked_np, axes=1).astype(np.float32)


class FederatedRound:
    """One federated round of a group: collects member states until complete, then averages.

    ``deadline_s`` is an absolute time on the caller's clock (the one ``now`` is read from,
    e.g. ``time.monotonic()``). The round is complete when every current member submitted,
    or when the deadline passed and at least one did. A member removed with ``drop`` (it left
    or vanished) is no longer waited for, and its submission, if any, is discarded.
    """

    def __init__(
        self,
        group_id: str,
        round: int,
        members: Iterable[str],
        deadline_s: float,
        weighting: Literal["samples", "uniform"] = "samples",
    ) -> None:
        self.group_id = group_id
        self.round = int(round)
        self.members: set[str] = set(members)
        if not self.members:
            raise ValueError(f"FederatedRound {group_id}#{round}: no members")
        if weighting not in ("samples", "uniform"):
            raise ValueError(f"weighting: expected 'samples' or 'uniform', got {weighting!r}")
        self.deadline_s = float(deadline_s)
        self.weighting = weighting
        self._states: dict[str, tuple[State, int]] = {}

    @property
    def submitted(self) -> set[str]:
        """Members whose state arrived."""
        return set(self._states)

    @property
    def pending(self) -> set[str]:
        """Members still waited for."""
        return self.members - set(self._states)

    def submit(self, agent: str, state: State, n_samples: int) -> None:
        """Record ``agent``'s state, trained on ``n_samples`` samples; a resubmission replaces
        the earlier one."""
        if agent not in self.members:
            raise ValueError(
                f"FederatedRound {self.group_id}#{self.round}: {agent!r} is not a member "
                f"(members: {sorted(self.members)})"
            )
        if n_samples < 0:
            raise ValueError(f"n_samples must be >= 0, got {n_samples} from {agent!r}")
        if agent in self._states:
            logger.info("round %s#%d: %s resubmitted", self.group_id, self.round, agent)
        self._states[agent] = (state, int(n_samples))

    def drop(self, agent: str) -> None:
        """Stop waiting for ``agent`` and forget its submission (unknown agents are ignored)."""
        self.members.discard(agent)
        self._states.pop(agent, None)

    def is_complete(self, now: float) -> bool:
        """All members submitted, or the deadline passed with at least one submission."""
        if not self._states:
            return False
        return not self.pending or now >= self.deadline_s

    def expired(self, now: float) -> bool:
        """The deadline passed with nothing submitted: the round can only be abandoned."""
        return now >= self.deadline_s and not self._states

    def result(self) -> tuple[dict[str, Tensor], list[str]]:
        """The averaged state and the sorted contributors."""
        if not self._states:
            raise RuntimeError(f"FederatedRound {self.group_id}#{self.round}: no submissions")
        agents = sorted(self._states)
        samples = [self._states[a][1] for a in agents]
        if self.weighting == "uniform" or sum(samples) == 0:
            # Nobody reporting samples says nothing about who trained more: treat alike.
            weights = [1.0] * len(agents)
        else:
            weights = [float(n) for n in samples]
        averaged = fedavg([self._states[a][0] for a in agents], weights)
        logger.info(
            "round %s#%d: averaged %d of %d members",
            self.group_id,
            self.round,
            len(agents),
            len(self.members),
        )
        return averaged, agents


class Federator:
    """The groups' decoders: first average at a merge, fine-tunes, federated rounds (see the
    module docstring).

    Args:
        federation: the config section.
        registry, groups: the back end's (read; a group's decoder and round are written).
        image: ``(agent_id, kf_id) -> KeyframeImage | None`` (the loop pipeline's cache).
        kf_poses: ``agent -> {kf_id: T_group_kf}``, best current keyframe poses.
        member_maps: ``group -> [MemberMap]``, the members' sub-maps in the group frame.
        now, t_start: monotonic clock (s) and its value that round times count from.
        spec: the neural field (fused maps, fine-tune rendering).
        decoders_factory: builds fresh `Decoders` to load averaged weights into for
            fine-tuning; None skips fine-tuning.
        finetune_lr: Adam learning rate of the decoders.
        color_weight: weight of the colour term of the fine-tune loss (the mapping loss's).
        seed: seed of every fine-tune.
        cached: ``(agent_id, kf_id) -> bool``, whether `image` holds the keyframe already;
            the views prefer those (no pull). None: the views are evenly spread.
        At most ``federation.finetune_views`` keyframe images (all when null) are pulled for
        one fine-tune.
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
        spec: FieldSpec,
        *,
        decoders_factory: Callable[[], Decoders] | None,
        finetune_lr: float,
        color_weight: float,
        seed: int,
        cached: Callable[[str, int], bool] | None = None,
    ) -> None:
        self.cached = cached
        self.fed_cfg, self.registry, self.groups = federation, registry, groups
        self.image, self.kf_poses, self.member_maps = image, kf_poses, member_maps
        self.now, self.t_start = now, t_start
        self.spec, self.decoders_factory = spec, decoders_factory
        self.finetune_lr, self.color_weight, self.seed = finetune_lr, color_weight, seed
        self.rounds: dict[str, FederatedRound] = {}  # open, by group
        self.rounds_closed: list[dict] = []

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
            self.registry.dropped.add("decoder weights for a past round or group")
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
        `point_map` is None) and up to ``federation.finetune_views`` keyframe images."""
        if self.decoders_factory is None or iters <= 0:
            return state
        decoders = self.decoders_factory()
        decoders.load_state_dict({k: torch.as_tensor(v) for k, v in state.items()})
        if point_map is None:
            point_map = fuse(self.member_maps(group), self.spec.feature_dim,
                             self.spec.grid_size)
        views = self._views(group)
        finetune_decoders(decoders, point_map, views, iters, self.finetune_lr, self.seed,
                          self.spec, color_weight=self.color_weight, lr_features=lr_features)
        return {k: v.detach().cpu().numpy().astype(np.float32)
                for k, v in decoders.state_dict().items()}

    def _views(self, group: Group) -> list[View]:
        keys = [(m, kf) for m in group.members for kf in self.registry.agents[m].kf_ids]
        if not keys:
            return []
        n_views = min(self.fed_cfg.finetune_views or len(keys), len(keys))
        have = None if self.cached is None else np.array([self.cached(*k) for k in keys])
        pick = spread_pick(len(keys), n_views, have)
        views = []
        for i in pick:
            agent, kf = keys[i]
            img = self.image(agent, kf)
            if img is None or img.depth is None or img.rgb is None:
                continue
            intr = Intrinsics.of(img)
            views.append(View(img.rgb, img.depth_metres(), self.kf_poses(agent)[kf], intr))
        return views

    def _group_decoder(self, group: Group, contributors: list[str]) -> GroupDecoder:
        # agents answer the next round with a delta against exactly these weights
        self.registry.decoder_bases.add(group.group_id, group.round, group.decoder)
        return GroupDecoder(group_id=group.group_id, round=group.round, members=contributors,
                            n_samples=group.decoder_samples, tensors=group.decoder)


def spread_pick(n: int, k: int, preferred: np.ndarray | None = None) -> np.ndarray:
    """Indices of k of n items spread evenly over them (sorted, distinct); with `preferred`
    (bool [n]) each pick moves to the nearest preferred item within half the spacing, so
    images the server holds already stand in for their neighbours."""
    targets = np.linspace(0, n - 1, k)
    pick = targets.round().astype(int)
    if preferred is not None and preferred.any() and k > 0:
        half = (n - 1) / (2 * (k - 1)) if k > 1 else (n - 1) / 2
        where = np.nonzero(preferred)[0]
        for j, t in enumerate(targets):
            near = where[np.abs(where - t) <= half]
            if len(near):
                pick[j] = near[np.argmin(np.abs(near - t))]
    return np.unique(pick)

"""Groups of agents sharing one frame and one set of decoders.

Each agent starts as its own group (its own world, its own decoders), with the agent's id as
group id, as `DecoderWeights.group_id` expects. A verified loop between two groups merges
them: the surviving group keeps its id and frame (the world of its anchor agent), the other
group's members are re-expressed in it. Every member has an alignment ``T_group_agent`` that
maps its own world into the group frame and an epoch that grows whenever that alignment
changes (the agents echo it as ``world_epoch``).

`Groups.merge_at_loop` is the group alignment of the paper's centralised stage: the loop's
relative pose between two keyframes, with both keyframes' current poses in their group
frames, gives the transform between the two groups' frames.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
import torch

from cpslam.common.geometry import compose, invert, is_rigid

if TYPE_CHECKING:
    from cpslam.server.loops import LoopRecord

__all__ = ["Group", "Groups"]

logger = logging.getLogger(__name__)


@dataclass
class Group:
    """Agents sharing a frame. ``members`` are in join order; the first is the anchor."""

    group_id: str
    anchor: str
    T_group_agent: dict[str, np.ndarray] = field(default_factory=dict)
    agent_epoch: dict[str, int] = field(default_factory=dict)
    """Alignment epoch of each member (1 after its first alignment message)."""
    epoch: int = 0
    """Grows with every change the members must apply (membership, alignments)."""
    decoder: dict[str, np.ndarray] | None = None
    """Shared decoder weights (float32 by name), None until the first average."""
    decoder_samples: int = 0
    round: int = 0
    """Last closed federated round (0: none)."""

    @property
    def members(self) -> list[str]:
        return list(self.T_group_agent)

    def state_dict(self) -> dict:
        return {
            "group_id": self.group_id, "anchor": self.anchor,
            "members": self.members,
            "T_group_agent": torch.from_numpy(np.stack(list(self.T_group_agent.values()))),
            "agent_epoch": dict(self.agent_epoch), "epoch": self.epoch,
            "decoder": None if self.decoder is None else {
                k: torch.from_numpy(v.copy()) for k, v in self.decoder.items()},
            "decoder_samples": self.decoder_samples, "round": self.round,
        }

    @classmethod
    def from_state_dict(cls, state: dict) -> Group:
        poses = state["T_group_agent"].cpu().numpy()
        return cls(
            group_id=state["group_id"], anchor=state["anchor"],
            T_group_agent={a: poses[i].copy() for i, a in enumerate(state["members"])},
            agent_epoch={str(a): int(e) for a, e in state["agent_epoch"].items()},
            epoch=int(state["epoch"]),
            decoder=None if state["decoder"] is None else {
                k: v.cpu().numpy().copy() for k, v in state["decoder"].items()},
            decoder_samples=int(state["decoder_samples"]), round=int(state["round"]),
        )


class Groups:
    """The partition of the agents into groups."""

    def __init__(self) -> None:
        self.groups: dict[str, Group] = {}
        self._of: dict[str, str] = {}

    def add_agent(self, agent: str) -> Group:
        """A singleton group for a new agent (its id as group id); the existing one if known."""
        if agent in self._of:
            return self.groups[self._of[agent]]
        if agent in self.groups:
            raise ValueError(f"add_agent: a group is already named {agent!r}")
        group = Group(agent, agent, {agent: np.eye(4)}, {agent: 0})
        self.groups[agent] = group
        self._of[agent] = agent
        return group

    def group_of(self, agent: str) -> Group:
        """The group of a known agent (KeyError naming it otherwise)."""
        if agent not in self._of:
            raise KeyError(f"agent {agent!r} is in no group")
        return self.groups[self._of[agent]]

    def same_group(self, a: str, b: str) -> bool:
        return self._of.get(a) is not None and self._of.get(a) == self._of.get(b)

    def merge(self, agent_a: str, agent_b: str, T_worldA_worldB: np.ndarray) -> Group:
        """Merge b's group into a's: ``T_worldA_worldB`` maps b's own world into a's.

        Members of b's group get ``T_ga_m = T_ga_a @ T_a_b @ inv(T_gb_b) @ T_gb_m`` and a new
        epoch; a's members keep their alignment. Returns the merged group (a's id and frame).
        """
        T_ab = np.asarray(T_worldA_worldB, np.float64)
        if T_ab.shape != (4, 4) or not is_rigid(T_ab):
            raise ValueError("merge: T_worldA_worldB must be a rigid 4x4 transform")
        ga, gb = self.group_of(agent_a), self.group_of(agent_b)
        if ga is gb:
            raise ValueError(f"merge: {agent_a!r} and {agent_b!r} are already in group "
                             f"{ga.group_id!r}")
        T_ga_gb = compose(ga.T_group_agent[agent_a], T_ab, invert(gb.T_group_agent[agent_b]))
        for member in gb.members:
            ga.T_group_agent[member] = compose(T_ga_gb, gb.T_group_agent[member])
            ga.agent_epoch[member] = gb.agent_epoch[member] + 1
            self._of[member] = ga.group_id
        ga.epoch = max(ga.epoch, gb.epoch) + 1
        ga.round = max(ga.round, gb.round)
        del self.groups[gb.group_id]
        logger.info("group %s absorbed group %s: members %s", ga.group_id, gb.group_id,
                    ga.members)
        return ga

    def merge_at_loop(self, loop: LoopRecord, kf_poses: Callable[[str], dict[int, np.ndarray]],
                      join_index: Callable[[str], int]) -> tuple[Group, str, np.ndarray,
                                                                 list[str]]:
        """Merge the groups of a verified loop between them.

        Args:
            loop: the loop (``T_a_b`` maps keyframe b's camera frame into keyframe a's).
            kf_poses: ``agent -> {kf_id: T_group_kf}``, best current keyframe poses.
            join_index: order in which agents joined; the group whose anchor joined first
                keeps its id and frame, so frames change as little as possible.

        Returns:
            The merged group, the id of the group it absorbed, ``T_new_old`` (the absorbed
            group's frame into the merged one) and the members that changed frame.
        """
        a, b = loop.agent_a, loop.agent_b
        ga, gb = self.group_of(a), self.group_of(b)
        if join_index(gb.anchor) < join_index(ga.anchor):
            ga, gb = gb, ga
        survivor = a if ga.group_id == self.group_of(a).group_id else b
        other = b if survivor == a else a
        T_s_o = np.asarray(loop.T_a_b) if survivor == a else invert(np.asarray(loop.T_a_b))
        kf_s = loop.kf_a if survivor == a else loop.kf_b
        kf_o = loop.kf_b if survivor == a else loop.kf_a
        T_ga_gb = compose(kf_poses(survivor)[kf_s], T_s_o, invert(kf_poses(other)[kf_o]))
        joined = sorted(gb.members)
        T_world = compose(invert(ga.T_group_agent[survivor]), T_ga_gb, gb.T_group_agent[other])
        absorbed = gb.group_id
        return self.merge(survivor, other, T_world), absorbed, T_ga_gb, joined

    def state_dict(self) -> dict:
        return {"groups": [g.state_dict() for g in self.groups.values()]}

    def load_state_dict(self, state: dict) -> None:
        self.groups = {}
        self._of = {}
        for s in state["groups"]:
            g = Group.from_state_dict(s)
            self.groups[g.group_id] = g
            for m in g.members:
                self._of[m] = g.group_id

"""What the members of a group are sent: one `ServerUpdate` each with the member's alignment,
its best current keyframe poses and the other members' points.

The points are incremental (`ForeignTracker`): an update carries only what is new or changed
since what the member acknowledged (`acked`, from its `UpdateAck`), and the ids it no longer
needs. After merges and corrections the back end sends updates at once; besides, a merged
group gets them every ``share_every_s`` when a member's points or keyframes changed, and again
``resend_after_s`` after an update a member has not acknowledged (`due`: the repair of a lost
update or ack). An update with more than ``max_points`` points is split into several.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable
from typing import TYPE_CHECKING

import numpy as np

from cpslam.protocol import ServerUpdate
from cpslam.server.ledger import ForeignTracker

if TYPE_CHECKING:
    from cpslam.server.fusion import MemberMap
    from cpslam.server.groups import Group
    from cpslam.server.registry import Registry

__all__ = ["MemberUpdates"]

logger = logging.getLogger(__name__)

UPDATE_BUDGET = 32 << 20
"""Bytes of foreign points in one update (half the ServerUpdate cap, for poses and framing)."""


class MemberUpdates:
    """Builds the members' `ServerUpdate`s and tells when a group is due again.

    Args:
        registry: the back end's (an update records the alignment it announces).
        kf_poses: ``agent -> {kf_id: T_group_kf}``, best current keyframe poses.
        cell_size: grid cell (m) that decides which of the other members' points are sent.
        share_every_s: least time between two periodic updates of a group.
        now: monotonic clock (s).
        resend_after_s: a group with an unacknowledged update is due again after this.
        max_points: most foreign points in one `ServerUpdate` (more are split).
    """

    def __init__(self, registry: Registry, kf_poses: Callable[[str], dict[int, np.ndarray]],
                 cell_size: float, share_every_s: float, now: Callable[[], float],
                 resend_after_s: float = 5.0, max_points: int = 200_000) -> None:
        self.registry, self.kf_poses = registry, kf_poses
        self.cell_size, self.share_every_s, self.now = cell_size, share_every_s, now
        self.resend_after_s, self.max_points = float(resend_after_s), int(max_points)
        self.foreign = ForeignTracker()  # what each agent holds of the others' points
        self.seq: dict[str, int] = {}  # last update seq per agent
        self.ignored_acks = 0
        self._last: dict[str, tuple[float, tuple]] = {}  # group -> (time, signature) sent

    def updates(self, group: Group, maps: list[MemberMap]) -> list[ServerUpdate]:
        """A `ServerUpdate` for every member of the group (`maps`: the members' sub-maps)."""
        out = []
        for mm in maps:
            agent = mm.agent_id
            others = [o for o in maps if o.agent_id != agent]
            versions = {o.agent_id: self.registry.agents[o.agent_id].points.seq for o in others}
            first = self.seq.get(agent, 0) + 1
            # Split by points and by bytes (features dominate: wide ones shrink the parts).
            limit = min(self.max_points, UPDATE_BUDGET // (27 + 2 * self.registry.feature_dim))
            parts = self.foreign.parts(mm, others, versions, self.cell_size, first, limit)
            poses = self.kf_poses(agent)
            kfs = sorted(poses)
            epoch = group.agent_epoch[agent]
            self.registry.set_alignment(agent, epoch, group.T_group_agent[agent])
            self.seq[agent] = first + len(parts) - 1
            out += [ServerUpdate(
                agent_id=agent, seq=first + p, epoch=epoch,
                group_id=group.group_id, group_members=group.members,
                T_group_agent=group.T_group_agent[agent],
                kf_ids=np.asarray(kfs, np.int32),
                T_group_kf=np.stack([poses[k] for k in kfs]) if kfs else np.zeros((0, 4, 4)),
                foreign=blocks) for p, blocks in enumerate(parts)]
        self._last[group.group_id] = (self.now(), self._signature(group))
        return out

    def acked(self, agent: str, seq: int) -> bool:
        """The agent applied update `seq` (its `UpdateAck`); one above every update sent to it
        is ignored with a warning. Returns True when it confirmed something new."""
        if seq > self.seq.get(agent, 0):
            self.ignored_acks += 1
            logger.warning("agent %s: ignoring update ack %d: only updates <= %d were sent",
                           agent, seq, self.seq.get(agent, 0))
            return False
        return self.foreign.acked(agent, seq)

    def due(self, groups: Iterable[Group]) -> list[Group]:
        """The merged groups whose last update is ``share_every_s`` old and out of date, or
        ``resend_after_s`` old with a live member that has not acknowledged everything."""
        out = []
        for group in groups:
            if len(group.members) < 2:
                continue
            last, sig = self._last.get(group.group_id, (-np.inf, ()))
            age = self.now() - last
            unconfirmed = any(self.foreign.pending(m) and self.registry.agents[m].alive
                              for m in group.members)
            if ((age >= self.share_every_s and self._signature(group) != sig)
                    or (age >= self.resend_after_s and unconfirmed)):
                out.append(group)
        return out

    def _signature(self, group: Group) -> tuple:
        return tuple((m, len(self.registry.agents[m].points),
                      int(self.registry.agents[m].points.seq.max(initial=-1)),
                      len(self.registry.agents[m].keyframes)) for m in group.members)

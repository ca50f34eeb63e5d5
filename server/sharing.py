"""What the members of a group are sent: one `ServerUpdate` each with the member's alignment,
its best current keyframe poses and the other members' points.

The points are incremental (`ForeignTracker`): an update carries only what is new or changed
since the member's last one, and the ids it no longer needs. After merges and corrections the
back end sends updates at once; besides, a merged group gets them every ``share_every_s``
when a member's points or keyframes changed (`due`).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import TYPE_CHECKING

import numpy as np

from cpslam.protocol import ServerUpdate
from cpslam.server.fusion import ForeignTracker

if TYPE_CHECKING:
    from cpslam.server.fusion import MemberMap
    from cpslam.server.groups import Group
    from cpslam.server.registry import Registry

__all__ = ["MemberUpdates"]


class MemberUpdates:
    """Builds the members' `ServerUpdate`s and tells when a group is due again.

    Args:
        registry: the back end's (an update records the alignment it announces).
        kf_poses: ``agent -> {kf_id: T_group_kf}``, best current keyframe poses.
        cell_size: grid cell (m) that decides which of the other members' points are sent.
        share_every_s: least time between two periodic updates of a group.
        now: monotonic clock (s).
    """

    def __init__(self, registry: Registry, kf_poses: Callable[[str], dict[int, np.ndarray]],
                 cell_size: float, share_every_s: float, now: Callable[[], float]) -> None:
        self.registry, self.kf_poses = registry, kf_poses
        self.cell_size, self.share_every_s, self.now = cell_size, share_every_s, now
        self.foreign = ForeignTracker()  # what each agent holds of the others' points
        self.seq: dict[str, int] = {}  # last update seq per agent
        self._last: dict[str, tuple[float, tuple]] = {}  # group -> (time, signature) sent

    def updates(self, group: Group, maps: list[MemberMap]) -> list[ServerUpdate]:
        """A `ServerUpdate` for every member of the group (`maps`: the members' sub-maps)."""
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
            self.seq[agent] = self.seq.get(agent, 0) + 1
            out.append(ServerUpdate(
                agent_id=agent, seq=self.seq[agent], epoch=epoch,
                group_id=group.group_id, group_members=group.members,
                T_group_agent=group.T_group_agent[agent],
                kf_ids=np.asarray(kfs, np.int32),
                T_group_kf=np.stack([poses[k] for k in kfs]) if kfs else np.zeros((0, 4, 4)),
                foreign=blocks))
        self._last[group.group_id] = (self.now(), self._signature(group))
        return out

    def due(self, groups: Iterable[Group]) -> list[Group]:
        """The merged groups whose last update is ``share_every_s`` old and out of date."""
        out = []
        for group in groups:
            if len(group.members) < 2:
                continue
            last, sig = self._last.get(group.group_id, (-np.inf, ()))
            if self.now() - last >= self.share_every_s and self._signature(group) != sig:
                out.append(group)
        return out

    def _signature(self, group: Group) -> tuple:
        return tuple((m, len(self.registry.agents[m].points),
                      int(self.registry.agents[m].points.seq.max(initial=-1)),
                      len(self.registry.agents[m].keyframes)) for m in group.members)

"""A merge of two groups at a verified fine loop (`merge_groups`) and its entry in the back
end's ``merges`` of ``metrics.json``, timed by stage (`merge_record`, `add_stages`).

A merge changes what every member of both groups does, so the back end makes it as soon as
the loop is verified; the same step then optimises the group's pose graph and pushes the
members' updates, and adds those two stages to the entry. Its inputs are handed in
(only the daemon imports the back end).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

from cpslam.common.geometry import compose

if TYPE_CHECKING:
    from cpslam.protocol import GroupDecoder
    from cpslam.server.federation import Federator
    from cpslam.server.groups import Group, Groups
    from cpslam.server.loops import LoopPipeline, LoopRecord

__all__ = ["add_stages", "merge_groups", "merge_record"]


def merge_groups(loop: LoopRecord, groups: Groups, pipeline: LoopPipeline, federator: Federator,
                 corrected: dict[tuple[str, int], np.ndarray],
                 kf_poses: Callable[[str], dict[int, np.ndarray]],
                 join_index: Callable[[str], int]
                 ) -> tuple[Group, list[str], list[GroupDecoder], dict[str, float]]:
    """Merge the two groups of `loop` (`Groups.merge_at_loop`): both groups' open rounds are
    abandoned, the joining members' queued candidates and their poses in `corrected` move to
    the merged group's frame, and the federator fuses the groups' decoders.

    Returns the merged group, the members that joined it, its first shared decoders (to
    publish) and the merge's stages so far (s): the loop's verification, the alignment of the
    two frames, the decoders' fusion.
    """
    t0 = time.perf_counter()
    for agent in (loop.agent_a, loop.agent_b):  # a merge abandons both groups' rounds
        federator.abandon(groups.group_of(agent).group_id)
    group, _, T_new_old, joined = groups.merge_at_loop(loop, kf_poses, join_index)
    for m in joined:  # the joining members' keyframes and corrected poses change frame
        pipeline.regroup(m, group.group_id)
        for key in [key for key in corrected if key[0] == m]:
            corrected[key] = compose(T_new_old, corrected[key])
    t1 = time.perf_counter()
    decoders = federator.merged(group)
    stages = {"verify_s": loop.seconds, "align_s": t1 - t0,
              "decoders_s": time.perf_counter() - t1}
    return group, joined, decoders, stages


def merge_record(time_s: float, group: Group, joined: list[str], loop: LoopRecord,
                 stages: dict[str, float]) -> dict:
    """The ``merges`` entry of a merge made `time_s` after the start: its group, the members
    that joined, all members, its loop, and its stages (s, rounded) with their sum."""
    return {"time": time_s, "group": group.group_id, "joined": joined,
            "members": group.members, "loop_id": loop.loop_id,
            "stages": {k: round(v, 4) for k, v in stages.items()},
            "seconds": round(sum(stages.values()), 4)}


def add_stages(merge: dict, stages: dict[str, float]) -> None:
    """Add the stages the merge's step ran after it (pose graph, push) to its entry."""
    merge["stages"].update({k: round(v, 4) for k, v in stages.items()})
    merge["seconds"] = round(sum(merge["stages"].values()), 4)

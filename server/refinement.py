"""Map refinement, the paper's last step: after the final pose graph every group's map is fused
from its members' sub-maps at their corrected keyframe poses (the points move with their
keyframes), grid-filtered, and its decoders and point features are fine-tuned briefly on
keyframe images.

A plain function of what it needs: the back end hands in its groups, the members' maps and its
fine-tune (`cpslam.server.federation.Federator.finetune`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from cpslam.common.field import NeuralPointMap
from cpslam.server.fusion import MemberMap, fuse

if TYPE_CHECKING:
    from cpslam.server.groups import Group

__all__ = ["refine_maps"]

State = dict[str, np.ndarray]


def refine_maps(
    groups: list[Group],
    member_maps: Callable[[Group], list[MemberMap]],
    agent_decoder: Callable[[str], State | None],
    finetune: Callable[..., State],
    feature_dim: int,
    cell_size: float,
    *,
    grid_filter: bool,
    finetune_iters: int,
    lr_features: float,
) -> tuple[dict[str, NeuralPointMap], dict[str, State], list[dict[str, Any]]]:
    """Each group's refined map and decoder weights.

    Args:
        groups: the groups to refine.
        member_maps: ``group -> [MemberMap]``, the members' sub-maps at their final
            group-frame keyframe poses.
        agent_decoder: ``agent -> weights | None``, an agent's latest local decoder (a group
            that never merged has no shared one).
        finetune: ``(group, weights, iters, lr_features, point_map=...) -> weights``.
        feature_dim, cell_size: the field's point feature width and grid cell (m).
        grid_filter, finetune_iters: the ``refinement`` section's.
        lr_features: the point features' learning rate in the fine-tune.

    Returns:
        Fused maps (group frame) and fine-tuned decoders by group id (groups without any
        decoder weights have none), and per group ``{"group", "points"}`` for metrics.json.
    """
    maps, decoders, stats = {}, {}, []
    for group in groups:
        fused = fuse(member_maps(group), feature_dim, cell_size, grid_filter=grid_filter)
        maps[group.group_id] = fused
        state = group.decoder
        if state is None and len(group.members) == 1:
            state = agent_decoder(group.members[0])
        if state is not None:
            decoders[group.group_id] = finetune(group, state, finetune_iters, lr_features,
                                                point_map=fused)
        stats.append({"group": group.group_id, "points": len(fused)})
    return maps, decoders, stats

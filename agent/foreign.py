"""Other agents' points joining an agent's map (the `ForeignPoints` blocks of a server update).

Each source agent has its own agent key in the neural point map (chosen by `AgentLink`); its
keyframe poses come with the block, so its points sit at ``T_group_kf @ xyz_local``.
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np
import torch

from cpslam.protocol import ForeignPoints

__all__ = ["merge_foreign"]

logger = logging.getLogger(__name__)


def merge_foreign(pm: Any, key: int, block: ForeignPoints, receiver: str) -> int:
    """Add (or replace) the block's points under agent key `key` of the map `pm`, after its
    keyframe poses and removals; returns how many were added (`receiver` names the log)."""
    if block.point_ids.size and block.features.shape[1] != pm.feature_dim:
        logger.warning(
            "agent %s: foreign points of %s have %d features, the map %d; dropped",
            receiver,
            block.source_agent_id,
            block.features.shape[1],
            pm.feature_dim,
        )
        return 0
    if len(block.kf_ids):
        pm.set_keyframe_poses(block.kf_ids.astype(np.int64), block.T_group_kf, key)
    if block.removed_ids.size:
        pm.remove(torch.from_numpy(block.removed_ids), key)
    if not block.point_ids.size:
        return 0
    pm.remove(torch.from_numpy(block.point_ids), key)
    anchored = np.array([pm.has_keyframe(int(k), key) for k in block.anchor_kf_ids], bool)
    if not anchored.all():
        logger.warning(
            "agent %s: %d foreign points of %s anchored to unknown keyframes; dropped",
            receiver,
            int((~anchored).sum()),
            block.source_agent_id,
        )
    n = int(anchored.sum())
    if n:
        _append_points(
            pm,
            key,
            block.point_ids[anchored],
            block.anchor_kf_ids[anchored].astype(np.int64),
            block.xyz_local[anchored],
            block.features[anchored],
            block.colors[anchored],
        )
    return n


def _append_points(
    pm: Any,
    agent: int,
    ids: np.ndarray,
    anchors: np.ndarray,
    xyz_local: np.ndarray,
    features: np.ndarray,
    colors: np.ndarray,
) -> None:
    """Append points given in their anchors' frames (no grid filter: the server only sends
    points in cells the receiver's own points leave free)."""
    state = pm.state_dict()
    n = len(ids)
    extra = {
        "anchor_kf": torch.from_numpy(anchors.astype(np.int64)),
        "xyz_local": torch.from_numpy(xyz_local.astype(np.float32)),
        "features": torch.from_numpy(features.astype(np.float32)),
        "agent_id": torch.full((n,), agent, dtype=torch.int32),
        "point_id": torch.from_numpy(ids.astype(np.int64)),
        "color": torch.from_numpy(colors.astype(np.uint8)),
    }
    for name, value in extra.items():
        state[name] = torch.cat((state[name], value))
    nxt = {int(a): int(v) for a, v in state["next_point_id"].tolist()}
    nxt[agent] = max(nxt.get(agent, 0), int(ids.max()) + 1)
    state["next_point_id"] = torch.tensor(sorted(nxt.items()), dtype=torch.int64).reshape(-1, 2)
    pm.load_state_dict(state, source="foreign points")

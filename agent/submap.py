"""The sub-map delta of an agent's own points: which of them go to the server, and their
`SubmapDelta` fields.

The points are read from the odometry's point map (the agent's own key only: other members'
points came from the server), picked by the `SubmapMirror` (new, moved enough, gone) and
their features encoded with the mirror's codec; the mirror then takes the delta as sent.
Split out of `cpslam.agent.link`, which numbers and keeps the message.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from cpslam.agent.deltas import SubmapMirror, encode_features

if TYPE_CHECKING:
    from cpslam.common.field import NeuralPointMap

__all__ = ["submap_delta_fields"]


def submap_delta_fields(pm: NeuralPointMap, own: int, mirror: SubmapMirror, seq: int,
                        feature_rows: bool, acked: int, max_points: int | None = None,
                        held: bool = True) -> dict[str, Any] | None:
    """`SubmapDelta` fields (all but ``agent_id`` and ``seq``) of the points of agent key
    `own` that are new or moved enough since the server's copy (the first `max_points` of
    them) and of own points that disappeared; None when there is none. `mirror` records them
    as sent in the message `seq`. With `feature_rows`, a known point whose full row went in a
    message the server acknowledged (seq <= `acked`) goes with its features alone. Without
    `held`, points the mirror knows wait for a later delta (only new ones and removals go)."""
    rows = (pm.agent_id == own).nonzero(as_tuple=True)[0]
    ids = pm.point_id[rows].cpu().numpy()
    order = np.argsort(ids)
    ids, rows = ids[order], rows[torch.from_numpy(order).to(rows.device)]
    feats = pm.features.detach()[rows].cpu().numpy().astype(np.float32)
    send, removed = mirror.select(ids, feats)
    if not held:
        send &= ~mirror.knows(ids)
    if max_points is not None:
        send[np.nonzero(send)[0][max_points:]] = False
    if not send.any() and not len(removed):
        return None
    alone = mirror.feature_only(ids, send, acked) if feature_rows else np.zeros_like(send)
    whole = send & ~alone
    # feature rows: the whole points' first, then those going alone
    order = np.concatenate((np.nonzero(whole)[0], np.nonzero(alone)[0]))
    fields, received = encode_features(feats[order], mirror.codec, mirror.bits)
    mirror.commit(ids, send, received[np.argsort(order)], seq, alone)
    r = rows[torch.from_numpy(np.nonzero(whole)[0]).to(rows.device)]
    return dict(point_ids=ids[whole],
                anchor_kf_ids=pm.anchor_kf[r].cpu().numpy().astype(np.int32),
                xyz_local=pm.xyz_local[r].detach().cpu().numpy().astype(np.float32),
                colors=pm.color[r].cpu().numpy().astype(np.uint8),
                removed_ids=removed.astype(np.int64), feature_ids=ids[alone], **fields)

"""What the server already holds of an agent's map and decoder, and the compact deltas to it.

`SubmapMirror` keeps the server's copy of the agent's own point features (what was sent,
after the wire codec's rounding) and picks the points worth sending: new ones, and known
ones whose features moved by more than ``threshold`` times the largest magnitude of the
server's copy of that point. Comparing against the server's copy, not against the last
local value, means slow drift below the threshold still gets sent once it adds up.

`DecoderBase` remembers the group decoder the agent last loaded (the last agreed weights of
its group) and turns local weights into an int8 delta against it.
"""

from __future__ import annotations

from typing import Any, Literal

import numpy as np

from cpslam.protocol.quant import dequantise_rows, quantise_rows

__all__ = ["DecoderBase", "SubmapMirror", "encode_features"]

FeatureCodec = Literal["float16", "int8"]


def encode_features(features: np.ndarray, codec: FeatureCodec) -> tuple[dict[str, Any], np.ndarray]:
    """(SubmapDelta feature fields, the float32 values the receiver decodes from them)."""
    if codec == "float16":
        f16 = np.asarray(features, np.float32).astype(np.float16)
        return {"features": f16}, f16.astype(np.float32)
    if codec == "int8":
        q, scale = quantise_rows(np.asarray(features, np.float32))
        return {"features_int8": q, "feature_scales": scale}, dequantise_rows(q, scale)
    raise ValueError(f"feature codec: expected 'float16' or 'int8', got {codec!r}")


class SubmapMirror:
    """The server's copy of one agent's own point features, and which points to send next.

    Args:
        feature_dim: width F of the features.
        threshold: relative change (of the copy's largest magnitude) that makes a known point
            worth resending; 0 sends every change.
        codec: how features travel ("float16" or "int8").
    """

    def __init__(
        self, feature_dim: int, threshold: float = 0.0, codec: FeatureCodec = "float16"
    ) -> None:
        if threshold < 0:
            raise ValueError(f"SubmapMirror: threshold must be >= 0, got {threshold}")
        if codec not in ("float16", "int8"):
            raise ValueError(f"SubmapMirror: codec must be 'float16' or 'int8', got {codec!r}")
        self.threshold, self.codec = float(threshold), codec
        self.ids = np.zeros(0, np.int64)  # sorted
        self.features = np.zeros((0, feature_dim), np.float32)

    def select(self, ids: np.ndarray, features: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(mask [N] of the rows to send, ids the server holds that are gone) for the current
        points `ids` int64 [N] (sorted) with `features` float32 [N, F]. Read only."""
        known = np.zeros(len(ids), bool)
        pos = np.zeros(len(ids), np.int64)
        if len(self.ids) and len(ids):
            pos = np.minimum(np.searchsorted(self.ids, ids), len(self.ids) - 1)
            known = self.ids[pos] == ids
        send = ~known
        if known.any():
            held = self.features[pos[known]]
            # at float16, the server's storage precision: with threshold 0 a change that
            # rounds away is no change (as before thresholds existed)
            now = features[known].astype(np.float16).astype(np.float32)
            moved = np.abs(now - held).max(axis=1)
            if self.threshold == 0:
                send[known] = moved > 0
            else:
                send[known] = moved > self.threshold * np.abs(held).max(axis=1)
        return send, np.setdiff1d(self.ids, ids)

    def commit(
        self, ids: np.ndarray, features: np.ndarray, send: np.ndarray, received: np.ndarray
    ) -> None:
        """The server now holds `received` (float32, rows of ``ids[send]``) for the sent rows
        and its old copy for the others; points not in `ids` are gone."""
        kept = np.zeros((len(ids), self.features.shape[1]), np.float32)
        old = ~send
        if old.any():
            pos = np.searchsorted(self.ids, ids[old])
            kept[old] = self.features[pos]
        kept[send] = received
        self.ids, self.features = np.asarray(ids, np.int64), kept


class DecoderBase:
    """The group decoder an agent last loaded, and deltas of local weights against it."""

    def __init__(self) -> None:
        self.group_id: str | None = None
        self.round = 0
        self.tensors: dict[str, np.ndarray] = {}

    def set(self, group_id: str, round: int, tensors: dict[str, np.ndarray]) -> None:
        """The agent loaded `group_id`'s shared decoder of `round`."""
        self.group_id, self.round = group_id, int(round)
        self.tensors = {k: np.asarray(v, np.float32).copy() for k, v in tensors.items()}

    def delta_fields(self, group_id: str, weights: dict[str, np.ndarray]) -> dict[str, Any]:
        """`DecoderWeights` fields for `weights`: an int8 delta against the base when it is of
        `group_id` and has the same tensors, else the full float32 weights."""
        usable = (
            self.group_id == group_id
            and self.round >= 1
            and set(self.tensors) == set(weights)
            and all(self.tensors[k].shape == weights[k].shape for k in weights)
        )
        if not usable:
            return {"tensors": {k: np.asarray(v, np.float32) for k, v in weights.items()}}
        q, scales = {}, {}
        for name, value in weights.items():
            q[name], scales[name] = quantise_rows(
                np.asarray(value, np.float32) - self.tensors[name]
            )
        return {"base_round": self.round, "tensors_int8": q, "tensor_scales": scales}

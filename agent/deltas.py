"""What the server already holds of an agent's map and decoder, and the compact deltas to it.

`SubmapMirror` keeps the server's copy of the agent's own point features (what was sent,
after the wire codec's rounding) and picks the points worth sending: new ones, and known
ones whose features moved by more than ``threshold`` times the largest magnitude of the
server's copy of that point. Comparing against the server's copy, not against the last
local value, means slow drift below the threshold still gets sent once it adds up.

`DecoderBase` remembers the group decoder the agent last loaded (the last agreed weights of
its group) and, while there is none, the weights the server holds from the agent's last
acknowledged `DecoderWeights`; it turns local weights into an int8 delta against one of them,
or, with neither, sends them whole at float16 (float32 where a weight is beyond float16's range).
Every ``full_every``-th message of the agent's own chain goes full, so a server that lost the
chain (a restart) is back in step within that many rounds.
"""

from __future__ import annotations

from typing import Any, Literal

import numpy as np

from cpslam.protocol.quant import add_delta, dequantise_rows, quantise_rows

__all__ = ["DecoderBase", "SubmapMirror", "encode_features", "feature_levels"]

FeatureCodec = Literal["float16", "int8"]
_F16_MAX = float(np.finfo(np.float16).max)


def encode_features(features: np.ndarray, codec: FeatureCodec,
                    bits: int = 8) -> tuple[dict[str, Any], np.ndarray]:
    """(SubmapDelta feature fields, the float32 values the receiver decodes from them); int8
    codes use `bits` bits (levels +-(2^(bits-1) - 1)), which zstd packs into about that many."""
    if codec == "float16":
        f16 = np.asarray(features, np.float32).astype(np.float16)
        return {"features": f16}, f16.astype(np.float32)
    if codec == "int8":
        q, scale = quantise_rows(np.asarray(features, np.float32), feature_levels(bits),
                                 scale_dtype=np.float16)
        return {"features_int8": q, "feature_scales": scale}, dequantise_rows(q, scale)
    raise ValueError(f"feature codec: expected 'float16' or 'int8', got {codec!r}")


def feature_levels(bits: int) -> int:
    """Largest int8 code magnitude of `bits`-bit feature codes (2-8 bits)."""
    if not 2 <= bits <= 8:
        raise ValueError(f"feature bits must be in 2..8, got {bits}")
    return (1 << (bits - 1)) - 1


class SubmapMirror:
    """The server's copy of one agent's own point features, and which points to send next.

    Args:
        feature_dim: width F of the features.
        threshold: relative change (of the copy's largest magnitude) that makes a known point
            worth resending; 0 sends every change.
        codec: how features travel ("float16" or "int8").
        bits: bits of an int8 feature code (`encode_features`).
    """

    def __init__(
        self, feature_dim: int, threshold: float = 0.0, codec: FeatureCodec = "float16",
        bits: int = 8,
    ) -> None:
        if threshold < 0:
            raise ValueError(f"SubmapMirror: threshold must be >= 0, got {threshold}")
        if codec not in ("float16", "int8"):
            raise ValueError(f"SubmapMirror: codec must be 'float16' or 'int8', got {codec!r}")
        feature_levels(bits)  # checks the range
        self.threshold, self.codec, self.bits = float(threshold), codec, int(bits)
        self.ids = np.zeros(0, np.int64)  # sorted
        self.features = np.zeros((0, feature_dim), np.float32)
        # seq of the message that carried each point's full row (position, anchor, colour)
        self.seqs = np.zeros(0, np.int64)

    def select(self, ids: np.ndarray, features: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(mask [N] of the rows to send, ids the server holds that are gone) for the current
        points `ids` int64 [N] (sorted) with `features` float32 [N, F]. Read only."""
        pos, known = self._find(ids)
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

    def knows(self, ids: np.ndarray) -> np.ndarray:
        """Mask [N] of the points `ids` int64 [N] the server holds a copy of."""
        return self._find(ids)[1]

    def _find(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(row [N] in the copy, whether it is that point [N]) for the points `ids` int64 [N]."""
        if not len(self.ids) or not len(ids):
            return np.zeros(len(ids), np.int64), np.zeros(len(ids), bool)
        pos = np.minimum(np.searchsorted(self.ids, ids), len(self.ids) - 1)
        return pos, self.ids[pos] == ids

    def feature_only(self, ids: np.ndarray, send: np.ndarray, acked_seq: int) -> np.ndarray:
        """Mask [N] of the rows of `send` that may go as features alone: points whose full row
        travelled in a message the server has acknowledged (seq <= `acked_seq`), so it holds
        them. A point's anchor, position and colour never change under its id."""
        out = np.zeros(len(ids), bool)
        rows = np.nonzero(send)[0]
        pos, hit = self._find(ids[rows])
        out[rows[hit]] = self.seqs[pos[hit]] <= acked_seq
        return out

    def commit(
        self, ids: np.ndarray, send: np.ndarray, received: np.ndarray, seq: int,
        feature_only: np.ndarray | None = None,
    ) -> None:
        """The server now holds `received` (float32, rows of ``ids[send]``) for the sent rows
        and its old copy for the others it knew; points not in `ids` are gone, and new points
        left out of this message stay unknown (sent by a later one). Rows of `send` not in
        `feature_only` travelled whole in message `seq`."""
        keep = send.copy()
        held = np.zeros((len(ids), self.features.shape[1]), np.float32)
        seqs = np.full(len(ids), int(seq), np.int64)
        held[send] = received
        old = np.nonzero(~send | (feature_only if feature_only is not None else False))[0]
        if len(old) and len(self.ids):
            pos, hit = self._find(ids[old])
            keep[old[hit]] = True
            unsent = hit & ~send[old]
            held[old[unsent]] = self.features[pos[unsent]]
            seqs[old[hit]] = self.seqs[pos[hit]]
        self.ids, self.features = np.asarray(ids, np.int64)[keep], held[keep]
        self.seqs = seqs[keep]


class DecoderBase:
    """The weights the server agreed on last, and deltas of local weights against them.

    Args:
        full_every: every this many messages answered against the agent's own weights, one
            goes full (>= 1; 1 never sends an own delta).
        full_codec: full weights as "float16" (as float32 where one does not fit) or as
            "int8" with one scale per row (half the bytes).
    """

    def __init__(self, full_every: int = 10, full_codec: str = "float16") -> None:
        if full_every < 1:
            raise ValueError(f"DecoderBase: full_every must be >= 1, got {full_every}")
        if full_codec not in ("float16", "int8"):
            raise ValueError(f"DecoderBase: full_codec must be float16 or int8, got {full_codec!r}")
        self.full_every, self.full_codec = full_every, full_codec
        self.group_id: str | None = None
        self.round = 0
        self.tensors: dict[str, np.ndarray] = {}
        self.own_seq: int | None = None  # acknowledged own message the server holds
        self.own: dict[str, np.ndarray] = {}
        self._sent: tuple[int, dict[str, np.ndarray]] | None = None  # waiting for its ack
        self._chain = 0

    def set(self, group_id: str, round: int, tensors: dict[str, np.ndarray]) -> None:
        """The agent loaded `group_id`'s shared decoder of `round`."""
        self.group_id, self.round = group_id, int(round)
        self.tensors = {k: np.asarray(v, np.float32).copy() for k, v in tensors.items()}

    def fields(self, group_id: str, weights: dict[str, np.ndarray]) -> dict[str, Any]:
        """`DecoderWeights` fields for `weights`: an int8 delta against `group_id`'s loaded
        decoder, else against the own weights the server holds, else the full weights (int8
        with `full_codec` "int8"; else float16 when every one fits, which the server's copy
        then is). No
        own delta while an earlier message is unacknowledged: the server keeps only the
        newest own weights it took, so by the time it reads this one it may hold that
        message's weights instead of the acknowledged ones."""
        weights = {k: np.asarray(v, np.float32) for k, v in weights.items()}
        if self.group_id == group_id and self.round >= 1 and _fits(self.tensors, weights):
            return {"base_round": self.round, **_delta(weights, self.tensors)}
        if (
            self.own_seq is not None
            and self._sent is None
            and self._chain % self.full_every != 0
            and _fits(self.own, weights)
        ):
            return {"base_seq": self.own_seq, **_delta(weights, self.own)}
        if self.full_codec == "int8":
            return _delta(weights)
        if all(np.abs(v).max(initial=0.0) <= _F16_MAX for v in weights.values()):
            return {"tensors_f16": {k: v.astype(np.float16) for k, v in weights.items()}}
        return {"tensors": weights}

    def sent(self, seq: int, fields: dict[str, Any]) -> None:
        """The message of `seq` carried `fields` (its weights become the own base once
        acknowledged)."""
        if "tensors" in fields or "tensors_f16" in fields:
            full = fields.get("tensors", fields.get("tensors_f16"))
            held = {k: np.asarray(v, np.float32) for k, v in full.items()}
        else:  # what the server rebuilds: the base (if any) plus the dequantised values
            values = {k: dequantise_rows(q, fields["tensor_scales"][k])
                      for k, q in fields["tensors_int8"].items()}
            if "base_round" in fields:
                held = add_delta(self.tensors, values)
            elif "base_seq" in fields:
                held = add_delta(self.own, values)
            else:
                held = values
        self._sent = (seq, held)
        self._chain += 1

    def acked(self, seq: int) -> None:
        """The server acknowledged every message up to `seq`."""
        if self._sent is not None and self._sent[0] <= seq:
            self.own_seq, self.own = self._sent
            self._sent = None


def _fits(base: dict[str, np.ndarray], weights: dict[str, np.ndarray]) -> bool:
    return set(base) == set(weights) and all(base[k].shape == weights[k].shape for k in weights)


def _delta(weights: dict[str, np.ndarray], base: dict[str, np.ndarray] | None = None
           ) -> dict[str, Any]:
    """int8 fields of `weights` minus `base` (None: the weights themselves)."""
    q, scales = {}, {}
    for name, value in weights.items():
        q[name], scales[name] = quantise_rows(value if base is None else value - base[name])
    return {"tensors_int8": q, "tensor_scales": scales}

"""The shared group decoders the server published lately: the bases agents' decoder deltas
refer to (`DecoderWeights.base_round`); `submitted_weights` resolves an agent's submission
against them (or against the agent's own previous weights) and checks it.

Bounded: the newest ``per_group`` rounds of each group and ``max_entries`` in all (the oldest
go first). A delta against a base no longer (or never) held cannot be applied; the registry
drops it with a reason naming the base, and the agent's next round, answered against a newer
base or with full weights after a group change, takes its place.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Mapping

import numpy as np

from cpslam.common.bounds import tensor_mismatch
from cpslam.protocol import DecoderWeights
from cpslam.protocol.quant import add_delta

__all__ = ["DecoderBases", "apply_delta", "submitted_weights"]


class DecoderBases:
    """Published group decoders by (group id, round), float32 tensors by name."""

    def __init__(self, per_group: int = 4, max_entries: int = 256) -> None:
        if per_group < 1 or max_entries < 1:
            raise ValueError(
                f"DecoderBases: per_group and max_entries must be >= 1, got "
                f"{per_group}, {max_entries}"
            )
        self.per_group, self.max_entries = per_group, max_entries
        self._held: OrderedDict[tuple[str, int], dict[str, np.ndarray]] = OrderedDict()

    def __len__(self) -> int:
        return len(self._held)

    def add(self, group_id: str, round: int, tensors: Mapping[str, np.ndarray]) -> None:
        """Remember the decoder `group_id` published for `round`."""
        key = (group_id, int(round))
        self._held[key] = {k: np.asarray(v, np.float32).copy() for k, v in tensors.items()}
        self._held.move_to_end(key)
        rounds = sorted(r for g, r in self._held if g == group_id)
        for r in rounds[: -self.per_group]:
            del self._held[(group_id, r)]
        while len(self._held) > self.max_entries:
            self._held.popitem(last=False)

    def apply(
        self, group_id: str, round: int, delta: Mapping[str, np.ndarray]
    ) -> dict[str, np.ndarray] | str:
        """Base plus `delta` as float32 weights, or the reason it cannot be applied."""
        base = self._held.get((group_id, int(round)))
        if base is None:
            return (
                f"decoder delta against {group_id}#{round}, a group decoder this server "
                "does not hold"
            )
        return apply_delta(base, delta, f"{group_id}#{round}")


def submitted_weights(
    msg: DecoderWeights,
    held: Mapping[str, np.ndarray] | None,
    held_seq: int,
    bases: DecoderBases,
    shapes: dict[str, tuple[int, ...]] | None,
    max_samples: int | None,
) -> dict[str, np.ndarray] | str:
    """The float32 weights `msg` carries, or why the server must not take them. `held`,
    `held_seq`: the agent's weights the server holds and the seq they came with (a delta may
    name them as its base); `shapes`: expected tensor names and shapes (None: not checked);
    `max_samples`: largest sample count a submission may claim (None: no cap)."""
    if int(msg.seq) < held_seq:
        # A resend that arrives after the agent's newer weights must not replace them.
        return (
            f"decoder weights of seq {msg.seq}, older than the agent's seq {held_seq} the "
            "server holds"
        )
    tensors = msg.values()
    if msg.base_round is not None:
        tensors = bases.apply(msg.group_id, msg.base_round, tensors)
    elif msg.base_seq is not None:
        if held is None or held_seq != msg.base_seq:
            return (
                f"decoder delta against the agent's seq {msg.base_seq}, the server holds its "
                f"weights of seq {held_seq}"
            )
        tensors = apply_delta(held, tensors, f"seq {msg.base_seq}")
    if isinstance(tensors, str):
        return tensors
    if shapes is not None:
        reason = tensor_mismatch(tensors, shapes)
        if reason:
            return reason
    n = int(msg.n_samples)
    if max_samples is not None and n > max_samples:
        return (
            f"field n_samples is {n}, expected at most {max_samples} "
            "(limits.max_federated_samples)"
        )
    return tensors


def apply_delta(
    base: Mapping[str, np.ndarray], delta: Mapping[str, np.ndarray], what: str
) -> dict[str, np.ndarray] | str:
    """`base` plus `delta` (float32, `add_delta`), or why they do not fit (`what` names the
    base)."""
    if set(base) != set(delta):
        return f"decoder delta names other tensors than the base {what}"
    for name, value in delta.items():
        if value.shape != base[name].shape:
            return (
                f"decoder delta tensor {name} has shape {list(value.shape)}, the base "
                f"{list(base[name].shape)}"
            )
    return add_delta(dict(base), dict(delta))

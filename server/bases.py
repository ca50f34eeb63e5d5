"""The shared group decoders the server published lately: the bases agents' decoder deltas
refer to (`DecoderWeights.base_round`).

Bounded: the newest ``per_group`` rounds of each group and ``max_entries`` in all (the oldest
go first). A delta against a base no longer (or never) held cannot be applied; the registry
drops it with a reason naming the base, and the agent's next round, answered against a newer
base or with full weights after a group change, takes its place.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Mapping

import numpy as np

from cpslam.protocol.quant import add_delta

__all__ = ["DecoderBases", "apply_delta"]


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

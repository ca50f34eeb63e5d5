"""Federated averaging of decoder weights inside a group of agents.

``fedavg`` is the pure weighted average of parameter dicts; ``FederatedRound`` keeps the
bookkeeping of one round: who is expected, who sent what, and when the round may close. No
transport here: the server daemon feeds submissions in and publishes the result.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Mapping, Sequence
from typing import Literal

import numpy as np
import torch

__all__ = ["FederatedRound", "fedavg"]

logger = logging.getLogger(__name__)

Tensor = np.ndarray | torch.Tensor
State = Mapping[str, Tensor]


def fedavg(states: Sequence[State], weights: Sequence[float]) -> dict[str, Tensor]:
    """Weighted average ``sum_i w_i state_i / sum_i w_i`` of parameter dicts.

    All states must have the same keys and, per key, the same shape and kind (all numpy or
    all torch). Weights are >= 0 and not all zero. The result is float32, numpy for numpy
    input and torch (on the first state's device) for torch input, keys in the order of the
    first state. Averaging runs in float64.
    """
    if len(states) == 0:
        raise ValueError("fedavg: no states to average")
    if len(weights) != len(states):
        raise ValueError(f"fedavg: {len(weights)} weights for {len(states)} states")
    w = np.asarray(weights, dtype=np.float64)
    if not np.all(np.isfinite(w)) or np.any(w < 0):
        raise ValueError(f"fedavg: weights must be finite and >= 0, got {list(weights)}")
    if w.sum() <= 0:
        raise ValueError("fedavg: weights are all zero")
    w = w / w.sum()

    keys = list(states[0])
    for i, state in enumerate(states[1:], start=1):
        missing, extra = set(keys) - set(state), set(state) - set(keys)
        if missing or extra:
            if missing:
                raise ValueError(f"fedavg: agent #{i} lacks key {sorted(missing)[0]!r} of agent #0")
            raise ValueError(f"fedavg: agent #{i} has key {sorted(extra)[0]!r} unknown to agent #0")
    return {key: _average([s[key] for s in states], w, key) for key in keys}


def _average(values: list[Tensor], w: np.ndarray, key: str) -> Tensor:
    first = values[0]
    is_torch = isinstance(first, torch.Tensor)
    for i, v in enumerate(values):
        if isinstance(v, torch.Tensor) != is_torch or not isinstance(v, np.ndarray | torch.Tensor):
            raise ValueError(
                f"fedavg: key {key!r} of agent #{i} is {type(v).__name__}, agent #0 has "
                f"{type(first).__name__}; all must be numpy arrays or all torch tensors"
            )
        if tuple(v.shape) != tuple(first.shape):
            raise ValueError(
                f"fedavg: key {key!r} of agent #{i} has shape {tuple(v.shape)}, "
                f"agent #0 has {tuple(first.shape)}"
            )
    if is_torch:
        device = first.device
        with torch.no_grad():
            stacked = torch.stack([v.detach().to(device, torch.float64) for v in values])
            coeff = torch.as_tensor(w, dtype=torch.float64, device=device)
            return torch.tensordot(coeff, stacked, dims=1).to(torch.float32)
    stacked_np = np.stack([np.asarray(v, dtype=np.float64) for v in values])
    return np.tensordot(w, stacked_np, axes=1).astype(np.float32)


class FederatedRound:
    """One federated round of a group: collects member states until complete, then averages.

    ``deadline_s`` is an absolute time on the caller's clock (the one ``now`` is read from,
    e.g. ``time.monotonic()``). The round is complete when every current member submitted,
    or when the deadline passed and at least one did. A member removed with ``drop`` (it left
    or vanished) is no longer waited for, and its submission, if any, is discarded.
    """

    def __init__(
        self,
        group_id: str,
        round: int,
        members: Iterable[str],
        deadline_s: float,
        weighting: Literal["samples", "uniform"] = "samples",
    ) -> None:
        self.group_id = group_id
        self.round = int(round)
        self.members: set[str] = set(members)
        if not self.members:
            raise ValueError(f"FederatedRound {group_id}#{round}: no members")
        if weighting not in ("samples", "uniform"):
            raise ValueError(f"weighting: expected 'samples' or 'uniform', got {weighting!r}")
        self.deadline_s = float(deadline_s)
        self.weighting = weighting
        self._states: dict[str, tuple[State, int]] = {}

    @property
    def submitted(self) -> set[str]:
        """Members whose state arrived."""
        return set(self._states)

    @property
    def pending(self) -> set[str]:
        """Members still waited for."""
        return self.members - set(self._states)

    def submit(self, agent: str, state: State, n_samples: int) -> None:
        """Record ``agent``'s state, trained on ``n_samples`` samples; a resubmission replaces
        the earlier one."""
        if agent not in self.members:
            raise ValueError(
                f"FederatedRound {self.group_id}#{self.round}: {agent!r} is not a member "
                f"(members: {sorted(self.members)})"
            )
        if n_samples < 0:
            raise ValueError(f"n_samples must be >= 0, got {n_samples} from {agent!r}")
        if agent in self._states:
            logger.info("round %s#%d: %s resubmitted", self.group_id, self.round, agent)
        self._states[agent] = (state, int(n_samples))

    def drop(self, agent: str) -> None:
        """Stop waiting for ``agent`` and forget its submission (unknown agents are ignored)."""
        self.members.discard(agent)
        self._states.pop(agent, None)

    def is_complete(self, now: float) -> bool:
        """All members submitted, or the deadline passed with at least one submission."""
        if not self._states:
            return False
        return not self.pending or now >= self.deadline_s

    def expired(self, now: float) -> bool:
        """The deadline passed with nothing submitted: the round can only be abandoned."""
        return now >= self.deadline_s and not self._states

    def result(self) -> tuple[dict[str, Tensor], list[str]]:
        """The averaged state and the sorted contributors."""
        if not self._states:
            raise RuntimeError(f"FederatedRound {self.group_id}#{self.round}: no submissions")
        agents = sorted(self._states)
        samples = [self._states[a][1] for a in agents]
        if self.weighting == "uniform" or sum(samples) == 0:
            # Nobody reporting samples says nothing about who trained more: treat alike.
            weights = [1.0] * len(agents)
        else:
            weights = [float(n) for n in samples]
        averaged = fedavg([self._states[a][0] for a in agents], weights)
        logger.info(
            "round %s#%d: averaged %d of %d members",
            self.group_id,
            self.round,
            len(agents),
            len(self.members),
        )
        return averaged, agents

"""Loop candidates from keyframe descriptors (place recognition).

`DescriptorDatabase` holds the L2-normalised global descriptor of every keyframe the server
has received, from every agent, in one stacked float32 matrix, so a query is one
matrix-vector product (cosine similarity = dot product). A query returns the stored keyframes
that resemble the query keyframe, with two thresholds (the paper's): score >= ``lambda_fine``
gives a "fine" candidate (good enough to align sub-maps with), ``lambda_coarse <= score <
lambda_fine`` a "coarse" one (an extra pose-graph edge once verified). Candidates come from
every agent and every group — an inter-group candidate is what triggers a merge — and from
the querying agent itself (loop closure within one agent), except its recent keyframes.

Thresholds depend on the descriptor; docs/loops.md has the calibration.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Literal, Protocol

import numpy as np

if TYPE_CHECKING:
    from cpslam.common.config.collab import LoopConfig

__all__ = ["Candidate", "DescriptorDatabase", "Keyframe", "LoopCandidate", "LoopDatabase"]

logger = logging.getLogger(__name__)

_STATE_VERSION = 1
Keyframe = tuple[str, int]
"""A keyframe: ``(agent id, keyframe id)``."""


class Candidate(Protocol):
    """What a loop database returns (`LoopCandidate`)."""

    agent_a: str
    kf_a: int
    agent_b: str
    kf_b: int
    score: float
    kind: str


class LoopDatabase(Protocol):
    """Where the loop pipeline looks for candidates (`DescriptorDatabase`)."""

    def add(self, agent_id: str, kf_id: int, descriptor: np.ndarray, group: str) -> Any: ...
    def query(self, agent_id: str, kf_id: int, descriptor: np.ndarray) -> list[Candidate]: ...


@dataclass(frozen=True)
class LoopCandidate:
    """A stored keyframe (b) that resembles a query keyframe (a)."""

    agent_a: str
    kf_a: int
    agent_b: str
    kf_b: int
    score: float
    """Cosine similarity of the two descriptors."""
    kind: Literal["fine", "coarse"]
    """"fine": score >= lambda_fine (sub-map alignment); "coarse": pose-graph edge only."""

    @property
    def pair(self) -> tuple[Keyframe, Keyframe]:
        """The two keyframes in a canonical order (the same whichever was the query)."""
        a, b = (self.agent_a, self.kf_a), (self.agent_b, self.kf_b)
        return (a, b) if a <= b else (b, a)

    @property
    def intra_agent(self) -> bool:
        """Whether both keyframes come from the same agent."""
        return self.agent_a == self.agent_b


class DescriptorDatabase:
    """Keyframe descriptors of all agents; loop candidates by cosine similarity.

    Args:
        lambda_fine: score at or above which a candidate is "fine".
        lambda_coarse: score at or above which a candidate is returned at all ("coarse").
        min_keyframe_gap: within one agent, keyframes fewer than this many keyframes apart
            are not candidates; the keyframe itself and its immediate neighbours never are
            (they are joined by sequential edges already), whatever the gap.
        max_candidates: at most this many candidates per query, best first.
        nms_radius: a candidate is dropped when a better one of the same agent lies within
            this many keyframes of it (they show the same place; one verification suffices).
            0 turns the suppression off.

    Keyframe distances count the agent's stored keyframes, not id differences, so ids may
    be frame indices or counters alike.
    """

    def __init__(
        self,
        *,
        lambda_fine: float,
        lambda_coarse: float,
        min_keyframe_gap: int,
        max_candidates: int,
        nms_radius: int = 2,
    ) -> None:
        if not -1.0 <= lambda_coarse <= lambda_fine <= 1.0:
            raise ValueError(
                f"need -1 <= lambda_coarse ({lambda_coarse}) <= lambda_fine ({lambda_fine}) <= 1"
            )
        if min_keyframe_gap < 0 or max_candidates < 1 or nms_radius < 0:
            raise ValueError(
                f"need min_keyframe_gap >= 0 (got {min_keyframe_gap}), max_candidates >= 1 "
                f"(got {max_candidates}), nms_radius >= 0 (got {nms_radius})"
            )
        self.lambda_fine = float(lambda_fine)
        self.lambda_coarse = float(lambda_coarse)
        self.min_keyframe_gap = int(min_keyframe_gap)
        self.max_candidates = int(max_candidates)
        self.nms_radius = int(nms_radius)
        self._clear()

    @classmethod
    def from_config(cls, cfg: LoopConfig) -> DescriptorDatabase:
        """Build from the ``loop`` config section."""
        return cls(
            lambda_fine=cfg.lambda_fine,
            lambda_coarse=cfg.lambda_coarse,
            min_keyframe_gap=cfg.min_keyframe_gap,
            max_candidates=cfg.max_candidates,
        )

    def __len__(self) -> int:
        return self._n

    @property
    def dim(self) -> int | None:
        """Descriptor length D (None until the first `add`)."""
        return None if self._desc is None else self._desc.shape[1]

    @property
    def groups(self) -> dict[str, str]:
        """Group of every agent (a copy)."""
        return dict(self._group)

    def group_of(self, agent: str) -> str:
        """Group the agent belongs to; KeyError for an agent never added."""
        return self._group[agent]

    def agents_in(self, group: str) -> list[str]:
        """Agents of a group, in the order they were first added."""
        return [a for a in self._agents if self._group[a] == group]

    def keyframes(self, agent: str) -> np.ndarray:
        """Sorted keyframe ids int64 [K] stored for an agent (empty if none)."""
        return self._sorted_kfs(agent).copy()

    def add(self, agent: str, kf_id: int, descriptor: np.ndarray, group: str) -> None:
        """Store (or replace) the descriptor [D] of keyframe ``kf_id`` of ``agent``.

        Raises:
            ValueError: for a descriptor of the wrong length, non-finite or zero, or an
                agent added under a different group than it belongs to (use `regroup`).
        """
        self._insert(agent, int(kf_id), self._normalised(descriptor, "add"), group)

    def query(
        self, agent: str, kf_id: int, descriptor: np.ndarray, group: str | None = None
    ) -> list[LoopCandidate]:
        """Stored keyframes resembling keyframe ``kf_id`` of ``agent`` (which need not be
        stored yet), best score first.

        Args:
            agent, kf_id: the query keyframe (its own agent's recent keyframes are excluded).
            descriptor: its descriptor [D].
            group: only keyframes of agents now in this group; None (default): every group.

        Returns:
            At most ``max_candidates`` candidates with score >= ``lambda_coarse``, after
            non-maximum suppression.
        """
        if self._n == 0:
            return []
        q = self._normalised(descriptor, "query")
        scores = self._desc[: self._n] @ q
        agent_idx = self._agent_idx[: self._n]
        keep = scores >= self.lambda_coarse
        if group is not None:
            members = [self._agent_index[a] for a in self.agents_in(group)]
            keep &= np.isin(agent_idx, members)
        own = self._agent_index.get(agent)
        if own is not None:
            mine = agent_idx == own
            rank = np.searchsorted(self._sorted_kfs(agent), self._kf[: self._n][mine])
            rank_q = self._rank(agent, int(kf_id))
            keep[mine] &= np.abs(rank - rank_q) >= max(self.min_keyframe_gap, 2)
        rows = np.flatnonzero(keep)
        rows = rows[np.argsort(-scores[rows], kind="stable")]

        out: list[LoopCandidate] = []
        kept: list[tuple[str, int]] = []  # (agent, rank) of the candidates kept so far
        for row in rows:
            other = self._agents[self._agent_idx[row]]
            kf_b = int(self._kf[row])
            rank_b = self._rank(other, kf_b)
            if any(a == other and abs(r - rank_b) <= self.nms_radius for a, r in kept):
                continue
            score = float(scores[row])
            kind: Literal["fine", "coarse"] = "fine" if score >= self.lambda_fine else "coarse"
            out.append(LoopCandidate(agent, int(kf_id), other, kf_b, score, kind))
            kept.append((other, rank_b))
            if len(out) == self.max_candidates:
                break
        return out

    def regroup(self, agent: str, group: str) -> None:
        """Move an agent (all its keyframes) to another group, e.g. after a merge."""
        if agent not in self._group:
            raise KeyError(f"regroup: unknown agent {agent!r}")
        if self._group[agent] != group:
            logger.debug("descriptor database: agent %s moves to group %s", agent, group)
        self._group[agent] = group

    def state_dict(self) -> dict[str, Any]:
        """Everything needed to rebuild the database: plain Python values and numpy arrays."""
        n = self._n
        dim = self.dim or 0
        return {
            "version": _STATE_VERSION,
            "descriptors": (self._desc[:n].copy() if self._desc is not None
                            else np.zeros((0, dim), np.float32)),
            "agents": [self._agents[i] for i in self._agent_idx[:n]] if n else [],
            "kf_ids": self._kf[:n].copy() if n else np.zeros(0, np.int64),
            "groups": dict(self._group),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Replace the contents with a `state_dict`.

        Raises:
            ValueError: naming the key, for a missing key, another version or inconsistent
                sizes.
        """
        for key in ("version", "descriptors", "agents", "kf_ids", "groups"):
            if key not in state:
                raise ValueError(f"descriptor database state: missing key {key!r}")
        if state["version"] != _STATE_VERSION:
            raise ValueError(
                f"descriptor database state: version {state['version']!r}, "
                f"expected {_STATE_VERSION}"
            )
        desc = np.asarray(state["descriptors"], dtype=np.float32)
        agents = [str(a) for a in state["agents"]]
        kf_ids = np.asarray(state["kf_ids"], dtype=np.int64).reshape(-1)
        groups = {str(a): str(g) for a, g in dict(state["groups"]).items()}
        if desc.ndim != 2 or not (len(desc) == len(agents) == len(kf_ids)):
            raise ValueError(
                "descriptor database state: 'descriptors' [N, D], 'agents' [N] and 'kf_ids' [N] "
                f"disagree: {desc.shape}, {len(agents)}, {kf_ids.shape}"
            )
        missing = sorted(set(agents) - set(groups))
        if missing:
            raise ValueError(f"descriptor database state: 'groups' lacks agents {missing}")
        self._clear()
        for agent, kf_id, d in zip(agents, kf_ids, desc, strict=True):
            self._insert(agent, int(kf_id), d, groups[agent])  # bit-exact, no renormalising
        for agent, group in groups.items():  # agents without keyframes keep their group
            self._register(agent, group)

    # -- internals --------------------------------------------------------------------------

    def _clear(self) -> None:
        self._desc: np.ndarray | None = None
        self._agent_idx = np.zeros(0, np.int32)
        self._kf = np.zeros(0, np.int64)
        self._n = 0
        self._agents: list[str] = []
        self._agent_index: dict[str, int] = {}
        self._group: dict[str, str] = {}
        self._rows: dict[Keyframe, int] = {}
        self._sorted: dict[str, np.ndarray] = {}

    def _insert(self, agent: str, kf_id: int, q: np.ndarray, group: str) -> None:
        known = self._group.get(agent)
        if known is not None and known != group:
            raise ValueError(
                f"add: agent {agent!r} belongs to group {known!r}, not {group!r}; "
                "move it with regroup()"
            )
        if self._desc is None:
            self._desc = np.zeros((16, q.size), np.float32)
            self._agent_idx = np.zeros(16, np.int32)
            self._kf = np.zeros(16, np.int64)
        self._register(agent, group)
        key = (agent, int(kf_id))
        row = self._rows.get(key)
        if row is None:
            row = self._n
            if row == len(self._kf):  # amortised doubling keeps add O(1)
                self._desc = np.concatenate([self._desc, np.zeros_like(self._desc)])
                self._agent_idx = np.concatenate([self._agent_idx, np.zeros_like(self._agent_idx)])
                self._kf = np.concatenate([self._kf, np.zeros_like(self._kf)])
            self._n += 1
            self._rows[key] = row
            self._sorted.pop(agent, None)
        self._desc[row] = q
        self._agent_idx[row] = self._agent_index[agent]
        self._kf[row] = int(kf_id)

    def _register(self, agent: str, group: str) -> None:
        if agent not in self._agent_index:
            self._agent_index[agent] = len(self._agents)
            self._agents.append(agent)
            self._group[agent] = group

    def _normalised(self, descriptor: np.ndarray, where: str) -> np.ndarray:
        q = np.asarray(descriptor, dtype=np.float32).reshape(-1)
        if self.dim is not None and q.size != self.dim:
            raise ValueError(f"{where}: descriptor has length {q.size}, expected {self.dim}")
        norm = float(np.linalg.norm(q))
        if not np.isfinite(norm) or norm == 0.0:
            raise ValueError(f"{where}: descriptor must be finite and non-zero")
        return q / norm

    def _sorted_kfs(self, agent: str) -> np.ndarray:
        if agent not in self._sorted:
            own = self._agent_index.get(agent)
            rows = (np.flatnonzero(self._agent_idx[: self._n] == own) if own is not None
                    else np.zeros(0, np.int64))
            self._sorted[agent] = np.sort(self._kf[rows])
        return self._sorted[agent]

    def _rank(self, agent: str, kf_id: int) -> int:
        """Position of kf_id among the agent's stored keyframe ids (where it would go)."""
        return int(np.searchsorted(self._sorted_kfs(agent), kf_id))


"""An agent's sub-map points as received: columns keyed by point id, with last-writer seq.

A point id can be written by several `SubmapDelta`s; the one with the higher ``seq`` wins even
when the deltas arrive out of order, and a removal leaves a tombstone so that an older add
arriving later does not bring the point back.

Columns are replaced, never written in place, and are read-only arrays: a state snapshot
shares them with the writer thread instead of copying the whole map every time it persists.
"""

from __future__ import annotations

import warnings

import numpy as np
import torch

from cpslam.common.field import NeuralPointMap
from cpslam.protocol.messages import check_points

__all__ = ["PointTable"]

_COLUMNS = ("ids", "anchor", "xyz", "features", "colors", "seq")


class PointTable:
    """Columns ids int64 [N], anchor int32 [N], xyz float32 [N, 3] (anchor camera frame),
    features float16 [N, F], colors uint8 [N, 3], seq int64 [N] (message that wrote it)."""

    def __init__(self) -> None:
        self.ids = np.zeros(0, np.int64)
        self.anchor = np.zeros(0, np.int32)
        self.xyz = np.zeros((0, 3), np.float32)
        self.features = np.zeros((0, 0), np.float16)
        self.colors = np.zeros((0, 3), np.uint8)
        self.seq = np.zeros(0, np.int64)
        self.tombstones: dict[int, int] = {}
        """Removed point id -> seq of the removal."""

    def __setattr__(self, name: str, value: object) -> None:
        if name in _COLUMNS:
            value = np.array(value, copy=None)
            if value.base is not None:  # a view: own the data, or its owner could change it
                value = value.copy()
            value.flags.writeable = False
        object.__setattr__(self, name, value)

    def __len__(self) -> int:
        return int(self.ids.shape[0])

    def upsert(self, ids: np.ndarray, anchor: np.ndarray, xyz: np.ndarray,
               features: np.ndarray, colors: np.ndarray, seq: int) -> None:
        """Insert or replace points, unless a newer write or removal of the same id exists."""
        if len(ids) == 0:
            return
        newer = np.array([self.tombstones.get(int(i), -1) > seq for i in ids], dtype=bool)
        if len(self):
            pos = np.searchsorted(self.ids, ids) if _sorted(self.ids) else None
            if pos is None:
                order = np.argsort(self.ids)
                pos = order[np.minimum(np.searchsorted(self.ids[order], ids), len(self) - 1)]
            else:
                pos = np.minimum(pos, len(self) - 1)
            present = self.ids[pos] == ids
            newer |= present & (self.seq[pos] > seq)
            replace = present & ~newer
            if replace.any():
                self._keep(~np.isin(self.ids, ids[replace]))
        take = ~newer
        if self.features.shape[1] != features.shape[1] and len(self) == 0:
            self.features = np.zeros((0, features.shape[1]), np.float16)
        self.ids = np.concatenate((self.ids, ids[take].astype(np.int64)))
        self.anchor = np.concatenate((self.anchor, anchor[take].astype(np.int32)))
        self.xyz = np.concatenate((self.xyz, xyz[take].astype(np.float32)))
        self.features = np.concatenate((self.features, features[take].astype(np.float16)))
        self.colors = np.concatenate((self.colors, colors[take].astype(np.uint8)))
        self.seq = np.concatenate((self.seq, np.full(int(take.sum()), seq, np.int64)))
        self._sort()

    def update_features(self, ids: np.ndarray, features: np.ndarray, seq: int) -> np.ndarray:
        """Replace the features of held points (ids int64 [U], features [U, F]) unless a newer
        write of them exists; returns the mask [U] of the ids held here."""
        held = np.zeros(len(ids), bool)
        if len(ids) == 0 or len(self) == 0:
            return held
        self._sort()  # a loaded state may not be
        pos = np.minimum(np.searchsorted(self.ids, ids), len(self) - 1)
        held = self.ids[pos] == ids
        write = held & (self.seq[pos] <= seq)
        if write.any():
            rows = pos[write]
            features_now = self.features.copy()
            features_now[rows] = features[write].astype(np.float16)
            seqs = self.seq.copy()
            seqs[rows] = seq
            self.features, self.seq = features_now, seqs
        return held

    def remove(self, ids: np.ndarray, seq: int, tombstone: bool = True) -> int:
        """Remove points by id (older than `seq`); with `tombstone`, remember the removal."""
        if len(ids) == 0:
            return 0
        if tombstone:
            for i in ids.tolist():
                self.tombstones[i] = max(seq, self.tombstones.get(i, -1))
        gone = np.isin(self.ids, ids) & (self.seq <= seq)
        if gone.any():
            self._keep(~gone)
        return int(gone.sum())

    def forget_tombstones(self, cap: int) -> int:
        """Keep at most `cap` tombstones, forgetting the oldest removals; returns how many
        were forgotten. Trims to 90 % of the cap so that a table at its cap is not sorted
        again for every further removal."""
        if len(self.tombstones) <= cap:
            return 0
        keep = max(int(cap * 0.9), 1)
        ids = np.fromiter(self.tombstones.keys(), np.int64, len(self.tombstones))
        seqs = np.fromiter(self.tombstones.values(), np.int64, len(self.tombstones))
        order = np.argsort(seqs, kind="stable")[len(ids) - keep:]
        self.tombstones = dict(zip(ids[order].tolist(), seqs[order].tolist(), strict=True))
        return len(ids) - keep

    def take(self, mask: np.ndarray) -> PointTable:
        """Remove the rows where `mask` is true and return them as a new table."""
        out = PointTable()
        for name in _COLUMNS:
            setattr(out, name, getattr(self, name)[mask].copy())
        self._keep(~mask)
        return out

    def absorb(self, other: PointTable) -> None:
        """Insert another table's rows (each with its own seq)."""
        for s in np.unique(other.seq):
            m = other.seq == s
            self.upsert(other.ids[m], other.anchor[m], other.xyz[m], other.features[m],
                        other.colors[m], int(s))

    def drop_oldest(self, count: int) -> None:
        """Drop the `count` rows written by the oldest messages."""
        order = np.argsort(self.seq, kind="stable")
        mask = np.ones(len(self), dtype=bool)
        mask[order[:count]] = False
        self._keep(mask)

    def to_point_map(self, agent_index: int, kf_poses: dict[int, np.ndarray], feature_dim: int,
                     cell_size: float, device: str | torch.device = "cpu") -> NeuralPointMap:
        """A `NeuralPointMap` holding these points (agent key `agent_index`, ids preserved)
        and the given keyframes ``T_world_kf``; every anchor must be among them."""
        kfs = sorted(kf_poses)
        n = len(self)
        state = {
            "format_version": 1,
            "feature_dim": feature_dim,
            "cell_size": cell_size,
            "default_agent": agent_index,
            "anchor_kf": torch.from_numpy(self.anchor.astype(np.int64)),
            "xyz_local": torch.from_numpy(self.xyz.copy()),
            "features": torch.from_numpy(self.features.astype(np.float32)).reshape(n, feature_dim)
            if n else torch.zeros(0, feature_dim),
            "agent_id": torch.full((n,), agent_index, dtype=torch.int32),
            "point_id": torch.from_numpy(self.ids.copy()),
            "color": torch.from_numpy(self.colors.copy()),
            "kf_keys": torch.tensor([[agent_index, k] for k in kfs], dtype=torch.int64
                                    ).reshape(-1, 2),
            "kf_poses": torch.from_numpy(np.stack([kf_poses[k] for k in kfs]).astype(np.float64))
            if kfs else torch.zeros(0, 4, 4, dtype=torch.float64),
            "next_point_id": torch.tensor([[agent_index, int(self.ids.max()) + 1 if n else 0]],
                                          dtype=torch.int64),
        }
        out = NeuralPointMap(feature_dim, cell_size, agent_index, device)
        out.load_state_dict(state, source=f"sub-map of agent #{agent_index}")
        return out

    def check(self) -> None:
        """Raise ValueError if the columns are inconsistent (used after loading)."""
        check_points(self.ids, self.anchor, self.xyz, self.features, self.colors,
                     np.zeros(0, np.int64))

    def state_dict(self) -> dict:
        """The columns (shared: they are read-only) and the tombstones."""
        # Features stay float16 as in the table (and on the wire): a float32 copy doubled
        # the state the server snapshots and writes (bench/persist.py). States written
        # with float32 features load the same.
        with warnings.catch_warnings():  # torch warns of read-only arrays; a snapshot is read
            warnings.filterwarnings("ignore", "The given NumPy array is not writable")
            out = {name: torch.from_numpy(getattr(self, name)) for name in _COLUMNS}
        out["tombstones"] = torch.tensor(sorted(self.tombstones.items()),
                                         dtype=torch.int64).reshape(-1, 2)
        return out

    @classmethod
    def from_state_dict(cls, state: dict) -> PointTable:
        out = cls()
        out.ids = state["ids"].cpu().numpy().astype(np.int64)
        out.anchor = state["anchor"].cpu().numpy().astype(np.int32)
        out.xyz = state["xyz"].cpu().numpy().astype(np.float32)
        out.features = state["features"].cpu().numpy().astype(np.float16)
        out.colors = state["colors"].cpu().numpy().astype(np.uint8)
        out.seq = state["seq"].cpu().numpy().astype(np.int64)
        out.tombstones = {int(i): int(s) for i, s in state["tombstones"].tolist()}
        out.check()
        return out

    def _keep(self, mask: np.ndarray) -> None:
        for name in _COLUMNS:
            setattr(self, name, getattr(self, name)[mask])

    def _sort(self) -> None:
        if not _sorted(self.ids):
            order = np.argsort(self.ids, kind="stable")
            for name in _COLUMNS:
                setattr(self, name, getattr(self, name)[order])


def _sorted(ids: np.ndarray) -> bool:
    return bool(len(ids) < 2 or (ids[1:] >= ids[:-1]).all())

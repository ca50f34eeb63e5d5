"""What the server holds of one agent (`AgentRecord`, `KeyframeRecord`) and their persisted form.

`record_state` turns a record into plain python data and torch tensors (``torch.save``-able,
loadable with ``weights_only=True``); `record_from_state` reads it back.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from cpslam.common.bounds import CappedCounter
from cpslam.common.field import NeuralPointMap
from cpslam.common.geometry import compose, invert
from cpslam.server.points import PointTable

__all__ = ["AGENT_DROP_REASONS", "AgentRecord", "KeyframeRecord", "record_from_state",
           "record_state"]

AGENT_DROP_REASONS = 32
"""Distinct drop reasons counted per agent (the rest under "other")."""


@dataclass
class KeyframeRecord:
    """One keyframe as the agent reported it, pose mapped into the agent's own world."""

    kf_id: int
    frame_index: int
    stamp: float
    T_own_kf: np.ndarray
    """Camera pose in the agent's own world [4, 4]."""
    descriptor: np.ndarray
    T_prev_kf_kf: np.ndarray | None


@dataclass
class AgentRecord:
    """Everything accepted from one agent."""

    agent_id: str
    index: int
    """Stable small integer (join order); the agent key of the neural point maps."""
    keyframes: dict[int, KeyframeRecord] = field(default_factory=dict)
    frames: dict[int, tuple[int, np.ndarray, float]] = field(default_factory=dict)
    """Frame index -> (keyframe id, T_kf_frame [4, 4], stamp)."""
    points: PointTable = field(default_factory=PointTable)
    """Sub-map points whose anchor keyframe is known."""
    pending_points: PointTable = field(default_factory=PointTable)
    """Points waiting for their anchor keyframe."""
    pending_frames: dict[int, tuple[int, np.ndarray, float]] = field(default_factory=dict)
    decoder: dict[str, np.ndarray] | None = None
    """Latest decoder weights (float32 numpy by name)."""
    decoder_samples: int = 0
    decoder_round: int = 0
    decoder_group: str = ""
    decoder_seq: int = -1
    """Seq of the message `decoder` came from (the base of the agent's next own delta)."""
    alignments: dict[int, np.ndarray] = field(default_factory=lambda: {0: np.eye(4)})
    """Epoch -> T_group_agent the agent was told at that epoch (0: identity)."""
    seq_floor: int = -1
    """Every seq <= seq_floor was handled."""
    seqs_above: set[int] = field(default_factory=set)
    incarnation: int | None = None
    """Incarnation of the agent's first message; others are refused."""
    raised: list[int] = field(default_factory=list)
    """Recent seqs whose handling raised (reported in acks as dropped)."""
    alive: bool = True
    messages: int = 0
    bytes: int = 0
    dropped: CappedCounter = field(default_factory=lambda: CappedCounter(AGENT_DROP_REASONS))
    feature_dim: int | None = None
    kf_seqs: dict[int, int] = field(default_factory=dict)
    """Keyframe id -> seq of its message (this run only; checks that ids increase with seq)."""

    @property
    def kf_ids(self) -> list[int]:
        return sorted(self.keyframes)

    def submap(self, feature_dim: int, cell_size: float) -> NeuralPointMap:
        """The sub-map in the agent's own world as a `NeuralPointMap` (agent key = index)."""
        return self.points.to_point_map(
            self.index, {k: r.T_own_kf for k, r in self.keyframes.items()}, feature_dim, cell_size
        )

    def status(self) -> dict:
        """The record's counts for the server's status query."""
        return {"index": self.index, "alive": self.alive, "keyframes": len(self.keyframes),
                "frames": len(self.frames), "points": len(self.points),
                "pending": len(self.pending_points) + len(self.pending_frames),
                "messages": self.messages, "bytes": self.bytes, "acked_seq": self.seq_floor,
                "dropped": dict(self.dropped)}

    def points_after(self, point_ids: np.ndarray, removed_ids: np.ndarray) -> int:
        """Points held (waiting ones included) once a delta with these ids is applied."""
        tables = (self.points, self.pending_points)
        new = np.ones(point_ids.shape[0], bool)
        gone = 0
        for table in tables:
            new &= ~np.isin(point_ids, table.ids)
            gone += int(np.isin(removed_ids, table.ids).sum())
        return sum(len(t) for t in tables) + int(new.sum()) - gone

    def odometry(self) -> dict[int, np.ndarray]:
        """Keyframe poses in the own world chained from the relative poses T_prev_kf_kf.

        The chain starts at the first keyframe's reported pose; where a link is missing (a
        first keyframe or a gap), the reported poses give it. Corrections the agent applied
        from server updates therefore do not leak into the odometry.
        """
        out: dict[int, np.ndarray] = {}
        prev: KeyframeRecord | None = None
        for kf in self.kf_ids:
            rec = self.keyframes[kf]
            if prev is None:
                out[kf] = rec.T_own_kf.copy()
            else:
                rel = rec.T_prev_kf_kf
                if rel is None:
                    rel = compose(invert(prev.T_own_kf), rec.T_own_kf)
                out[kf] = compose(out[prev.kf_id], rel)
            prev = rec
        return out


def record_state(rec: AgentRecord) -> dict:
    """Plain data (python, torch tensors) of one record; see `record_from_state`."""
    return {
        "agent_id": rec.agent_id, "index": rec.index,
        "keyframes": _keyframes_state(list(rec.keyframes.values())),
        "frames": _frames_state(rec.frames),
        "pending_frames": _frames_state(rec.pending_frames),
        "points": rec.points.state_dict(),
        "pending_points": rec.pending_points.state_dict(),
        "decoder": None if rec.decoder is None else {k: _t(v) for k, v in rec.decoder.items()},
        "decoder_samples": rec.decoder_samples, "decoder_round": rec.decoder_round,
        "decoder_group": rec.decoder_group,
        "decoder_seq": rec.decoder_seq,
        "alignments": {int(e): _t(T) for e, T in rec.alignments.items()},
        "seq_floor": rec.seq_floor, "seqs_above": sorted(rec.seqs_above),
        "alive": rec.alive, "messages": rec.messages, "bytes": rec.bytes,
        "incarnation": rec.incarnation, "raised": list(rec.raised),
        "dropped": dict(rec.dropped),
    }


def record_from_state(a: dict) -> AgentRecord:
    """The record a `record_state` describes."""
    rec = AgentRecord(a["agent_id"], int(a["index"]))
    for k in _keyframes_load(a["keyframes"]):
        rec.keyframes[k.kf_id] = k
    rec.frames = _frames_load(a["frames"])
    rec.pending_frames = _frames_load(a["pending_frames"])
    rec.points = PointTable.from_state_dict(a["points"])
    rec.pending_points = PointTable.from_state_dict(a["pending_points"])
    rec.decoder = None if a["decoder"] is None else {k: _n(v) for k, v in a["decoder"].items()}
    rec.decoder_samples = int(a["decoder_samples"])
    rec.decoder_round = int(a["decoder_round"])
    rec.decoder_group = str(a["decoder_group"])
    rec.decoder_seq = int(a["decoder_seq"])
    rec.alignments = {int(e): _n(T) for e, T in a["alignments"].items()}
    rec.seq_floor, rec.seqs_above = int(a["seq_floor"]), set(a["seqs_above"])
    rec.alive, rec.messages, rec.bytes = bool(a["alive"]), int(a["messages"]), int(a["bytes"])
    for reason, count in a["dropped"].items():
        rec.dropped.add(reason, count)
    inc = a.get("incarnation")
    rec.incarnation = None if inc is None else int(inc)
    rec.raised = [int(x) for x in a.get("raised", [])]
    return rec


def _t(a: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(a).copy())


def _n(t: torch.Tensor) -> np.ndarray:
    return t.cpu().numpy().copy()


def _keyframes_state(kfs: list[KeyframeRecord]) -> dict:
    # Columns, not a dict per keyframe: a snapshot of thousands of keyframes is a few stacks
    # instead of thousands of small tensors for the poll loop to make and copy.
    eye = np.eye(4)
    return {
        "kf_id": torch.tensor([k.kf_id for k in kfs], dtype=torch.int64),
        "frame_index": torch.tensor([k.frame_index for k in kfs], dtype=torch.int64),
        "stamp": torch.tensor([k.stamp for k in kfs], dtype=torch.float64),
        "T_own_kf": _stack([k.T_own_kf for k in kfs], (4, 4), np.float64),
        "descriptor": _stack([k.descriptor for k in kfs], (0,), np.float32),
        "T_prev_kf_kf": _stack([eye if k.T_prev_kf_kf is None else k.T_prev_kf_kf
                                for k in kfs], (4, 4), np.float64),
        "has_prev": torch.tensor([k.T_prev_kf_kf is not None for k in kfs], dtype=torch.bool),
    }


def _keyframes_load(state: dict | list) -> list[KeyframeRecord]:
    if isinstance(state, list):  # a state written before keyframes were stored as columns
        return [KeyframeRecord(int(k["kf_id"]), int(k["frame_index"]), float(k["stamp"]),
                               _n(k["T_own_kf"]), _n(k["descriptor"]),
                               None if k["T_prev_kf_kf"] is None else _n(k["T_prev_kf_kf"]))
                for k in state]
    T, D, prev = _n(state["T_own_kf"]), _n(state["descriptor"]), _n(state["T_prev_kf_kf"])
    return [KeyframeRecord(int(kf), int(fi), float(st), T[i], D[i],
                           prev[i] if has else None)
            for i, (kf, fi, st, has) in enumerate(zip(
                state["kf_id"].tolist(), state["frame_index"].tolist(),
                state["stamp"].tolist(), state["has_prev"].tolist(), strict=True))]


def _stack(arrays: list[np.ndarray], empty: tuple[int, ...], dtype: type) -> torch.Tensor:
    if not arrays:
        return torch.from_numpy(np.zeros((0, *empty), dtype))
    return torch.from_numpy(np.stack(arrays).astype(dtype, copy=False))


def _frames_state(frames: dict[int, tuple[int, np.ndarray, float]]) -> dict:
    order = sorted(frames)
    return {
        "index": torch.tensor(order, dtype=torch.int64),
        "kf": torch.tensor([frames[f][0] for f in order], dtype=torch.int64),
        "T_kf_frame": _stack([frames[f][1] for f in order], (4, 4), np.float64),
        "stamp": torch.tensor([frames[f][2] for f in order], dtype=torch.float64),
    }


def _frames_load(state: dict) -> dict[int, tuple[int, np.ndarray, float]]:
    T = state["T_kf_frame"].cpu().numpy()
    return {
        int(f): (int(k), T[i].copy(), float(s))
        for i, (f, k, s) in enumerate(zip(state["index"].tolist(), state["kf"].tolist(),
                                          state["stamp"].tolist(), strict=True))
    }

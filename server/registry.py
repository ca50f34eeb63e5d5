"""What the server knows of each agent: keyframes, frame poses, sub-map, decoder weights.

`Registry.handle` takes one decoded agent -> server message and applies it. It never raises
on bad content: a message that contradicts what the registry holds is logged and dropped with
a reason (counted in `Registry.dropped`). Messages are idempotent by their ``seq``: a replay
is ignored but still acknowledged, so an agent that resends after a lost `Ack` converges.
Points and frames anchored to a keyframe that has not arrived yet wait in a bounded buffer
until it does (messages of one agent may arrive out of order).

Poses are kept in the agent's *own* world (its first camera): a keyframe reported after the
agent applied a server alignment (``world_epoch`` > 0) is mapped back with the inverse of the
alignment of that epoch, which the back end records with `Registry.set_alignment`.
"""

from __future__ import annotations

import logging
from collections import Counter
from dataclasses import dataclass, field

import numpy as np
import torch

from cpslam.common.field import NeuralPointMap
from cpslam.common.geometry import compose, invert
from cpslam.protocol import Ack, DecoderWeights, FramePoses, KeyframeMsg, Message, SubmapDelta
from cpslam.server.bases import DecoderBases, apply_delta
from cpslam.server.points import PointTable

__all__ = ["AgentRecord", "KeyframeRecord", "Registry"]

logger = logging.getLogger(__name__)

AGENT_MESSAGES = (KeyframeMsg, SubmapDelta, DecoderWeights, FramePoses)


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
    alive: bool = True
    messages: int = 0
    bytes: int = 0
    dropped: Counter = field(default_factory=Counter)
    feature_dim: int | None = None

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


class Registry:
    """Agents by id; applies their messages.

    Args:
        feature_dim: expected width F of point features (others are dropped).
        decoder_shapes: expected decoder tensor names and shapes (None: not checked).
        first_seq: the first ``seq`` agents send (their counter starts there).
        max_pending_points: most points an agent may have waiting for their keyframe; the
            oldest beyond it are dropped.
    """

    def __init__(
        self,
        feature_dim: int,
        decoder_shapes: dict[str, tuple[int, ...]] | None = None,
        first_seq: int = 0,
        max_pending_points: int = 1_000_000,
    ) -> None:
        self.feature_dim = int(feature_dim)
        self.decoder_shapes = decoder_shapes
        self.first_seq = int(first_seq)
        self.max_pending_points = int(max_pending_points)
        self.agents: dict[str, AgentRecord] = {}
        self.new_keyframes: list[tuple[str, int]] = []
        """(agent, kf) accepted since the back end last took them."""
        self.new_decoders: list[tuple[str, DecoderWeights]] = []
        self.decoder_bases = DecoderBases()
        """Published group decoders that agents' decoder deltas refer to."""
        self.dropped: Counter = Counter()
        """Reason -> count of dropped messages (or parts), over all agents."""

    # ------------------------------------------------------------------------------- public

    def agent(self, agent_id: str) -> AgentRecord:
        """The record of an agent, created (next index) on first contact."""
        rec = self.agents.get(agent_id)
        if rec is None:
            rec = AgentRecord(agent_id, len(self.agents), seq_floor=self.first_seq - 1)
            self.agents[agent_id] = rec
            # The join itself is logged once, by the node that sees the agent's liveliness.
            logger.debug("agent %s registered (index %d)", agent_id, rec.index)
        return rec

    def handle(self, msg: Message, nbytes: int = 0) -> list[Ack]:
        """Apply one agent message; returns the `Ack` to send (empty if none can be given)."""
        if not isinstance(msg, AGENT_MESSAGES):
            self._drop(None, f"unexpected message type {type(msg).__name__}")
            return []
        rec = self.agent(msg.agent_id)
        rec.messages += 1
        rec.bytes += int(nbytes)
        rec.alive = True
        seq = int(msg.seq)
        if seq <= rec.seq_floor or seq in rec.seqs_above:
            logger.debug("agent %s: seq %d already handled", rec.agent_id, seq)
            return self._ack(rec)
        reason = self._apply(rec, msg)
        if reason:
            self._drop(rec, reason, f"{msg.type} seq {seq}")
        # A dropped message is handled too: the agent must not resend it forever.
        rec.seqs_above.add(seq)
        while rec.seq_floor + 1 in rec.seqs_above:
            rec.seq_floor += 1
            rec.seqs_above.discard(rec.seq_floor)
        return self._ack(rec)

    def set_alignment(self, agent_id: str, epoch: int, T_group_agent: np.ndarray) -> None:
        """Record the alignment the agent is told with `epoch` (to read its later poses)."""
        self.agent(agent_id).alignments[int(epoch)] = np.asarray(T_group_agent, np.float64).copy()

    def take_new_keyframes(self) -> list[tuple[str, int]]:
        out, self.new_keyframes = self.new_keyframes, []
        return out

    def take_new_decoders(self) -> list[tuple[str, DecoderWeights]]:
        out, self.new_decoders = self.new_decoders, []
        return out

    def drop_unresolved(self) -> int:
        """Drop every point and frame still waiting for a keyframe (at finalisation)."""
        total = 0
        for rec in self.agents.values():
            n = len(rec.pending_points) + len(rec.pending_frames)
            if n:
                self._drop(rec, "anchor keyframe never arrived", f"{n} points/frames", count=n)
                rec.pending_points = PointTable()
                rec.pending_frames = {}
                total += n
        return total

    # ---------------------------------------------------------------------------- appliers

    def _apply(self, rec: AgentRecord, msg: Message) -> str:
        if isinstance(msg, KeyframeMsg):
            return self._keyframe(rec, msg)
        if isinstance(msg, SubmapDelta):
            return self._submap(rec, msg)
        if isinstance(msg, FramePoses):
            return self._frames(rec, msg)
        return self._decoder(rec, msg)

    def _keyframe(self, rec: AgentRecord, msg: KeyframeMsg) -> str:
        kf = int(msg.kf_id)
        if kf in rec.keyframes:
            return f"keyframe {kf} already known (a different seq)"
        align = rec.alignments.get(int(msg.world_epoch))
        if align is None:
            return f"world_epoch {msg.world_epoch} was never sent to this agent"
        dims = {r.descriptor.shape[0] for r in self.all_keyframes()}
        if dims and msg.descriptor.shape[0] not in dims:
            return f"descriptor length {msg.descriptor.shape[0]}, others have {sorted(dims)}"
        rec.keyframes[kf] = KeyframeRecord(
            kf_id=kf,
            frame_index=int(msg.frame_index),
            stamp=float(msg.stamp),
            T_own_kf=compose(invert(align), msg.T_world_cam),
            descriptor=np.asarray(msg.descriptor, np.float32),
            T_prev_kf_kf=None if msg.T_prev_kf_kf is None else msg.T_prev_kf_kf.copy(),
        )
        self.new_keyframes.append((rec.agent_id, kf))
        self._resolve(rec)
        return ""

    def _submap(self, rec: AgentRecord, msg: SubmapDelta) -> str:
        f = msg.feature_dim
        if msg.point_ids.size and f != self.feature_dim:
            return f"features have width {f}, the map uses {self.feature_dim}"
        seq = int(msg.seq)
        # Removal and replacement touch both tables: a newer message supersedes a waiting one.
        for table in (rec.points, rec.pending_points):
            table.remove(msg.removed_ids, seq)
            table.remove(msg.point_ids, seq, tombstone=False)
        known = np.isin(msg.anchor_kf_ids, np.fromiter(rec.keyframes, np.int64, len(rec.keyframes)))
        columns = (msg.point_ids, msg.anchor_kf_ids, msg.xyz_local,
                   msg.feature_values().astype(np.float16), msg.colors)
        rec.points.upsert(*(c[known] for c in columns), seq)
        rec.pending_points.upsert(*(c[~known] for c in columns), seq)
        overflow = len(rec.pending_points) - self.max_pending_points
        if overflow > 0:
            rec.pending_points.drop_oldest(overflow)
            self._drop(rec, "too many points waiting for keyframes", count=overflow)
        return ""

    def _frames(self, rec: AgentRecord, msg: FramePoses) -> str:
        for i, frame in enumerate(msg.frame_indices.tolist()):
            entry = (int(msg.kf_ids[i]), msg.T_kf_frame[i].copy(), float(msg.stamps[i]))
            target = rec.frames if entry[0] in rec.keyframes else rec.pending_frames
            target[int(frame)] = entry
        return ""

    def _decoder(self, rec: AgentRecord, msg: DecoderWeights) -> str:
        tensors = msg.values()
        if msg.base_round is not None:
            tensors = self.decoder_bases.apply(msg.group_id, msg.base_round, tensors)
        elif msg.base_seq is not None:
            if rec.decoder is None or rec.decoder_seq != msg.base_seq:
                return (f"decoder delta against the agent's seq {msg.base_seq}, the server "
                        f"holds its weights of seq {rec.decoder_seq}")
            tensors = apply_delta(rec.decoder, tensors, f"seq {msg.base_seq}")
        if isinstance(tensors, str):
            return tensors
        if self.decoder_shapes is not None:
            names = set(tensors)
            if names != set(self.decoder_shapes):
                missing = sorted(set(self.decoder_shapes) - names)[:3]
                extra = sorted(names - set(self.decoder_shapes))[:3]
                return f"decoder tensors differ (missing {missing}, unknown {extra})"
            for name, value in tensors.items():
                if tuple(value.shape) != tuple(self.decoder_shapes[name]):
                    return (f"decoder tensor {name} has shape {list(value.shape)}, expected "
                            f"{list(self.decoder_shapes[name])}")
        rec.decoder = tensors
        rec.decoder_samples = int(msg.n_samples)
        rec.decoder_round = int(msg.round)
        rec.decoder_group = str(msg.group_id)
        rec.decoder_seq = int(msg.seq)
        self.new_decoders.append((rec.agent_id, msg))
        return ""

    # ----------------------------------------------------------------------------- helpers

    def all_keyframes(self) -> list[KeyframeRecord]:
        return [k for rec in self.agents.values() for k in rec.keyframes.values()]

    def _resolve(self, rec: AgentRecord) -> None:
        """Move waiting points and frames whose keyframe is now known."""
        kfs = np.fromiter(rec.keyframes, np.int64, len(rec.keyframes))
        if len(rec.pending_points):
            ready = np.isin(rec.pending_points.anchor, kfs)
            if ready.any():
                rec.points.absorb(rec.pending_points.take(ready))
        for frame in [f for f, e in rec.pending_frames.items() if e[0] in rec.keyframes]:
            rec.frames[frame] = rec.pending_frames.pop(frame)

    def _ack(self, rec: AgentRecord) -> list[Ack]:
        return [Ack(agent_id=rec.agent_id, seq=rec.seq_floor)] if rec.seq_floor >= 0 else []

    def _drop(self, rec: AgentRecord | None, reason: str, what: str = "", count: int = 1) -> None:
        self.dropped[reason] += count
        if rec is not None:
            rec.dropped[reason] += count
        logger.warning("dropped %s from %s: %s", what or "message",
                       rec.agent_id if rec else "?", reason)

    # ----------------------------------------------------------------------------- state

    def state_dict(self) -> dict:
        """Plain data (python, torch tensors) of every record; see `load_state_dict`."""
        agents = []
        for rec in self.agents.values():
            agents.append({
                "agent_id": rec.agent_id, "index": rec.index,
                "keyframes": [
                    {"kf_id": k.kf_id, "frame_index": k.frame_index, "stamp": k.stamp,
                     "T_own_kf": _t(k.T_own_kf), "descriptor": _t(k.descriptor),
                     "T_prev_kf_kf": None if k.T_prev_kf_kf is None else _t(k.T_prev_kf_kf)}
                    for k in rec.keyframes.values()
                ],
                "frames": _frames_state(rec.frames),
                "pending_frames": _frames_state(rec.pending_frames),
                "points": rec.points.state_dict(),
                "pending_points": rec.pending_points.state_dict(),
                "decoder": None if rec.decoder is None else {k: _t(v) for k, v in
                                                               rec.decoder.items()},
                "decoder_samples": rec.decoder_samples, "decoder_round": rec.decoder_round,
                "decoder_group": rec.decoder_group,
                "alignments": {int(e): _t(T) for e, T in rec.alignments.items()},
                "seq_floor": rec.seq_floor, "seqs_above": sorted(rec.seqs_above),
                "alive": rec.alive, "messages": rec.messages, "bytes": rec.bytes,
                "dropped": dict(rec.dropped),
            })
        return {"agents": agents, "dropped": dict(self.dropped),
                "new_keyframes": [list(x) for x in self.new_keyframes]}

    def load_state_dict(self, state: dict) -> None:
        """Replace the content by a `state_dict` (pending decoder submissions are not kept)."""
        self.agents = {}
        for a in state["agents"]:
            rec = AgentRecord(a["agent_id"], int(a["index"]))
            for k in a["keyframes"]:
                rec.keyframes[int(k["kf_id"])] = KeyframeRecord(
                    int(k["kf_id"]), int(k["frame_index"]), float(k["stamp"]),
                    _n(k["T_own_kf"]), _n(k["descriptor"]),
                    None if k["T_prev_kf_kf"] is None else _n(k["T_prev_kf_kf"]))
            rec.frames = _frames_load(a["frames"])
            rec.pending_frames = _frames_load(a["pending_frames"])
            rec.points = PointTable.from_state_dict(a["points"])
            rec.pending_points = PointTable.from_state_dict(a["pending_points"])
            rec.decoder = None if a["decoder"] is None else {
                k: _n(v) for k, v in a["decoder"].items()}
            rec.decoder_samples = int(a["decoder_samples"])
            rec.decoder_round = int(a["decoder_round"])
            rec.decoder_group = str(a["decoder_group"])
            rec.alignments = {int(e): _n(T) for e, T in a["alignments"].items()}
            rec.seq_floor, rec.seqs_above = int(a["seq_floor"]), set(a["seqs_above"])
            rec.alive, rec.messages, rec.bytes = bool(a["alive"]), int(a["messages"]), int(
                a["bytes"])
            rec.dropped = Counter(a["dropped"])
            self.agents[rec.agent_id] = rec
        self.dropped = Counter(state["dropped"])
        self.new_keyframes = [(str(a), int(k)) for a, k in state["new_keyframes"]]
        self.new_decoders = []


def _t(a: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(a).copy())


def _n(t: torch.Tensor) -> np.ndarray:
    return t.cpu().numpy().copy()


def _frames_state(frames: dict[int, tuple[int, np.ndarray, float]]) -> dict:
    order = sorted(frames)
    return {
        "index": torch.tensor(order, dtype=torch.int64),
        "kf": torch.tensor([frames[f][0] for f in order], dtype=torch.int64),
        "T_kf_frame": _t(np.stack([frames[f][1] for f in order])) if order
        else torch.zeros(0, 4, 4, dtype=torch.float64),
        "stamp": torch.tensor([frames[f][2] for f in order], dtype=torch.float64),
    }


def _frames_load(state: dict) -> dict[int, tuple[int, np.ndarray, float]]:
    T = state["T_kf_frame"].cpu().numpy()
    return {
        int(f): (int(k), T[i].copy(), float(s))
        for i, (f, k, s) in enumerate(zip(state["index"].tolist(), state["kf"].tolist(),
                                          state["stamp"].tolist(), strict=True))
    }

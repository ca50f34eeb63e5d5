"""What the server knows of each agent: keyframes, frame poses, sub-map, decoder weights.

`Registry.handle` takes one decoded agent -> server message and applies it. It never raises
on bad content: a message that contradicts what the registry holds is logged and dropped with
a reason (counted in `Registry.dropped`); one whose handling raises is dropped and counted
too, and its seq is reported in the ack's ``dropped`` list, so it is never left hanging.
Messages are idempotent by their ``seq``: a replay is ignored but still acknowledged, so an
agent that resends after a lost `Ack` converges; the ack carries the floor and the handled
ranges above it (`cpslam.server.acks`), so one lost message stalls nothing. A seq more than
``max_seq_ahead`` above the floor is dropped unacknowledged (it would pin memory).
An agent id belongs to the incarnation of the first message of its stream (``seq`` 0; a later
message of an unknown agent is dropped unacknowledged until that one came): another
incarnation is refused (`Refusal`) and none of its data is taken (see docs/protocol.md).
Points and frames anchored to a keyframe that has not arrived yet wait in a bounded buffer
until it does (messages of one agent may arrive out of order).

Everything a peer keys or sizes is capped (the ``limits`` config section, unpacked by
`registry_args`, which lives in `cpslam.server.settings`): agent ids, messages ahead of the
acknowledged seq, waiting points and frames, removed ids per delta and tombstones in total,
drop reasons counted. Content is checked against the server's own config, never against what
the first agent sent: descriptor length, point feature width, decoder tensor names and shapes;
and for plausibility: finite poses with |t| below a bound, keyframe ids increasing with seq,
sample counts below a bound.

Poses are kept in the agent's *own* world (its first camera): a keyframe reported after the
agent applied a server alignment (``world_epoch`` > 0) is mapped back with the inverse of the
alignment of that epoch, which the back end records with `Registry.set_alignment`.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

import numpy as np

from cpslam.common.bounds import CappedCounter, LogThrottle
from cpslam.common.geometry import compose, invert
from cpslam.protocol import (
    Ack,
    DecoderWeights,
    FramePoses,
    KeyframeMsg,
    Message,
    Refusal,
    SubmapDelta,
)
from cpslam.server import acks
from cpslam.server.bases import DecoderBases, submitted_weights
from cpslam.server.plausibility import implausible
from cpslam.server.points import PointTable
from cpslam.server.records import AgentRecord, KeyframeRecord, record_from_state, record_state
from cpslam.server.settings import registry_args

__all__ = ["Registry", "registry_args"]

logger = logging.getLogger(__name__)

AGENT_MESSAGES = (KeyframeMsg, SubmapDelta, DecoderWeights, FramePoses)


class Registry:
    """Agents by id; applies their messages.

    Args:
        feature_dim: expected width F of point features (others are dropped).
        decoder_shapes: expected decoder tensor names and shapes (None: not checked).
        first_seq: the first ``seq`` agents send (their counter starts there).
        max_pending_points: most points an agent may have waiting for their keyframe; the
            oldest beyond it are dropped.
        descriptor_dim: expected keyframe descriptor length (None: not checked).
        max_agents: agent ids accepted; messages of further ids are dropped (None: no cap).
        max_pending_frames: most frame poses an agent may have waiting for their keyframe;
            the oldest beyond it are dropped.
        max_seq_ahead: a message whose seq is this far beyond the acknowledged one is dropped
            without an ack, so the set of out-of-order seqs stays bounded (None: no cap).
        max_removed_per_message: a delta with more removed ids is refused whole, before any
            table is touched (None: no cap).
        max_tombstones: removals remembered per agent; the oldest beyond it are forgotten
            (an older add of such a point arriving after that would bring it back).
        max_translation_m: largest |t| (m) of a reported pose (None: only finiteness).
        max_federated_samples: largest sample count a decoder submission may claim.
        max_counter_keys: distinct drop reasons counted (the rest under "other").
        max_keyframes_per_agent: keyframes kept per agent; further ones are dropped (None: no
            cap).
        max_points_per_agent: points kept per agent (waiting ones included); a delta that
            would go beyond it is dropped whole (None: no cap).
        now: monotonic clock of the throttled log lines.
    """

    def __init__(
        self,
        feature_dim: int,
        decoder_shapes: dict[str, tuple[int, ...]] | None = None,
        first_seq: int = 0,
        max_pending_points: int = 1_000_000,
        *,
        descriptor_dim: int | None = None,
        max_agents: int | None = None,
        max_pending_frames: int = 100_000,
        max_seq_ahead: int | None = 65_536,
        max_removed_per_message: int | None = None,
        max_tombstones: int | None = None,
        max_translation_m: float | None = None,
        max_federated_samples: int | None = None,
        max_counter_keys: int = 1024,
        max_keyframes_per_agent: int | None = None,
        max_points_per_agent: int | None = None,
        now: Callable[[], float] = time.monotonic,
    ) -> None:
        self.max_keyframes_per_agent = max_keyframes_per_agent
        self.max_points_per_agent = max_points_per_agent
        self.feature_dim = int(feature_dim)
        self.decoder_shapes = decoder_shapes
        self.first_seq = int(first_seq)
        self.max_pending_points = int(max_pending_points)
        self.descriptor_dim = descriptor_dim
        self.max_agents = max_agents
        self.max_pending_frames = int(max_pending_frames)
        self.max_seq_ahead = max_seq_ahead
        self.max_removed_per_message = max_removed_per_message
        self.max_tombstones = max_tombstones
        self.max_translation_m = max_translation_m
        self.max_federated_samples = max_federated_samples
        self.max_counter_keys = int(max_counter_keys)
        self.agents: dict[str, AgentRecord] = {}
        self.new_keyframes: list[tuple[str, int]] = []
        """(agent, kf) accepted since the back end last took them."""
        self.new_decoders: list[tuple[str, DecoderWeights]] = []
        self.decoder_bases = DecoderBases()
        """Published group decoders that agents' decoder deltas refer to."""
        self.dropped = CappedCounter(self.max_counter_keys)
        """Reason -> count of dropped messages (or parts), over all agents."""
        self.refused_agents = 0
        """Messages dropped because their agent id was beyond `max_agents`."""
        self._log = LogThrottle(now=now)

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

    def handle(self, msg: Message, nbytes: int = 0) -> list[Ack | Refusal]:
        """Apply one agent message; returns the `Ack` to send (empty if none can be given), or
        a `Refusal` for a message of another incarnation than the agent id's."""
        if not isinstance(msg, AGENT_MESSAGES):
            self._drop(None, f"unexpected message type {type(msg).__name__}")
            return []
        if (msg.agent_id not in self.agents and self.max_agents is not None
                and len(self.agents) >= self.max_agents):
            self.refused_agents += 1
            self.dropped.add("agent cap reached")
            held = self._log.allow("agent cap")
            if held is not None:
                logger.warning("dropped %s from new agent %s: already %d agents (limits."
                               "max_agents); %d more refused since the last line", msg.type,
                               msg.agent_id, len(self.agents), held)
            return []
        known = self.agents.get(msg.agent_id)
        if (known is None or known.incarnation is None) and int(msg.seq) != self.first_seq:
            # An id is bound by the first message of a stream: a later one is what an agent
            # sent to a server before this one (lost with its state); taking it would bind the
            # id to a stream the agent is about to start over. Unacknowledged: a genuine agent
            # resends it after its stream's first message.
            self._drop(known, "stream start not seen", f"{msg.type} seq {msg.seq} of agent "
                       f"{msg.agent_id}")
            return []
        rec = self.agent(msg.agent_id)
        incarnation = int(msg.incarnation)
        if rec.incarnation is None:
            rec.incarnation = incarnation
        elif incarnation != rec.incarnation:
            self._drop(rec, "another incarnation", f"{msg.type} seq {msg.seq}")
            return [Refusal(
                agent_id=rec.agent_id, incarnation=incarnation,
                reason=f"agent id {rec.agent_id} already streams as incarnation "
                       f"{rec.incarnation} into this session's world; restart with --resume "
                       "to continue it, or use a new agent id")]
        if self.max_seq_ahead is not None and int(msg.seq) - rec.seq_floor > self.max_seq_ahead:
            # Not acknowledged and not held (it would pin memory); a genuine agent resends it
            # once the gap has closed.
            self._drop(rec, "seq too far ahead", f"{msg.type} seq {msg.seq} (acknowledged "
                       f"{rec.seq_floor}, limits.max_seq_ahead {self.max_seq_ahead})")
            return []
        rec.messages += 1
        rec.bytes += int(nbytes)
        rec.alive = True
        seq = int(msg.seq)
        if acks.handled(rec, seq):
            logger.debug("agent %s: seq %d already handled", rec.agent_id, seq)
            return acks.ack(rec)
        try:
            reason = self._apply(rec, msg)
        except Exception:  # noqa: BLE001 - a bad message must never stop the server
            logger.exception("agent %s: handling %s seq %d raised", rec.agent_id, msg.type, seq)
            reason = "handling raised"
            acks.mark_raised(rec, seq)
        if reason:
            self._drop(rec, reason, f"{msg.type} seq {seq}")
        acks.mark_handled(rec, seq)  # a dropped message too (see `acks`)
        return acks.ack(rec)

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
        reason = implausible(msg, rec.kf_seqs, self.max_translation_m)
        if reason:
            return reason
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
        cap = self.max_keyframes_per_agent
        if cap is not None and len(rec.keyframes) >= cap:
            return f"already {cap} keyframes of this agent (limits.max_keyframes_per_agent)"
        align = rec.alignments.get(int(msg.world_epoch))
        if align is None:
            return f"world_epoch {msg.world_epoch} was never sent to this agent"
        got = msg.descriptor.shape[0]
        if self.descriptor_dim is not None and got != self.descriptor_dim:
            return (f"field descriptor has length {got}, expected {self.descriptor_dim} "
                    "(place_recognition / limits.descriptor_dim)")
        rec.keyframes[kf] = KeyframeRecord(
            kf_id=kf,
            frame_index=int(msg.frame_index),
            stamp=float(msg.stamp),
            T_own_kf=compose(invert(align), msg.T_world_cam),
            descriptor=msg.unit_descriptor(),
            T_prev_kf_kf=None if msg.T_prev_kf_kf is None else msg.T_prev_kf_kf.copy(),
        )
        rec.kf_seqs[kf] = int(msg.seq)
        self.new_keyframes.append((rec.agent_id, kf))
        self._resolve(rec)
        return ""

    def _submap(self, rec: AgentRecord, msg: SubmapDelta) -> str:
        f = msg.feature_dim
        if (msg.point_ids.size or msg.feature_ids.size) and f != self.feature_dim:
            return f"field features has width {f}, expected {self.feature_dim} (field config)"
        m = msg.removed_ids.size
        if self.max_removed_per_message is not None and m > self.max_removed_per_message:
            return (f"field removed_ids has {m} ids, expected at most "
                    f"{self.max_removed_per_message} (limits.max_removed_per_message)")
        cap = self.max_points_per_agent
        held = len(rec.points) + len(rec.pending_points)
        # The exact count (a search over the tables) only when the delta could pass the cap.
        if cap is not None and held + msg.point_ids.size > cap and (
                after := rec.points_after(msg.point_ids, msg.removed_ids)) > cap:
            return (f"sub-map delta would hold {after} points of this agent, expected at most "
                    f"{cap} (limits.max_points_per_agent)")
        seq = int(msg.seq)
        # Removal and replacement touch both tables: a newer message supersedes a waiting one.
        for table in (rec.points, rec.pending_points):
            table.remove(msg.removed_ids, seq)
            table.remove(msg.point_ids, seq, tombstone=False)
        if self.max_tombstones is not None:
            forgotten = rec.points.forget_tombstones(self.max_tombstones)
            forgotten += rec.pending_points.forget_tombstones(self.max_tombstones)
            if forgotten:
                self._drop(rec, "tombstones forgotten (limits.max_tombstones)", count=forgotten)
        known = np.isin(msg.anchor_kf_ids, np.fromiter(rec.keyframes, np.int64, len(rec.keyframes)))
        columns = (msg.point_ids, msg.anchor_kf_ids, msg.xyz_local,
                   msg.feature_values().astype(np.float16), msg.colors)
        rec.points.upsert(*(c[known] for c in columns), seq)
        rec.pending_points.upsert(*(c[~known] for c in columns), seq)
        if msg.feature_ids.size:
            values = msg.updated_feature_values()
            held = rec.points.update_features(msg.feature_ids, values, seq)
            held |= rec.pending_points.update_features(msg.feature_ids, values, seq)
            if not held.all():  # removed since, or never taken (a cap)
                self._drop(rec, "features of points not held", count=int((~held).sum()))
        overflow = len(rec.pending_points) - self.max_pending_points
        if overflow > 0:
            rec.pending_points.drop_oldest(overflow)
            self._drop(rec, "too many points waiting for keyframes", count=overflow)
        return ""

    def _frames(self, rec: AgentRecord, msg: FramePoses) -> str:
        for i, frame in enumerate(msg.frame_indices.tolist()):
            entry = (int(msg.kf_ids[i]), msg.T_kf_frame[i].copy(), float(msg.stamps[i]))
            target = rec.frames if entry[0] in rec.keyframes else rec.pending_frames
            target.pop(int(frame), None)  # re-inserted last: the dict's order is arrival
            target[int(frame)] = entry
        overflow = len(rec.pending_frames) - self.max_pending_frames
        if overflow > 0:
            for frame in list(rec.pending_frames)[:overflow]:
                del rec.pending_frames[frame]
            self._drop(rec, "too many frames waiting for keyframes", count=overflow)
        return ""

    def _decoder(self, rec: AgentRecord, msg: DecoderWeights) -> str:
        tensors = submitted_weights(msg, rec.decoder, rec.decoder_seq, self.decoder_bases,
                                    self.decoder_shapes, self.max_federated_samples)
        if isinstance(tensors, str):
            return tensors
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

    def _drop(self, rec: AgentRecord | None, reason: str, what: str = "", count: int = 1) -> None:
        self.dropped.add(reason, count)
        if rec is not None:
            rec.dropped.add(reason, count)
        agent = rec.agent_id if rec else "?"
        held = self._log.allow(f"drop {agent}")
        if held is not None:
            logger.warning("dropped %s from %s: %s%s", what or "message", agent, reason,
                           f" ({held} more drops of this agent not logged)" if held else "")

    # ----------------------------------------------------------------------------- state

    def state_dict(self) -> dict:
        """Plain data (python, torch tensors) of every record; see `load_state_dict`."""
        return {"agents": [record_state(rec) for rec in self.agents.values()],
                "dropped": dict(self.dropped),
                "new_keyframes": [list(x) for x in self.new_keyframes]}

    def load_state_dict(self, state: dict) -> None:
        """Replace the content by a `state_dict` (pending decoder submissions are not kept)."""
        self.agents = {}
        for a in state["agents"]:
            rec = record_from_state(a)
            self.agents[rec.agent_id] = rec
        self.dropped = CappedCounter(self.max_counter_keys)
        for reason, count in state["dropped"].items():
            self.dropped.add(reason, count)
        self.new_keyframes = [(str(a), int(k)) for a, k in state["new_keyframes"]]
        self.new_decoders = []


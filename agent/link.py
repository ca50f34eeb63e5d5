"""The agent's side of the collaboration, independent of the transport.

`AgentLink` sits next to an `Odometry`. After every ``odometry.step`` it turns what happened
into protocol messages (keyframes with descriptors, sub-map deltas of the agent's OWN points,
batched frame poses, decoder weights for federated rounds), numbers them with one counter
(``seq`` from 0) and keeps each in an outbox until an `Ack` covers it. Sub-map deltas go
every ``submap_every_mappings`` mapping calls with only the points that moved enough since
the server's copy (`cpslam.agent.submap`), decoder weights as a delta against the last loaded
group decoder (`cpslam.agent.deltas`). Between frames it applies what the server pushed:

- `ServerUpdate`: the whole local world moves into the group frame (keyframe poses in the
  map's pose table, so every point moves with its keyframe; the keyframe store; the
  trajectory, whose last poses seed the tracker), corrected keyframe poses replace the agent's
  own (frames follow their keyframe), and the other members' points join the local map;
- `GroupDecoder`: the shared weights replace the decoders (the mapper builds its Adam afresh at
  every call, so there is no optimiser state to reset) and the round is remembered;
- after either, the odometry re-fits its map to the new decoders and points before it tracks
  the next frame (`Odometry.mark_fused`);
- `KeyframeImageRequest`: answered from the keyframe store (its downsampled RGB-D copy).

Agent keys of the neural point map: the agent's own points and keyframes keep the odometry's
int id (``odometry.agent_id``); every other agent gets a local int on first sight, counting up
from ``own + 1`` in the order the sources appear. The mapping is local to this agent.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np
import torch

from cpslam.agent.corrections import correct_keyframes, move_world, rigid
from cpslam.agent.deltas import DecoderBase, SubmapMirror
from cpslam.agent.foreign import merge_foreign
from cpslam.agent.images import ImageReplies
from cpslam.agent.outbox import Outbox
from cpslam.agent.submap import submap_delta_fields
from cpslam.common.bounds import tensor_mismatch
from cpslam.common.geometry import compose, invert
from cpslam.protocol import (
    Ack,
    DecoderWeights,
    ErrorReply,
    ForeignPoints,
    FramePoses,
    GroupDecoder,
    KeyframeImage,
    KeyframeImageRequest,
    KeyframeMsg,
    Message,
    ServerUpdate,
    SubmapDelta,
)

if TYPE_CHECKING:
    from cpslam.agent.odometry import FrameResult, Odometry
    from cpslam.common.datasets import RGBDFrame

__all__ = ["AgentLink"]

logger = logging.getLogger(__name__)

MAX_WAITING_DECODERS = 16
"""Shared decoders of other groups an agent holds on to (the newest groups first)."""

MAX_FRAMES_PER_MESSAGE = 8192
"""Frame poses per `FramePoses` message (well under its size cap)."""

Describe = Callable[[np.ndarray], np.ndarray]


class AgentLink:
    """Messages out of one agent's odometry, and the server's answers applied to it.

    Args:
        agent_id: the agent's protocol id (also its initial group id).
        odometry: the agent's `Odometry` (its point map, decoders, keyframes and trajectory are
            read and, on server updates, changed).
        describe: ``rgb uint8 [H, W, 3] -> unit float32 [D]`` global descriptor of a keyframe
            (e.g. ``DescriptorExtractor.compute``).
        frames_every: frame poses are sent in batches of this many frames (and at keyframes).
        round_every_mappings: decoder weights are sent every this many mapping calls.
        federation: send decoder weights at all.
        images: how keyframe image requests are answered (size, codecs; `ImageReplies`).
        incarnation: this run's incarnation id, stamped on every message (0: none drawn).
        outbox: where sent messages wait for their acks (default: `Outbox()`'s bounds).
        update_window: a `ServerUpdate` more than this many seqs above the last one applied
            is ignored with a warning (forged or corrupt: it would mask every real one).
        submap_every_mappings: a sub-map delta goes every this many mapping calls.
        feature_threshold, feature_codec, feature_bits: which known points are resent, and
            how features travel (`SubmapMirror`).
        feature_rows: a known point the server acknowledged goes with its features alone.
        held_every_deltas: points the server holds are resent with every this-many-th
            sub-map delta (and the last); the others carry new and removed points only.
        decoder_delta: send decoder weights as an int8 delta against the last group decoder.
        decoder_full_codec: full decoder weights as "float16" or "int8" (`DecoderBase`).
    """

    def __init__(
        self,
        agent_id: str,
        odometry: Odometry,
        describe: Describe,
        frames_every: int = 10,
        round_every_mappings: int = 5,
        federation: bool = True,
        images: ImageReplies | None = None,
        incarnation: int = 0,
        outbox: Outbox | None = None,
        update_window: int = 4096,
        submap_every_mappings: int = 1,
        feature_threshold: float = 0.0,
        feature_codec: str = "float16",
        feature_bits: int = 8,
        feature_rows: bool = False,
        held_every_deltas: int = 1,
        decoder_delta: bool = False,
        decoder_full_codec: str = "float16",
    ) -> None:
        if min(frames_every, round_every_mappings, submap_every_mappings, held_every_deltas) < 1:
            raise ValueError(f"AgentLink: frames_every, round_every_mappings, "
                             f"submap_every_mappings and held_every_deltas must be >= 1, got "
                             f"{frames_every}, {round_every_mappings}, {submap_every_mappings}, "
                             f"{held_every_deltas}")
        self.agent_id = agent_id
        self.odometry = odometry
        self.describe = describe
        self.frames_every, self.round_every_mappings = frames_every, round_every_mappings
        self.federation = federation
        self.images = images if images is not None else ImageReplies()
        self.own = int(odometry.agent_id)
        self.group_id = agent_id
        self.group_members = [agent_id]
        self.epoch = 0
        self.round = 0
        self.T_group_agent = np.eye(4)
        self.update_seq = 0
        self.incarnation = int(incarnation)
        self.update_window = int(update_window)
        self.outbox = outbox if outbox is not None else Outbox()
        self.foreign_index: dict[str, int] = {}
        self.stats = {"updates": 0, "decoders": 0, "foreign_points": 0, "images": 0}
        self._seq = 0
        self._frame_kf: list[int] = []  # keyframe each trajectory entry is expressed against
        self._frame_index: list[int] = []  # stream index of each trajectory entry
        self._descriptors: dict[int, np.ndarray] = {}  # as sent, for a restarted stream
        self.server_state: int | None = None
        """State id of the server this stream goes to (`cpslam.agent.rebase`)."""
        self._pending_frames: list[tuple[int, float, int, np.ndarray]] = []
        self.mirror = SubmapMirror(odometry.point_map.feature_dim, feature_threshold,
                                   feature_codec, feature_bits)  # type: ignore[arg-type]
        self.submap_every_mappings = submap_every_mappings
        self.feature_rows = feature_rows
        self.held_every_deltas = held_every_deltas
        self._deltas = 0  # sub-map deltas built, the one that resends held points included
        self.decoder_delta = decoder_delta
        self.decoder_base = DecoderBase(full_codec=decoder_full_codec)
        self._submap_mappings = 0
        self._mappings = 0
        self._samples = 0
        self._decoders_waiting: dict[str, GroupDecoder] = {}

    # ------------------------------------------------------------------------- outgoing

    def after_step(self, frame: RGBDFrame, result: FrameResult) -> list[Message]:
        """Messages for one processed frame (`frame` at the processing resolution)."""
        out: list[Message] = []
        kf = self.odometry.keyframes.latest
        assert kf is not None  # frame 0 is always a keyframe
        self._frame_kf.append(kf.kf_id)
        self._frame_index.append(int(result.index))
        T_kf_frame = rigid(compose(invert(kf.T_world_cam), result.T_world_cam))
        self._pending_frames.append((result.index, result.timestamp, kf.kf_id, T_kf_frame))
        if result.is_keyframe:
            out.append(self._keyframe_msg(frame, result))
        if result.map_steps > 0:
            first = self.odometry.n_frames == 1
            pixels = self.odometry.n_pixels_first if first else self.odometry.n_pixels
            self._samples += result.map_steps * pixels
            self._mappings += 1
            self._submap_mappings += 1
            # the first mapping call's map goes at once: the server aligns and fuses with it
            if self._submap_mappings >= self.submap_every_mappings or not len(self.mirror.ids):
                delta = self._submap_delta()
                if delta is not None:
                    out.append(delta)
            if self.federation and self._mappings >= self.round_every_mappings:
                out.append(self._decoder_weights())
        if result.is_keyframe or len(self._pending_frames) >= self.frames_every:
            out += self.flush()
        return out

    def finish(self) -> list[Message]:
        """End of the stream (mapping drained): a last sub-map delta when mapping changed the
        map since the previous one, then the frame poses not sent yet."""
        delta = self._submap_delta(held=True)
        return ([delta] if delta is not None else []) + self.flush()

    def flush(self) -> list[Message]:
        """The frame poses not sent yet (call at the end of the stream), at most
        `MAX_FRAMES_PER_MESSAGE` per message."""
        out: list[Message] = []
        while self._pending_frames:
            batch = self._pending_frames[:MAX_FRAMES_PER_MESSAGE]
            del self._pending_frames[:MAX_FRAMES_PER_MESSAGE]
            idx, stamps, kfs, T = zip(*batch, strict=True)
            out.append(self._stamp(FramePoses(
                agent_id=self.agent_id, seq=0, frame_indices=np.asarray(idx, np.int64),
                stamps=np.asarray(stamps, np.float64), kf_ids=np.asarray(kfs, np.int32),
                T_kf_frame=np.stack(T))))
        return out

    def on_ack(self, ack: Ack) -> int:
        """Forget every message the ack covers (`Outbox.on_ack`); returns how many left."""
        if ack.agent_id != self.agent_id:
            return 0
        n = self.outbox.on_ack(ack, self._seq, self.incarnation)
        self.decoder_base.acked(self.acked)
        return n

    @property
    def acked(self) -> int:
        """The highest ack floor seen."""
        return self.outbox.floor

    def unacked(self) -> list[Message]:
        """Messages sent but not acknowledged yet, oldest first (to resend on reconnect)."""
        return self.outbox.messages()

    @property
    def next_seq(self) -> int:
        """The seq the next message gets."""
        return self._seq

    def restart(self, incarnation: int) -> list[Message]:
        """Start the stream over for a server that lost this agent's state (`restart_stream`:
        new incarnation, the whole state again); returns the messages to publish."""
        from cpslam.agent.rebase import restart_stream

        return restart_stream(self, incarnation)

    def _stamp(self, msg: Message) -> Message:
        msg = msg.model_copy(update={"seq": self._seq, "incarnation": self.incarnation})
        self.outbox.add(self._seq, msg)
        self._seq += 1
        return msg

    def _keyframe_msg(self, frame: RGBDFrame, result: FrameResult) -> KeyframeMsg:
        store = self.odometry.keyframes
        ids = store.ids()
        kf = store.get(result.kf_id)
        T_prev = None
        if len(ids) > 1:
            T_prev = compose(invert(store.get(ids[-2]).T_world_cam), kf.T_world_cam)
        descriptor = np.asarray(self.describe(frame.rgb), np.float32)
        descriptor = descriptor / np.linalg.norm(descriptor)
        self._descriptors[kf.kf_id] = descriptor
        return self._stamp(KeyframeMsg(
            agent_id=self.agent_id, seq=0, kf_id=kf.kf_id, frame_index=kf.frame_index,
            stamp=kf.timestamp, world_epoch=self.epoch, T_world_cam=kf.T_world_cam,
            T_prev_kf_kf=T_prev, descriptor=descriptor, n_points=len(kf.point_ids)))

    def _submap_delta(self, max_points: int | None = None, held: bool | None = None
                      ) -> SubmapDelta | None:
        """Own points that are new or moved enough since the server's copy (the first
        `max_points` of them), and own points that disappeared (`submap_delta_fields`);
        points the server holds only with every `held_every_deltas`-th delta or when `held`."""
        self._submap_mappings = 0
        if held is None:
            held = self._deltas % self.held_every_deltas == 0
        self._deltas += 1
        fields = submap_delta_fields(self.odometry.point_map, self.own, self.mirror, self._seq,
                                     self.feature_rows, self.outbox.floor, max_points, held)
        if fields is None:
            return None
        return self._stamp(SubmapDelta(agent_id=self.agent_id, seq=0, **fields))

    def _decoder_weights(self) -> DecoderWeights:
        tensors = {k: v.detach().cpu().numpy().astype(np.float32)
                   for k, v in self.odometry.decoders.state_dict().items()}
        fields = (self.decoder_base.fields(self.group_id, tensors) if self.decoder_delta
                  else {"tensors": tensors})
        msg = DecoderWeights(agent_id=self.agent_id, seq=self._seq, group_id=self.group_id,
                             round=self.round, n_samples=self._samples, **fields)
        self._mappings, self._samples = 0, 0
        self.decoder_base.sent(self._seq, fields)
        return self._stamp(msg)

    # ------------------------------------------------------------------------- incoming

    def apply_update(self, update: ServerUpdate) -> bool:
        """Move into the group frame, take corrected poses and foreign points (between
        frames). Returns False for an update that is not for this agent, is stale (applied
        already: each seq is applied once) or lies beyond ``update_window``."""
        if update.agent_id != self.agent_id or update.seq <= self.update_seq:
            logger.debug("agent %s: ignoring server update seq %d", self.agent_id, update.seq)
            return False
        if update.seq > self.update_seq + self.update_window:
            logger.warning("agent %s: ignoring server update seq %d: more than %d above the "
                           "last applied (%d)", self.agent_id, update.seq, self.update_window,
                           self.update_seq)
            return False
        self.update_seq = int(update.seq)
        with self.odometry.editing():
            self._apply_update(update)
        return True

    def _apply_update(self, update: ServerUpdate) -> None:
        T_new_old = compose(update.T_group_agent, invert(self.T_group_agent))
        if not np.allclose(T_new_old, np.eye(4), atol=1e-12):
            move_world(self.odometry, T_new_old)
        self.T_group_agent = np.asarray(update.T_group_agent, np.float64).copy()
        if update.group_id != self.group_id:
            self.round = 0  # rounds count per group: the new group's next decoder is newer
            # Offer weights at the next mapping call: the new group's first federated round
            # should not wait a whole round_every_mappings period (agents may end before).
            self._mappings = max(self._mappings, self.round_every_mappings - 1)
        self.epoch, self.group_id = int(update.epoch), update.group_id
        self.group_members = list(update.group_members)
        correct_keyframes(self.odometry, self.own, self._frame_kf,
                          dict(zip(update.kf_ids.tolist(), update.T_group_kf, strict=True)))
        added = sum(self._merge_foreign(block) for block in update.foreign)
        if added:
            self.odometry.mark_fused()
        self.stats["updates"] += 1
        logger.info("agent %s: update %d (group %s, epoch %d, %d keyframes corrected, %d "
                    "foreign points)", self.agent_id, update.seq, self.group_id, self.epoch,
                    len(update.kf_ids), added)
        waiting = self._decoders_waiting.pop(self.group_id, None)
        if waiting is not None:
            self.apply_decoder(waiting)

    def apply_decoder(self, msg: GroupDecoder) -> bool:
        """Load a newer shared decoder of this agent's group; one of another group is kept in
        case this agent joins that group later (the newest MAX_WAITING_DECODERS groups).
        Tensors whose names or shapes differ from this agent's decoders (a server on another
        preset) are logged and dropped. Returns True when loaded."""
        expected = {k: tuple(v.shape) for k, v in self.odometry.decoders.state_dict().items()}
        reason = tensor_mismatch(msg.tensors, expected, "this agent's field config")
        if reason:
            logger.warning("agent %s: dropped group decoder %s#%d: %s", self.agent_id,
                           msg.group_id, msg.round, reason)
            return False
        if msg.group_id != self.group_id:
            held = self._decoders_waiting.pop(msg.group_id, None)
            self._decoders_waiting[msg.group_id] = (
                msg if held is None or msg.round > held.round else held)
            while len(self._decoders_waiting) > MAX_WAITING_DECODERS:
                self._decoders_waiting.pop(next(iter(self._decoders_waiting)))
            return False
        if msg.round <= self.round:
            return False
        with self.odometry.editing() as state:
            device = next(iter(state.decoders.state_dict().values())).device
            state.decoders.load_state_dict({k: torch.as_tensor(v, device=device)
                                            for k, v in msg.tensors.items()})
        self.round = int(msg.round)
        self.decoder_base.set(msg.group_id, msg.round, msg.tensors)
        self._mappings, self._samples = 0, 0
        self.odometry.mark_fused()
        self.stats["decoders"] += 1
        logger.info("agent %s: shared decoder %s#%d loaded", self.agent_id, msg.group_id,
                    msg.round)
        return True

    def answer_image(self, request: KeyframeImageRequest) -> KeyframeImage | ErrorReply:
        """The keyframe's full-size RGB-D (the processed frame's), resized by the request's
        scale, with its intrinsics; the small copy for a keyframe saved without its full-size
        images."""
        store = self.odometry.keyframes
        if request.agent_id != self.agent_id or request.kf_id not in store:
            return ErrorReply(code="not_found", reason=f"agent {self.agent_id} has no keyframe "
                              f"{request.agent_id}/{request.kf_id}")
        kf = store.get(request.kf_id)
        try:
            rgb, depth = store.full_rgbd(kf.kf_id)
            intr = store.intrinsics
        except KeyError:
            rgb, depth, intr = kf.rgb_small, kf.depth_small, store.intrinsics_small
        self.stats["images"] += 1
        return self.images.answer(request, rgb, depth, intr,
                                  merged=len(self.group_members) > 1)

    # ------------------------------------------------------------------------- internals

    def _merge_foreign(self, block: ForeignPoints) -> int:
        """Add (or replace) another member's points; returns how many were added."""
        key = self.foreign_index.setdefault(
            block.source_agent_id, max([self.own, *self.foreign_index.values()]) + 1)
        n = merge_foreign(self.odometry.point_map, key, block, self.agent_id)
        self.stats["foreign_points"] += n
        return n


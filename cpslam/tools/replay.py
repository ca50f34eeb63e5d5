"""The load harness's agents: wire recordings replayed as N agents, each in its own world.

`replica_messages` turns one recording (`cpslam.agent.recording`) into the stream of another
agent: a new agent id and incarnation, every keyframe pose ``T_world_cam`` moved into the
replica's world by a rigid ``T_world_rec`` (frame poses are relative to their keyframes and
sub-map points local to their keyframes, so they stay as recorded), ``world_epoch`` 0 (a
replica never applies an alignment), and seqs renumbered from 0 in send order (a decoder
delta's ``base_seq`` follows its base). A decoder delta against a shared decoder
(``base_round``) cannot be replayed, since the replica's group never had that decoder: it is
left out, and so is a delta whose base was left out.

`ReplayAgent` plays one replica on a bus as the agent daemon would: liveliness token, image
queryable answered from the recording's keyframe images (agent id rewritten), messages
published at the recorded time divided by ``speed`` (by default the sensor time of the frame
that produced them: an agent keeping up with its camera, whatever the recording machine's
speed; none while the outbox is full), an `Outbox` that acks trim and that resends what
stays unacknowledged ``resend_after_s``, an `UpdateAck` for each server update (which it
does not apply: it does not track or map), and shared decoders taken off the bus
unapplied. Replicas of one recording are the same map in different frames, so the server
must find the loops between them and merge them; with the right merge replica k's group
alignment is ``T_group_k = C @ inv(T_world_rec_k)`` with one C for all replicas.

`replay` drives N of them on their buses in one thread on the wall clock; tests call
`ReplayAgent.step` with their own clock.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from cpslam import protocol
from cpslam.agent.images import rescale_reply
from cpslam.agent.node import new_incarnation
from cpslam.agent.outbox import Outbox
from cpslam.agent.recording import Recording
from cpslam.protocol import (
    Ack,
    DecoderWeights,
    ErrorReply,
    GroupDecoder,
    KeyframeImage,
    KeyframeImageRequest,
    KeyframeMsg,
    Message,
    ProtocolError,
    Refusal,
    ServerUpdate,
    UpdateAck,
    keys,
)

CLOCKS = ("sensor", "wall")
"""Timelines a recording can be replayed on (`replica_messages`)."""

__all__ = ["ReplayAgent", "Replica", "random_rigid", "replay", "replica_messages"]

logger = logging.getLogger(__name__)


def random_rigid(rng: np.random.Generator, max_translation_m: float = 5.0) -> np.ndarray:
    """A rigid 4x4 transform: uniformly random rotation (a normalised Gaussian quaternion),
    translation uniform in the cube of half-side `max_translation_m`."""
    q = rng.normal(size=4)
    x, y, z, w = q / np.linalg.norm(q)
    T = np.eye(4)
    T[:3, :3] = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ]
    T[:3, 3] = rng.uniform(-max_translation_m, max_translation_m, 3)
    return T


def replica_messages(
    rec: Recording,
    agent_id: str,
    incarnation: int,
    T_world_rec: np.ndarray,
    clock: str = "sensor",
) -> tuple[list[tuple[float, str, Message]], int]:
    """The recording's messages as agent `agent_id` in the world ``T_world_rec`` moves the
    recorded one into: ``[(t, topic, message)]`` and how many were left out (see the module
    docstring). `clock`: ``t`` is the sensor time of the frame that produced the message
    (``sensor``: an agent that keeps up with its camera) or the time the recorded agent sent
    it (``wall``: as fast as the recording machine was). Raises ValueError naming the
    recording for a message that does not decode."""
    if clock not in CLOCKS:
        raise ValueError(f"replica_messages: clock must be one of {CLOCKS}, got {clock!r}")
    out: list[tuple[float, str, Message]] = []
    new_seq: dict[int, int] = {}
    skipped = 0
    for i, (t_wall, topic, payload, stamp) in enumerate(rec.messages):
        t = stamp if clock == "sensor" else t_wall
        try:
            msg = protocol.decode(payload)
        except ProtocolError as exc:
            raise ValueError(f"{rec.path}: message {i} ({topic}) does not decode: {exc}") from exc
        update: dict[str, Any] = {
            "agent_id": agent_id,
            "incarnation": int(incarnation),
            "seq": len(out),
        }
        if isinstance(msg, KeyframeMsg):
            update["T_world_cam"] = T_world_rec @ msg.T_world_cam
            update["world_epoch"] = 0
        elif isinstance(msg, DecoderWeights):
            if msg.base_round is not None or (
                msg.base_seq is not None and msg.base_seq not in new_seq
            ):
                skipped += 1
                continue
            if msg.base_seq is not None:
                update["base_seq"] = new_seq[msg.base_seq]
            update["group_id"], update["round"] = agent_id, 0
        new_seq[int(msg.seq)] = len(out)
        out.append((t, topic, msg.model_copy(update=update)))
    return out, skipped


@dataclass
class Replica:
    """What one replayed agent is: its id, source recording and world transform."""

    agent_id: str
    recording: Recording
    T_world_rec: np.ndarray
    """Moves the recorded agent's world into this replica's (4x4)."""
    incarnation: int = 0


class ReplayAgent:
    """One replica on an open bus (see the module docstring).

    Args:
        replica: who it is.
        bus: an open bus (not closed here).
        session: the Zenoh session name of the keys.
        speed: recorded seconds per replayed second.
        outbox: where sent messages wait for their acks.
        zstd_level: compression of the re-encoded messages (the agent's ``link.zstd_level``).
        clock: the recording's timeline to follow (`replica_messages`).
    """

    def __init__(
        self,
        replica: Replica,
        bus: Any,
        session: str,
        speed: float = 1.0,
        outbox: Outbox | None = None,
        zstd_level: int = 3,
        clock: str = "sensor",
    ) -> None:
        if speed <= 0:
            raise ValueError(f"ReplayAgent: speed must be > 0, got {speed}")
        self.replica, self.bus, self.session = replica, bus, session
        self.agent_id = keys.check_id(replica.agent_id, "agent id")
        if not replica.incarnation:
            replica.incarnation = new_incarnation()
        self.incarnation = replica.incarnation
        self.speed, self.zstd_level = float(speed), zstd_level
        self.messages, self.skipped = replica_messages(
            replica.recording, self.agent_id, self.incarnation, replica.T_world_rec, clock
        )
        self.outbox = outbox if outbox is not None else Outbox()
        self.next = 0
        """Index of the next message to publish (also its seq)."""
        self.refused: str | None = None
        self.stats = {
            "sent": 0,
            "resent": 0,
            "images": 0,
            "image_misses": 0,
            "updates": 0,
            "decoders": 0,
            "bytes": 0,
        }
        self._images: dict[int, KeyframeImage] = {}
        self._lock = threading.Lock()  # the image queryable runs on the bus's thread
        self._handles: list[Any] = []
        self._server_sub: Any = None
        self._last_update = 0

    def start(self) -> ReplayAgent:
        s, a = self.session, self.agent_id
        self._server_sub = self.bus.subscribe(keys.server_agent_all(s, a), queue_size=256)
        self._handles = [
            self._server_sub,
            self.bus.declare_queryable(keys.agent_image_queryable(s, a), self._serve_image),
            self.bus.declare_liveliness(keys.alive_agent(s, a)),
        ]
        return self

    def close(self) -> None:
        for handle in self._handles:
            (handle.close if hasattr(handle, "close") else handle.undeclare)()
        self._handles = []

    @property
    def sent_all(self) -> bool:
        return self.next >= len(self.messages)

    @property
    def done(self) -> bool:
        """Everything published and acknowledged (or refused)."""
        return self.refused is not None or (self.sent_all and not self.outbox)

    def next_due_s(self) -> float | None:
        """Replay time (s since start) of the next message; None when all are out."""
        return None if self.sent_all else self.messages[self.next][0] / self.speed

    def step(self, elapsed_s: float) -> int:
        """Apply what the server sent, publish every message due by `elapsed_s` seconds of
        replay, resend what is due; returns how many were published."""
        self.poll()
        if self.refused is not None:
            return 0
        n = 0
        # like the agent daemon: no new message while the outbox is at its bound
        while (
            not self.sent_all
            and not self.outbox.full()
            and self.messages[self.next][0] / self.speed <= elapsed_s
        ):
            _, topic, msg = self.messages[self.next]
            self.outbox.add(int(msg.seq), msg)
            self._publish(topic, msg)
            self.next += 1
            n += 1
        for msg in self.outbox.due():
            self.stats["resent"] += 1
            self._publish(_TOPIC[msg.type], msg)
        return n

    def poll(self) -> int:
        """Take acks (the outbox forgets what they cover), updates (acknowledged, not
        applied), refusals and shared decoders off the bus."""
        n = 0
        while (sample := self._server_sub.get(timeout=0)) is not None:
            n += 1
            msg = self._decode(sample.key, sample.payload,
                               (Ack, ServerUpdate, Refusal, GroupDecoder))
            if isinstance(msg, Ack) and msg.agent_id == self.agent_id:
                self.outbox.on_ack(msg, self.next, self.incarnation)
            elif isinstance(msg, ServerUpdate) and msg.agent_id == self.agent_id:
                self.stats["updates"] += 1
                self._last_update = max(self._last_update, int(msg.seq))
                self._publish(
                    "update_ack",
                    UpdateAck(
                        agent_id=self.agent_id,
                        incarnation=self.incarnation,
                        update_seq=self._last_update,
                    ),
                )
            elif isinstance(msg, Refusal) and msg.agent_id == self.agent_id:
                if msg.incarnation == self.incarnation and self.refused is None:
                    self.refused = msg.reason or "refused"
                    logger.error(
                        "replica %s: refused by the server: %s", self.agent_id, self.refused
                    )
            elif isinstance(msg, GroupDecoder):
                self.stats["decoders"] += 1
        return n

    def wait(self, timeout_s: float) -> bool:
        """Block until the server sent this replica something or `timeout_s` passed."""
        return self._server_sub.wait(timeout_s)

    # ------------------------------------------------------------------------- helpers

    def _publish(self, topic: str, msg: Message) -> None:
        key = keys.agent_topic(self.session, self.agent_id, topic)
        try:
            payload = protocol.encode(msg, self.zstd_level)
            self.bus.publish(key, payload)
        except ProtocolError as exc:
            logger.error("replica %s: could not send %s: %s", self.agent_id, msg.type, exc)
            return
        self.stats["sent"] += 1
        self.stats["bytes"] += len(payload)

    def _decode(self, key: str, payload: bytes, expected: Any) -> Any:
        try:
            return protocol.decode(payload, expected=expected)
        except ProtocolError as exc:
            logger.warning("replica %s: dropped message on %s: %s", self.agent_id, key, exc)
            return None

    def _serve_image(self, key: str, payload: bytes | None) -> bytes:
        """The recorded keyframe image under this replica's id, with what the request
        wants (as `AgentNode` answers: a bad request or an unknown keyframe gets an
        `ErrorReply`)."""
        try:
            agent, kf = keys.parse_image_key(self.session, key)
            request = (
                protocol.decode(payload, expected=KeyframeImageRequest)
                if payload
                else KeyframeImageRequest(agent_id=agent, kf_id=kf)
            )
        except ProtocolError as exc:
            return protocol.encode(ErrorReply(code="bad_request", reason=str(exc)[:4000]))
        if (request.agent_id, request.kf_id) != (agent, kf):
            return protocol.encode(
                ErrorReply(code="bad_request", reason="request does not match the key")
            )
        recorded = self.replica.recording.images.get(kf)
        if agent != self.agent_id or recorded is None:
            with self._lock:
                self.stats["image_misses"] += 1
            return protocol.encode(
                ErrorReply(code="not_found", reason=f"replica {self.agent_id} has no keyframe {kf}")
            )
        with self._lock:
            image = self._images.get(kf)
            if image is None:
                image = self._images[kf] = protocol.decode(recorded, expected=KeyframeImage)
            self.stats["images"] += 1
        try:
            reply = rescale_reply(image, request)
        except ValueError as exc:
            return protocol.encode(ErrorReply(code="not_found", reason=str(exc)[:4000]))
        return protocol.encode(reply)


_TOPIC = {
    "keyframe": "keyframe",
    "submap_delta": "submap",
    "decoder_weights": "decoder",
    "frame_poses": "frames",
    "update_ack": "update_ack",
}


def replay(
    agents: Sequence[ReplayAgent],
    ack_timeout_s: float = 120.0,
    stop: threading.Event | None = None,
    now: Callable[[], float] = time.monotonic,
) -> dict[str, Any]:
    """Play `agents` (started) together on the wall clock until each has published
    everything and had it acknowledged (or `ack_timeout_s` after the last was published).
    Returns ``{"wall_s", "streamed_s", "unacknowledged": {agent: n}}``."""
    t0 = now()
    streamed = None
    while not (stop is not None and stop.is_set()):
        elapsed = now() - t0
        for agent in agents:
            agent.step(elapsed)
        if streamed is None and all(a.sent_all for a in agents):
            streamed = now() - t0
        if all(a.done for a in agents):
            break
        if streamed is not None and now() - t0 - streamed > ack_timeout_s:
            logger.warning(
                "replay: still unacknowledged after %.0f s: %s",
                ack_timeout_s,
                {a.agent_id: len(a.outbox) for a in agents if a.outbox},
            )
            break
        due = [d for a in agents if (d := a.next_due_s()) is not None]
        pause = min([*due, elapsed + 0.05]) - (now() - t0)
        if pause > 0:
            agents[0].wait(min(pause, 0.05))
    return {
        "wall_s": now() - t0,
        "streamed_s": streamed,
        "unacknowledged": {a.agent_id: len(a.outbox) for a in agents if a.outbox},
    }

"""An agent process's loop over a bus: frames in, messages out, the server's answers applied.

`AgentNode` owns one agent's `Odometry` and `AgentLink`. `start` declares the agent's
liveliness token, its keyframe-image queryable and its subscription to everything the server
sends it (its group's shared decoders included: a decoder of a group the agent has not yet
learnt it joined is kept until the update that says so);
`step` processes one frame and publishes what the link produced; `poll` applies, without
blocking, what arrived (acks trim the outbox, updates move the world and are acknowledged
with an `UpdateAck`, decoders load, a `Refusal` of this incarnation sets `refused`).
Every start draws a fresh random incarnation id (`new_incarnation`), stamped on every
message, so the server can tell a restarted agent from the one it knows.
`cpslam.agent.daemon.run_networked` is the daemon loop around it; ``cpslam run`` drives
`step`/`poll` itself in lock-step for determinism.
"""

from __future__ import annotations

import json
import logging
import os
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from cpslam import protocol
from cpslam.agent.images import ImageReplies
from cpslam.agent.link import AgentLink
from cpslam.agent.odometry import FrameResult, Odometry
from cpslam.agent.outbox import Outbox
from cpslam.agent.recording import WireRecorder
from cpslam.agent.standalone import processing_frames, write_agent_outputs
from cpslam.common.rundir import write_json
from cpslam.common.trajectory import sensor_seconds
from cpslam.protocol import (
    Ack,
    ErrorReply,
    GroupDecoder,
    KeyframeImageRequest,
    Message,
    ProtocolError,
    Refusal,
    ServerUpdate,
    UpdateAck,
    keys,
)

if TYPE_CHECKING:
    from cpslam.common.bus import Bus
    from cpslam.common.config import CpslamConfig
    from cpslam.common.datasets import RGBDFrame, RGBDSequence

__all__ = ["AgentNode", "new_incarnation"]

logger = logging.getLogger(__name__)


def new_incarnation() -> int:
    """A random non-zero 63-bit incarnation id, from the OS (never from the config seed:
    two restarts with one config must not collide)."""
    return int.from_bytes(os.urandom(8), "big") % (2**63 - 1) + 1


class AgentNode:
    """One agent on a bus.

    Args:
        cfg: the whole config.
        seq: the agent's RGB-D sequence.
        bus: an open bus (not closed by the node).
        agent_id: protocol id of the agent.
        run_dir: the run folder; outputs go to ``run_dir/agent_<id>/``.
        device: torch device.
        describe: descriptor function (default: `DescriptorExtractor.from_config`).
        frames_every: frame poses per batch.
        incarnation: this run's incarnation id (default: `new_incarnation`).
        now: monotonic clock of the outbox's resend timing (s).
    """

    def __init__(self, cfg: CpslamConfig, seq: RGBDSequence, bus: Bus, agent_id: str,
                 run_dir: str | Path, device: str = "cpu", describe: Any = None,
                 frames_every: int = 10, incarnation: int | None = None,
                 now: Callable[[], float] = time.monotonic) -> None:
        self.cfg, self.seq, self.bus = cfg, seq, bus
        self.agent_id = keys.check_id(agent_id, "agent id")
        self.session = keys.check_id(cfg.transport.session, "transport.session")
        self.run_dir, self.device = Path(run_dir), device
        self.intrinsics, self._frames = processing_frames(seq, cfg.camera.downscale)
        self.odometry = Odometry.from_config(cfg, self.intrinsics, device, agent_id=0)
        if describe is None:
            from cpslam.agent.descriptor import DescriptorExtractor

            describe = DescriptorExtractor.from_config(cfg.place_recognition, device,
                                                       seed=cfg.run.seed).compute
        t = cfg.transport
        self.incarnation = new_incarnation() if incarnation is None else int(incarnation)
        outbox = Outbox(t.outbox_messages, t.outbox_mb, t.resend_after_s, now)
        self.link = AgentLink(agent_id, self.odometry, describe, frames_every=frames_every,
                              round_every_mappings=cfg.federation.round_every_mappings,
                              federation=cfg.federation.enabled, incarnation=self.incarnation,
                              outbox=outbox, update_window=t.update_window,
                              submap_every_mappings=cfg.link.submap_every_mappings,
                              feature_threshold=cfg.link.feature_threshold,
                              feature_rows=cfg.link.feature_rows,
                              held_every_deltas=cfg.link.held_every_deltas,
                              feature_codec=cfg.link.feature_codec,
                              feature_bits=cfg.link.feature_bits,
                              decoder_delta=cfg.link.decoder_delta,
                              decoder_full_codec=cfg.link.decoder_full_codec,
                              images=ImageReplies(
                                  jpeg_quality=cfg.link.jpeg_quality,
                                  depth_codec=cfg.link.depth_codec,
                                  depth_step_mm_per_m2=cfg.link.depth_step_mm_per_m2,
                                  noisy_scale=cfg.link.noisy_image_scale,
                                  noisy_depth_mm_per_m2=cfg.link.noisy_depth_mm_per_m2,
                                  step_noise_ratio=cfg.link.depth_step_noise_ratio))
        self.refused: str | None = None
        """The server's reason when it refused this incarnation (the agent must stop)."""
        self.results: list[FrameResult] = []
        self.dropped = 0
        self.wall_s = 0.0
        self._lock = threading.Lock()  # the image queryable reads the keyframe store
        self._handles: list[Any] = []
        self._server_sub: Any = None
        self.online: Callable[[], bool] | None = None
        """While this says False (the server is away, or back and not yet answered) messages
        wait in the outbox instead of going out; None: always publish."""
        self.restarts = 0
        self.recorder: WireRecorder | None = None
        if cfg.link.record:
            self.recorder = WireRecorder(self.run_dir / f"agent_{self.agent_id}" / "wire.rec",
                                         self.agent_id, self.session, self.incarnation,
                                         cfg.link.record_mb, start=time.monotonic())

    # ------------------------------------------------------------------------- lifecycle

    def start(self) -> AgentNode:
        s, a = self.session, self.agent_id
        queue = max(self.cfg.transport.queue_size, 256)
        self._server_sub = self.bus.subscribe(keys.server_agent_all(s, a), queue_size=queue)
        self._handles = [
            self._server_sub,
            self.bus.declare_queryable(keys.agent_image_queryable(s, a), self._serve_image),
            self.bus.declare_liveliness(keys.alive_agent(s, a)),
        ]
        return self

    def close(self) -> None:
        """Withdraw token, queryable and subscriptions, stop the mapping thread
        (idempotent)."""
        self.odometry.close()
        if self.recorder is not None:  # closed without outputs: the messages stay readable
            self.recorder.close()
            self.recorder = None
        for handle in self._handles:
            (handle.close if hasattr(handle, "close") else handle.undeclare)()
        self._handles = []

    def frames(self) -> Any:
        """The agent's frames at the processing resolution (an iterator, consumed once)."""
        return self._frames

    # ------------------------------------------------------------------------- per frame

    def step(self, frame: RGBDFrame) -> FrameResult:
        """Track/map one frame and publish the resulting messages."""
        t0 = time.perf_counter()
        with self._lock:
            result = self.odometry.step(frame)
            out = self.link.after_step(frame, result)
        self.results.append(result)
        self.send(out, record=True, stamp=result.timestamp)
        self.wall_s += time.perf_counter() - t0
        return result

    def send(self, messages: list[Message], record: bool = False,
             stamp: float | None = None) -> None:
        """Publish agent messages on their topic keys (`record`: new ones, into the wire
        recording when ``link.record`` is on, produced at frame time `stamp`; resends and
        update acks are not recorded)."""
        topic = {"keyframe": "keyframe", "submap_delta": "submap",
                 "decoder_weights": "decoder", "frame_poses": "frames",
                 "update_ack": "update_ack"}
        # While the server is away (or back and not yet answered) messages stay in the outbox
        # only; update acks are repeated after the server's resend.
        online = self.online is None or self.online()
        for msg in messages:
            key = keys.agent_topic(self.session, self.agent_id, topic[msg.type])
            try:
                payload = protocol.encode(msg, self.cfg.link.zstd_level)
                if online:
                    self.bus.publish(key, payload)
            except ProtocolError as exc:
                logger.error("agent %s: could not send %s seq %d: %s", self.agent_id, msg.type,
                             getattr(msg, "seq", -1), exc)
                continue
            if record and self.recorder is not None:
                first = self.results[0].timestamp if self.results else 0.0
                at = stamp if stamp is not None else (
                    self.results[-1].timestamp if self.results else 0.0)
                self.recorder.message(time.monotonic(), topic[msg.type], payload,
                                      stamp=at - first)

    def poll(self) -> int:
        """Apply everything queued (acks, updates, shared decoders) without waiting."""
        n = 0
        while (sample := self._server_sub.get(timeout=0)) is not None:
            msg = self._decode(sample.key, sample.payload,
                               (ServerUpdate, Ack, Refusal, GroupDecoder))
            if isinstance(msg, Ack):
                self._apply(sample.key, self.link.on_ack, msg)
            elif isinstance(msg, ServerUpdate) and msg.agent_id == self.agent_id:
                with self._lock:
                    self._apply(sample.key, self.link.apply_update, msg)
                # Applied or a repeat: confirm the latest applied (a lost ack is repaired by
                # the server's resend).
                if self.link.update_seq > 0:
                    self.send([UpdateAck(agent_id=self.agent_id, incarnation=self.incarnation,
                                         update_seq=self.link.update_seq)])
            elif isinstance(msg, Refusal) and msg.agent_id == self.agent_id:
                if msg.incarnation == self.incarnation and self.refused is None:
                    self.refused = msg.reason or "refused"
                    logger.error("agent %s: the server refused this incarnation: %s",
                                 self.agent_id, self.refused)
            elif isinstance(msg, GroupDecoder):
                with self._lock:
                    self._apply(sample.key, self.link.apply_decoder, msg)
            n += 1
        return n

    def _apply(self, key: str, apply: Any, msg: Any) -> None:
        # A message that passed validation but cannot be applied (a server on another
        # preset, a bug) is dropped: the daemon goes on with the next one.
        try:
            apply(msg)
        except Exception:  # noqa: BLE001 - a daemon never dies of a bad message
            self.dropped += 1
            logger.exception("agent %s: dropped %s on %s: applying it failed", self.agent_id,
                             type(msg).__name__, key)

    def flush(self) -> None:
        """End of the stream: let the mapping thread finish, send what it changed since the
        last sub-map delta and the frame poses not sent yet."""
        with self._lock:
            self.odometry.drain()
            out = self.link.finish()
        self.send(out, record=True)

    def resend(self) -> int:
        """Publish every unacknowledged message again (after a reconnect)."""
        pending = self.link.unacked()
        self.send(pending)
        self.link.outbox.mark_sent()
        return len(pending)

    def restart_stream(self) -> int:
        """The server lost this agent's acknowledged data (it came back under another state
        id): stream the whole state again as a new incarnation (`AgentLink.restart`). Returns
        the messages sent."""
        with self._lock:
            self.odometry.drain()
            self.incarnation = new_incarnation()
            out = self.link.restart(self.incarnation)
        self.restarts += 1
        self.send(out)
        return len(out)

    def resend_due(self) -> int:
        """Publish again the messages unacknowledged ``transport.resend_after_s`` after they
        were last sent (a lost message or ack, while streaming)."""
        due = self.link.outbox.due()
        if due:
            logger.info("agent %s: resending %d unacknowledged messages (seq %d…)",
                        self.agent_id, len(due), due[0].seq)
            self.send(due)
        return len(due)

    def wait_for_server_message(self, timeout_s: float) -> bool:
        """Block until something from the server is queued or `timeout_s` passed."""
        return self._server_sub.wait(timeout_s)

    def resume(self, state_path: Path) -> int:
        """Continue an earlier run of this agent: the odometry from `state_path` (its
        state.pt), the link (incarnation, seq counter, outbox) from ``link.pt`` beside it; the
        frames restart after the last one done. Returns that position in the sequence."""
        import numpy as np
        import torch

        from cpslam.agent.link_state import load_link_state, read_link_state

        link_path = Path(state_path).with_name("link.pt")
        if not link_path.is_file():
            raise ValueError(f"{link_path}: missing; --resume of a networked agent needs the "
                             "link.pt its earlier run wrote next to state.pt")
        self.odometry.load_state_dict(torch.load(state_path, map_location=self.device,
                                                 weights_only=True))
        load_link_state(self.link, read_link_state(link_path))
        self.incarnation = self.link.incarnation
        done, _ = self.odometry.trajectory()
        start = int(np.searchsorted(self.seq.timestamps, done[-1], side="right")) if len(
            done) else 0
        self._frames = processing_frames(self.seq, self.cfg.camera.downscale, start)[1]
        logger.info("agent %s: resumed incarnation %d at frame position %d (next seq %d, %d "
                    "unacknowledged)", self.agent_id, self.incarnation, start,
                    self.link.next_seq, len(self.link.outbox))
        return start

    def sent_per_sensor_s(self, stats: dict[str, dict]) -> dict[str, float]:
        """Bytes published per second of sensor time (the processed frames' span), per key;
        empty before two frames."""
        sensor = sensor_seconds(r.timestamp for r in self.results)
        if not sensor:
            return {}
        return {k: row["bytes"] / sensor for k, row in stats.get("sent", {}).items()}

    def write_outputs(self, extra: dict[str, Any] | None = None) -> Path:
        """``run_dir/agent_<id>/`` as a standalone run writes it, plus ``link.pt`` (for
        --resume); `extra` (e.g. bytes sent per key expression) is added to its metrics.json."""
        from cpslam.agent.link_state import write_link_state

        agent_dir = self.run_dir / f"agent_{self.agent_id}"
        agent_dir.mkdir(parents=True, exist_ok=True)
        self._record_images()
        write_agent_outputs(self.odometry, agent_dir, self.results, self.wall_s, False,
                            str(self.device), self.seq)
        write_link_state(self.link, agent_dir / "link.pt")
        if extra:
            metrics_path = agent_dir / "metrics.json"
            metrics = json.loads(metrics_path.read_text())
            metrics.update(extra)
            write_json(metrics_path, metrics)
        return agent_dir

    # ------------------------------------------------------------------------- helpers

    def _record_images(self) -> None:
        """Every kept keyframe's images into the wire recording, which then closes (a replay
        answers the server's image requests from them)."""
        if self.recorder is None:
            return
        with self._lock:
            served = self.link.stats["images"]  # counts the server's requests only
            for kf in list(self.odometry.keyframes):
                reply = self.link.answer_image(KeyframeImageRequest(agent_id=self.agent_id,
                                                                    kf_id=kf.kf_id))
                self.recorder.image(kf.kf_id, protocol.encode(reply))
            self.link.stats["images"] = served
        self.recorder.close()
        self.recorder = None

    def _decode(self, key: str, payload: bytes, expected: Any) -> Any:
        try:
            return protocol.decode(payload, expected=expected)
        except ProtocolError as exc:
            self.dropped += 1
            logger.warning("agent %s: dropped message on %s: %s", self.agent_id, key, exc)
            return None

    def _serve_image(self, key: str, payload: bytes | None) -> bytes:
        try:
            agent, kf = keys.parse_image_key(self.session, key)
            request = (protocol.decode(payload, expected=KeyframeImageRequest) if payload
                       else KeyframeImageRequest(agent_id=agent, kf_id=kf))
        except ProtocolError as exc:
            return protocol.encode(ErrorReply(code="bad_request", reason=str(exc)[:4000]))
        if (request.agent_id, request.kf_id) != (agent, kf):
            return protocol.encode(ErrorReply(code="bad_request",
                                              reason="request does not match the key"))
        with self._lock:
            reply = self.link.answer_image(request)
        return protocol.encode(reply)


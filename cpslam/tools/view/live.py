"""A live observer of a running session: `cpslam view --connect tcp/HOST:7447`.

It only listens to the documented wire protocol (docs/protocol.md): it subscribes to the
agents' keyframes, sub-map deltas and frame poses, to the server's updates and group decoders,
watches presence, and queries ``server/status`` (which carries the recent loop pairs) and,
for thumbnails, the agents' keyframe images. It never publishes, so it cannot change any SLAM
state; queries are reads (an image query costs the agent one JPEG encoding).

Poses are shown in each agent's current frame: its own first camera until the server aligns
it into a group, then the group's (every stored pose is moved when ``T_group_agent`` changes).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from cpslam.common.camera import Intrinsics
from cpslam.tools.view.sink import Scene

logger = logging.getLogger(__name__)

__all__ = ["Observer"]

# Sub-map deltas must not be dropped (each carries points sent once); frame poses and
# keyframes are small. Depth of the subscriptions' drop-oldest queues:
QUEUE_SIZE = 4096
MAX_THUMBNAILS_PER_POLL = 4
POINTS_EVERY_S = 5.0
"""Sub-map points are re-logged at most this often per agent (each time whole: a keyframe
correction moves all its points), which bounds a recording's size."""


@dataclass
class _Agent:
    """What the observer knows of one agent, in its current display frame."""

    index: int
    epoch: int = 0
    T_group_agent: dict[int, np.ndarray] = field(default_factory=lambda: {0: np.eye(4)})
    group: str | None = None
    members: tuple[str, ...] = ()
    kf_poses: dict[int, np.ndarray] = field(default_factory=dict)
    frames: dict[int, tuple[float, int, np.ndarray]] = field(default_factory=dict)
    intr: Intrinsics | None = None
    point_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    anchors: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32))
    xyz_local: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.float32))
    colours: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.uint8))
    dirty: bool = False
    points_at: float = -np.inf
    thumbnails: list[int] = field(default_factory=list)

    def to_display(self, T: np.ndarray, world_epoch: int) -> np.ndarray:
        """A pose sent in the frame of `world_epoch`, in the current frame."""
        old = self.T_group_agent.get(world_epoch)
        if world_epoch == self.epoch or old is None:
            return T
        return self.T_group_agent[self.epoch] @ np.linalg.inv(old) @ T

    def points_world(self) -> tuple[np.ndarray, np.ndarray]:
        """Positions [N, 3] of the points whose keyframe pose is known, and their colours."""
        known = np.array([k in self.kf_poses for k in self.anchors.tolist()], dtype=bool)
        if not known.any():
            return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8)
        T = np.stack([self.kf_poses[k] for k in self.anchors[known].tolist()])
        xyz = np.einsum("nij,nj->ni", T[:, :3, :3], self.xyz_local[known]) + T[:, :3, 3]
        return xyz.astype(np.float32), self.colours[known]


class Observer:
    """Follows session `session` on `bus` and logs it to `scene` (docs/viewer.md).

    Args:
        thumbnails: query each new keyframe's colour image (at most a few per poll).
        clock: seconds for the `run_time` timeline (monotonic; tests pass a fake).
    """

    def __init__(self, bus: Any, session: str, scene: Scene, thumbnails: bool = True,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.bus, self.session, self.scene = bus, session, scene
        self.thumbnails = thumbnails
        self.clock = clock
        self.t0 = clock()
        self.agents: dict[str, _Agent] = {}
        self.loops_seen: set[int] = set()
        self.messages = 0
        self.rejected = 0
        self._lock = threading.RLock()
        self._handles: list[Any] = []

    # -- wiring ---------------------------------------------------------------------------

    def start(self) -> None:
        """Subscribe and watch presence (nothing is declared that others could see)."""
        from cpslam.protocol import keys

        s = self.session
        for topic in ("keyframe", "submap", "frames"):
            self._handles.append(self.bus.subscribe(keys.all_agents_topic(s, topic),
                                                    self._on_sample, queue_size=QUEUE_SIZE))
        # Not the members' copies of the group decoders: the group key carries each once.
        for topic in ("update", "ack"):
            self._handles.append(self.bus.subscribe(keys.all_server_agent_topic(s, topic),
                                                    self._on_sample, queue_size=QUEUE_SIZE))
        self._handles.append(self.bus.subscribe(keys.all_group_decoders(s), self._on_sample))
        self._handles.append(self.bus.watch_liveliness(
            keys.alive_all(s), on_join=lambda k: self._presence(k, "joined"),
            on_leave=lambda k: self._presence(k, "left")))

    def run(self, stop: threading.Event, period_s: float = 1.0) -> None:
        """Poll the server's status and refresh the view every `period_s` until `stop`; the
        last poll logs every agent's points whatever their age."""
        while not stop.is_set():
            self.poll()
            stop.wait(period_s)
        self.poll(final=True)

    def close(self) -> None:
        for handle in self._handles:
            handle.close()
        self._handles.clear()

    # -- messages -------------------------------------------------------------------------

    def _on_sample(self, sample: Any) -> None:
        from cpslam import protocol
        from cpslam.protocol import ProtocolError

        try:
            msg = protocol.decode(sample.payload)
        except ProtocolError as err:
            self.rejected += 1
            logger.warning("ignored a malformed message on %s: %s", sample.key, err)
            return
        handler = getattr(self, f"_on_{msg.type}", None)
        if handler is None:
            return
        with self._lock:
            self.messages += 1
            self.scene.at(run_s=self.clock() - self.t0)
            handler(msg, sample.key)

    def _agent(self, agent_id: str) -> _Agent:
        if agent_id not in self.agents:
            self.agents[agent_id] = _Agent(index=len(self.agents))
        return self.agents[agent_id]

    def _on_keyframe(self, msg: Any, key: str) -> None:
        a = self._agent(msg.agent_id)
        a.kf_poses[msg.kf_id] = a.to_display(msg.T_world_cam, msg.world_epoch)
        self.scene.at(stamp_s=msg.stamp)
        self.scene.keyframe(msg.agent_id, a.index, msg.kf_id, a.kf_poses[msg.kf_id], a.intr,
                            static=False)
        if self.thumbnails:
            a.thumbnails.append(msg.kf_id)
        a.dirty = True

    def _on_submap_delta(self, msg: Any, key: str) -> None:
        a = self._agent(msg.agent_id)
        drop = np.isin(a.point_ids, np.concatenate([msg.removed_ids, msg.point_ids]))
        keep = ~drop
        a.point_ids = np.concatenate([a.point_ids[keep], msg.point_ids])
        a.anchors = np.concatenate([a.anchors[keep], msg.anchor_kf_ids])
        a.xyz_local = np.concatenate([a.xyz_local[keep], msg.xyz_local])
        a.colours = np.concatenate([a.colours[keep], msg.colors])
        a.dirty = True

    def _on_frame_poses(self, msg: Any, key: str) -> None:
        a = self._agent(msg.agent_id)
        for f, t, kf, T in zip(msg.frame_indices.tolist(), msg.stamps.tolist(),
                               msg.kf_ids.tolist(), msg.T_kf_frame, strict=True):
            a.frames[f] = (t, kf, T)
            if kf in a.kf_poses:
                self.scene.at(stamp_s=t)
                self.scene.camera(msg.agent_id, a.kf_poses[kf] @ T)
        a.dirty = True

    def _on_server_update(self, msg: Any, key: str) -> None:
        a = self._agent(msg.agent_id)
        if msg.epoch != a.epoch:
            move = msg.T_group_agent @ np.linalg.inv(a.T_group_agent[a.epoch])
            a.kf_poses = {k: move @ T for k, T in a.kf_poses.items()}
            a.T_group_agent[msg.epoch] = msg.T_group_agent
            a.epoch = msg.epoch
        for kf, T in zip(msg.kf_ids.tolist(), msg.T_group_kf, strict=True):
            a.kf_poses[kf] = T
        members = tuple(sorted(msg.group_members))
        if (msg.group_id, members) != (a.group, a.members):
            if a.group is not None or len(members) > 1:
                self.scene.event("merges", f"agent {msg.agent_id} in group {msg.group_id} "
                                 f"with {', '.join(members)} (epoch {msg.epoch})")
            a.group, a.members = msg.group_id, members
        for kf, T in a.kf_poses.items():
            self.scene.keyframe(msg.agent_id, a.index, kf, T, None, static=False)
        a.dirty = True

    def _on_group_decoder(self, msg: Any, key: str) -> None:
        self.scene.event("rounds", f"group {msg.group_id} federated round {msg.round}: "
                         f"{', '.join(msg.members)} ({msg.n_samples} samples)")
        self.scene.scalar(f"groups/{msg.group_id}/round", msg.round)

    def _on_ack(self, msg: Any, key: str) -> None:
        self.scene.scalar(f"agents/{msg.agent_id}/acked_seq", msg.seq)

    def _presence(self, key: str, what: str) -> None:
        with self._lock:
            self.scene.at(run_s=self.clock() - self.t0)
            self.scene.event("agents", f"{key.split('/', 2)[-1]} {what}")

    # -- polling --------------------------------------------------------------------------

    def poll(self, final: bool = False) -> dict | None:
        """One status query, the loops it reports, thumbnails and the refreshed geometry
        (points: see POINTS_EVERY_S, or now when `final`); returns the status summary (None
        when the server did not answer)."""
        from cpslam.server.client import query_status

        summary = query_status(self.bus, self.session, timeout_s=1.0)
        images = self._fetch_thumbnails()  # queries wait: not under the lock
        with self._lock:
            self.scene.at(run_s=self.clock() - self.t0)
            if summary is not None:
                self._log_status(summary)
                self._log_loops(summary.get("loops", {}).get("recent", []))
            for agent_id, img in images:
                a = self.agents[agent_id]
                a.intr = Intrinsics.of(img)
                if img.kf_id in a.kf_poses:
                    self.scene.keyframe(agent_id, a.index, img.kf_id, a.kf_poses[img.kf_id],
                                        a.intr, img.rgb, static=False)
            for agent_id, a in self.agents.items():
                if a.dirty:
                    self._refresh(agent_id, a, final)
        return summary

    def _log_status(self, summary: dict) -> None:
        for agent_id, info in summary.get("agents", {}).items():
            for name in ("keyframes", "frames", "points", "pending"):
                if isinstance(info.get(name), int | float):
                    self.scene.scalar(f"agents/{agent_id}/{name}", info[name])
            if isinstance(info.get("bytes"), int | float):
                self.scene.scalar(f"agents/{agent_id}/received_mb", info["bytes"] / 1e6)
        loops = summary.get("loops", {})
        for name in ("found", "accepted", "rejected", "pending"):
            if isinstance(loops.get(name), int | float):
                self.scene.scalar(f"loops/{name}", loops[name])
        rounds = summary.get("rounds", {})
        if isinstance(rounds.get("closed"), int):
            self.scene.scalar("rounds/closed", rounds["closed"])
        if isinstance(summary.get("merges"), int):
            self.scene.scalar("merges", summary["merges"])
        self.scene.scalar("groups", len(summary.get("groups", {})))

    def _log_loops(self, recent: list) -> None:
        """Every reported loop pair whose keyframes are known, as segments (re-logged whole
        when a loop is new or an agent's poses changed, since corrections move their ends);
        new ones also on the event log."""
        starts, ends, accepted, labels = [], [], [], []
        changed = any(a.dirty for a in self.agents.values())
        for lp in recent if isinstance(recent, list) else []:
            try:
                a, b = self.agents[str(lp["agent_a"])], self.agents[str(lp["agent_b"])]
                Ta, Tb = a.kf_poses[int(lp["kf_a"])], b.kf_poses[int(lp["kf_b"])]
            except (KeyError, TypeError, ValueError):
                continue
            starts.append(Ta[:3, 3])
            ends.append(Tb[:3, 3])
            accepted.append(bool(lp.get("accepted")))
            labels.append(f"{float(lp.get('score', 0.0)):.2f}")
            if lp.get("loop_id") not in self.loops_seen:
                self.loops_seen.add(lp.get("loop_id"))
                changed = True
                verdict = "accepted" if lp.get("accepted") else "rejected"
                self.scene.event("loops", f"loop {lp['agent_a']}:{lp['kf_a']} - "
                                 f"{lp['agent_b']}:{lp['kf_b']} {verdict}, score {labels[-1]}")
        if starts and changed:
            self.scene.loops(np.array(starts), np.array(ends), np.array(accepted), labels,
                             static=False)

    def _fetch_thumbnails(self) -> list[tuple[str, Any]]:
        """(agent id, KeyframeImage) of up to MAX_THUMBNAILS_PER_POLL waiting keyframes; an
        error reply (the image is gone) or no reply gives none."""
        from cpslam import protocol
        from cpslam.protocol import KeyframeImage, KeyframeImageRequest, ProtocolError, keys

        with self._lock:
            wanted = []
            for agent_id, a in self.agents.items():
                take = MAX_THUMBNAILS_PER_POLL - len(wanted)
                wanted += [(agent_id, kf) for kf in a.thumbnails[:take]]
                del a.thumbnails[:take]
        out = []
        for agent_id, kf in wanted:
            request = protocol.encode(KeyframeImageRequest(
                agent_id=agent_id, kf_id=kf, want_rgb=True, want_depth=False))
            for reply in self.bus.query(keys.agent_image(self.session, agent_id, kf), request,
                                        timeout_s=1.0):
                try:
                    out.append((agent_id, protocol.decode(reply.payload,
                                                          expected=KeyframeImage)))
                    break
                except ProtocolError:
                    continue
        return out

    def _refresh(self, agent_id: str, a: _Agent, final: bool) -> None:
        """Trajectory (frames at their keyframe's latest pose) and sub-map points."""
        rows = [a.kf_poses[kf] @ T for _, (_, kf, T) in sorted(a.frames.items())
                if kf in a.kf_poses]
        if rows:
            self.scene.trajectory(agent_id, a.index, np.stack(rows)[:, :3, 3], static=False)
        now = self.clock()
        if final or now - a.points_at >= POINTS_EVERY_S:
            xyz, colours = a.points_world()
            self.scene.points(f"world/agents/{agent_id}/points", xyz, colours, static=False)
            a.points_at = now
            a.dirty = False

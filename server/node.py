"""The server's loop over a bus: agents' messages in, the back end's answers out.

`ServerNode` subscribes to every agent's topics (``agent/*/*``), to ``server/control`` and to
the agents' liveliness; `poll` decodes what arrived (a payload that fails validation is logged
with its key, counted and dropped, never raised), feeds `Backend.handle` in (agent, seq) order,
runs `Backend.step` and publishes the `Outgoing` messages on their keys. Keyframe images are
pulled with a bus query to the agent's image queryable (`fetch_image`). The server's
liveliness token carries the back end's state id (``alive/server/<state>``, kept by a restored
state): an agent that sees another id knows the acknowledged data is gone and streams its
whole state again (`cpslam.agent.daemon`). A status queryable
answers with `Backend.status()`. `finalise` runs the back end's final optimisation and writes
the run folder (`export_run`).

What peers key is bounded by the ``limits`` section: drop and traffic counters keep
``max_counter_keys`` keys (then "other"), drop warnings are throttled, presence is tracked for
at most ``max_agents`` agents, and the status reply is trimmed to ``status_reply_kb``
(`fit_status`). An image reply must be the keyframe that was asked for.

`run` is the daemon loop (poll until a `Control` asks to finalise or shut down); a driver
that needs lock-step determinism (``cpslam run``) calls `poll` itself instead.
"""

from __future__ import annotations

import copy
import logging
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from cpslam import protocol
from cpslam.common import durable
from cpslam.common.bounds import CappedCounter, LogThrottle
from cpslam.common.rundir import peak_rss_mb
from cpslam.common.trajectory import sensor_seconds
from cpslam.protocol import (
    Ack,
    Control,
    ErrorReply,
    GroupDecoder,
    KeyframeImage,
    KeyframeImageRequest,
    ProtocolError,
    Refusal,
    ServerUpdate,
    Status,
    UpdateAck,
    keys,
)
from cpslam.server.backend import Backend
from cpslam.server.bounds import fit_status, status_size
from cpslam.server.export import export_run
from cpslam.server.outgoing import Outgoing
from cpslam.server.persist import AckGate, StateWriter, detach
from cpslam.server.presence import AgentPresence
from cpslam.server.traffic import KeyCounter, PollTimes, bus_metrics

if TYPE_CHECKING:
    from cpslam.common.bus import Bus
    from cpslam.common.config import CpslamConfig
    from cpslam.server.result import FinalResult

__all__ = ["ServerNode"]

logger = logging.getLogger(__name__)


class ServerNode:
    """The back end on a bus.

    Args:
        cfg: the whole config (back end settings; ``transport.session`` and ``queue_size``).
        bus: an open bus (the node does not close it).
        run_dir: where `finalise` exports.
        image_timeout_s: how long a keyframe image query may take.
        state_path: where the accepted state is persisted (None: nothing is persisted). When
            set, acknowledgements are held back until the state that contains the acknowledged
            messages is durable (fsynced, see `StateWriter`), so an agent never drops a
            message the server could lose; a state already there is loaded by `start` (a
            restarted server goes on from it, or from the previous generation when the newest
            is torn).
        persist_every_s: at most one state snapshot per this many seconds (acks wait that
            long); it is also the retry interval while writes fail.
        persist_background: write the state on a writer thread, off the poll loop (False: in
            the poll loop, for tests that step it).
        persist_log_every_s: while state writes fail (full disk), one log line per this many
            seconds.
        backend_kwargs: passed to `Backend.from_config` (e.g. ``now`` or ``refine_pose``).
    """

    def __init__(self, cfg: CpslamConfig, bus: Bus, run_dir: str | Path,
                 image_timeout_s: float = 10.0, state_path: str | Path | None = None,
                 persist_every_s: float = 1.0, persist_background: bool = True,
                 persist_log_every_s: float = 60.0, **backend_kwargs: Any) -> None:
        self.cfg, self.bus, self.run_dir = cfg, bus, Path(run_dir)
        self.state_path = Path(state_path) if state_path is not None else None
        self.persist_every_s = float(persist_every_s)
        self.writer = self.acks = None
        if self.state_path is not None:
            self.writer = StateWriter(self.state_path, background=persist_background,
                                      retry_s=max(persist_every_s, 0.1),
                                      log_every_s=persist_log_every_s)
            self.acks = AckGate(self.writer, persist_every_s, self.publish)
        self.restored = False
        self._t_start = time.monotonic()
        self._status: dict = {}
        self._status_at = time.monotonic()
        self.session = keys.check_id(cfg.transport.session, "transport.session")
        self.image_timeout_s = image_timeout_s
        self.backend = Backend.from_config(cfg, self.fetch_image, **backend_kwargs)
        limits = cfg.limits
        self.presence = AgentPresence(self.session, limits.max_agents)
        self.status_budget = limits.status_reply_kb * 1024
        self.dropped = CappedCounter(limits.max_counter_keys)
        self._log = LogThrottle()
        self.control: Control | None = None
        self.step_errors = 0
        self.finalised: FinalResult | None = None
        self._lock = threading.RLock()  # the back end is touched by poll and the status query
        self._status_lock = threading.Lock()
        self._handles: list[Any] = []
        self._subs: list[Any] = []
        # Agents' messages per concrete key (daemon thread only).
        self._received = KeyCounter(limits.max_counter_keys)
        self.poll_times = PollTimes()

    # ------------------------------------------------------------------------- lifecycle

    def start(self) -> ServerNode:
        """Declare presence, subscriptions, the status queryable and the liveliness watch."""
        queue = max(self.cfg.transport.queue_size, 1024)
        s = self.session
        if self.state_path is not None and durable.has_generation(self.state_path):
            self._restore(self.state_path)
        self._subs = [self.bus.subscribe(keys.all_agents(s), queue_size=queue),
                      self.bus.subscribe(keys.server_control(s), queue_size=16)]
        self._handles = [
            *self._subs,
            self.bus.declare_queryable(keys.server_status(s), self._serve_status),
            self.bus.watch_liveliness(keys.alive_agents(s), on_join=self.presence.joined,
                                      on_leave=self.presence.left),
            self.bus.declare_liveliness(keys.alive_server(s, self.backend.state_id)),
        ]
        self._snapshot()
        logger.info("server node on session %s (state %d)", s, self.backend.state_id)
        return self

    def close(self) -> None:
        """Withdraw everything `start` declared (idempotent)."""
        for handle in self._handles:
            for name in ("close", "undeclare"):
                if hasattr(handle, name):
                    getattr(handle, name)()
                    break
        self._handles, self._subs = [], []
        self.backend.close()
        if self.writer is not None:
            self.writer.close()

    def run(self, poll_s: float = 0.05, stop: threading.Event | None = None) -> FinalResult | None:
        """Serve until a Control message (or `stop`) ends it; finalise unless told to shut
        down. Returns the final result (None on shutdown)."""
        while self.control is None and not (stop is not None and stop.is_set()):
            if not self.poll():
                # Idle: block on the agents' queue (not a sleep) so a message is handled as
                # soon as it arrives; control and liveliness are seen within poll_s.
                self._subs[0].wait(timeout=poll_s)
        if self.acks is not None and self.acks.pending:
            self.persist()
        if self.control is not None and self.control.action == "shutdown":
            logger.info("shutdown requested: %s", self.control.reason)
            return None
        return self.finalise()

    # ------------------------------------------------------------------------- work

    def poll(self) -> int:
        """Handle everything queued, run one back-end step, publish. Returns messages handled."""
        t0 = time.perf_counter()
        depth = len(self._subs[0])
        handled = self._poll()
        self.poll_times.add(time.perf_counter() - t0, depth, handled)
        return handled

    def _poll(self) -> int:
        self._liveliness()
        control_sub = self._subs[1]
        while (sample := control_sub.get(timeout=0)) is not None:
            msg = self._decode(sample.key, sample.payload, Control)
            if msg is not None:
                logger.info("control: %s (%s)", msg.action, msg.reason)
                self.control = msg
        batch, update_acks = [], []
        while (sample := self._subs[0].get(timeout=0)) is not None:
            self._received.add(sample.key, len(sample.payload))
            msg = self._decode(sample.key, sample.payload, None)
            if msg is None:
                continue
            try:
                agent, _ = keys.parse_agent_key(self.session, sample.key)
            except ProtocolError as exc:
                self._drop(sample.key, f"bad key: {exc}")
                continue
            if getattr(msg, "agent_id", None) != agent:
                self._drop(sample.key, "agent_id does not match the key")
                continue
            if isinstance(msg, UpdateAck):
                update_acks.append(msg)
                continue
            batch.append((agent, int(msg.seq), msg, len(sample.payload)))
        batch.sort(key=lambda item: item[:2])
        with self._lock:
            for ack in update_acks:
                self.backend.update_acked(ack.agent_id, ack.incarnation, ack.update_seq)
            for _, _, msg, nbytes in batch:
                out = self.backend.handle(msg, nbytes)
                if self.acks is not None:
                    for o in out:
                        if isinstance(o.message, Ack):
                            self.acks.hold(o)
                    out = [o for o in out if not isinstance(o.message, Ack)]
                self.publish(out)
            try:
                self.publish(self.backend.step())
            except Exception:  # noqa: BLE001 - the server outlives a failing step
                self.step_errors += 1
                logger.exception("back-end step failed (%d so far)", self.step_errors)
            if self.acks is not None:
                self.acks.tick(self._state_snapshot)
            self._snapshot()
        return len(batch) + len(update_acks)

    def persist(self, timeout_s: float | None = None) -> bool:
        """Snapshot the accepted state now, wait (up to `timeout_s`) for its write and release
        the acks it covers. Returns whether it is durable (False: a failed write; the acks
        stay held and the writer retries)."""
        if self.acks is None:
            return True
        with self._lock:
            gen = self.acks.submit(self._state_snapshot())
        ok = self.writer.wait(gen, timeout_s)
        with self._lock:
            self.acks.release()
        return ok

    def _state_snapshot(self) -> dict:
        # The arrays in state_dict are copies; detach copies the containers, so the loop
        # may go on changing the back end while the writer thread pickles this.
        return detach(self.backend.state_dict())

    def publish(self, out: list[Outgoing]) -> None:
        """Encode and put each outgoing message on its key (too large: logged, dropped). A
        group's decoder goes to each member on its own key, and once on the group's key for
        observers (a put no one subscribes to costs nothing on the wire)."""
        for item in out:
            msg = item.message
            if item.scope == "group" and isinstance(msg, GroupDecoder):
                group = self.backend.groups.groups.get(item.target)
                members = list(group.members) if group is not None else []
                targets = [keys.server_group_decoder(self.session, item.target),
                           *(keys.server_agent_group_decoder(self.session, m) for m in members)]
            elif isinstance(msg, ServerUpdate):
                targets = [keys.server_agent_update(self.session, item.target)]
            elif isinstance(msg, Ack):
                targets = [keys.server_agent_ack(self.session, item.target)]
            elif isinstance(msg, Refusal):
                targets = [keys.server_agent_refusal(self.session, item.target)]
            else:
                logger.error("no key for outgoing %s to %s", type(msg).__name__, item.target)
                continue
            try:
                payload = protocol.encode(msg)
                for key in targets:
                    self.bus.publish(key, payload)
            except ProtocolError as exc:
                logger.error("could not send %s on %s: %s", type(msg).__name__, targets[0], exc)

    def fetch_image(self, agent_id: str, kf_id: int) -> KeyframeImage | None:
        """A keyframe's RGB-D from the agent's image queryable; None if it cannot be had."""
        record = self.backend.registry.agents.get(agent_id)
        if self.presence.gone(agent_id) or (record is not None and not record.alive):
            # A departed agent cannot answer: do not wait out the query timeout.
            logger.debug("image %s/%d: agent has left", agent_id, kf_id)
            return None
        request = KeyframeImageRequest(agent_id=agent_id, kf_id=int(kf_id),
                                       scale=self.cfg.loop.image_scale)
        key = keys.agent_image(self.session, agent_id, int(kf_id))
        replies = self.bus.query(key, protocol.encode(request), timeout_s=self.image_timeout_s)
        for reply in replies:
            if not reply.ok:
                logger.warning("image %s/%d: agent failed: %s", agent_id, kf_id,
                               reply.payload[:200].decode(errors="replace"))
                continue
            msg = self._decode(key, reply.payload, (KeyframeImage, ErrorReply))
            if isinstance(msg, KeyframeImage):
                if (msg.agent_id, int(msg.kf_id)) != (agent_id, int(kf_id)):
                    self._drop(key, f"image reply is {msg.agent_id}/{msg.kf_id}, expected "
                                    f"{agent_id}/{kf_id}")
                    continue
                return msg
            if isinstance(msg, ErrorReply):
                logger.warning("image %s/%d: %s %s", agent_id, kf_id, msg.code, msg.reason)
        if not replies:
            logger.warning("image %s/%d: no reply within %.1f s", agent_id, kf_id,
                           self.image_timeout_s)
        return None

    def finalise(self, mark_complete: bool = True) -> FinalResult:
        """Final optimisation and export into the run folder (once); without `mark_complete`
        metrics.json is left to the caller (`export.write_metrics`, after its own outputs)."""
        with self._lock:
            if self.finalised is None:
                self.persist()
                self.publish(self.backend.step())
                self.finalised = self.backend.finalise()
                self.finalised.metrics["bus"] = bus_metrics(
                    self.session, self.bus.stats(), time.monotonic() - self._t_start,
                    self._received.table(), self.dropped,
                    {a: sensor_seconds(e[2] for e in rec.frames.values())
                     for a, rec in self.backend.registry.agents.items()})
                self.finalised.metrics["process"] = {
                    "peak_rss_mb": peak_rss_mb(), "uptime_s": time.monotonic() - self._t_start,
                    "cpu_s": _cpu_seconds(), "poll": self.poll_times.summary()}
                export_run(self.finalised, self.run_dir, mark_complete=mark_complete)
        return self.finalised

    # ------------------------------------------------------------------------- helpers

    def _restore(self, path: Path) -> None:
        import io

        import torch

        try:
            state, path = durable.load_generation(
                path, lambda data: torch.load(io.BytesIO(data), weights_only=True))
            self.backend.load_state_dict(state)
        except Exception as exc:  # noqa: BLE001 - a bad state file must not be half-loaded
            raise RuntimeError(f"{path}: cannot restore the server state ({exc}); move the "
                               "file and its .prev away to start this run afresh") from exc
        self.restored = True
        status = self.backend.status()
        logger.info("restored server state from %s: agents %s, groups %d", path,
                    ", ".join(sorted(status.get("agents", {}))) or "none",
                    len(status.get("groups", {})))

    def _decode(self, key: str, payload: bytes, expected: Any) -> Any:
        try:
            return protocol.decode(payload, expected=expected)
        except ProtocolError as exc:
            self._drop(key, str(exc))
            return None

    def _drop(self, key: str, reason: str) -> None:
        counted = self.dropped.add(key)
        held = self._log.allow("drop")
        if held is not None:
            logger.warning("dropped message on %s (%d so far on %s; %d other drops not logged): "
                           "%s", key, self.dropped[counted], counted, held, reason[:500])

    def _serve_status(self, key: str, payload: bytes | None) -> bytes:
        # Never wait for a long back-end step: answer from the snapshot of the last poll,
        # with presence as the liveliness callbacks saw it a moment ago.
        with self._status_lock:
            summary = copy.deepcopy(self._status)
        present = self.presence.alive()
        for agent, alive in present.items():
            if agent in summary.get("agents", {}):
                summary["agents"][agent]["alive"] = alive
        summary["bus_dropped"] = dict(self.dropped)
        if self.writer is not None:  # a full disk shows here, not only in the log
            summary["persist"] = {"generation": self.writer.durable_gen,
                                  "failures": self.writer.failures}
        summary["stale_s"] = round(time.monotonic() - self._status_at, 3)
        summary = fit_status(summary, status_size, self.status_budget)
        return protocol.encode(Status(stamp=time.time(), summary=summary))

    def _snapshot(self) -> None:
        status = self.backend.status()
        with self._status_lock:
            self._status, self._status_at = status, time.monotonic()

    def _liveliness(self) -> None:
        for kind, agent in self.presence.take_events():
            if kind == "leave":
                with self._lock:
                    self.backend.agent_left(agent)


def _cpu_seconds() -> float:
    """User plus system CPU time of this process so far (s; every thread)."""
    import resource

    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime

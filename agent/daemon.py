"""The networked agent: one sequence streamed to a `cpslam-server` over Zenoh.

1. Open a client session to the server's endpoint, retrying until ``wait_timeout_s``
   (agents may start before the server); "waiting for the server at …" is logged as soon as
   the first attempt has not succeeded within a second.
2. Wait until the server's liveliness token is seen (logged likewise when it takes longer
   than a second). A stop request (SIGINT/SIGTERM) ends either wait within a fraction of a
   second.
3. For every frame: apply what the server pushed, resend what is unacknowledged
   ``transport.resend_after_s`` after it was sent, track and map, publish. While the outbox
   is full (``transport.outbox_messages`` / ``outbox_mb``) no frame is taken until acks make
   room (logged once per stall): accepted data is never dropped.
4. While the server's token is gone, messages wait in the outbox. When it comes back (restart,
   network loss) under the same state id, resend every message it has not acknowledged (the
   server drops what it already had); under another state id (a server restarted without its
   state) stream the whole state again as a new incarnation (`cpslam.agent.rebase`).
5. At the end: send the last frame poses and wait until everything is acknowledged, then
   write ``RUN/agent_<id>/`` (as a standalone run, plus bytes sent per key expression).

Exit codes (`cpslam.common.cli.ExitCode`): 0 done and acknowledged, 3 no server within
``wait_timeout_s``, 4 the server did not acknowledge everything within ``ack_timeout_s``
(outputs are written all the same), 5 the server refused this incarnation (the agent id
already streams into the session as another incarnation: restart with a new id), 130
interrupted (outputs written once streaming has begun).
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

from cpslam.common.bus import open_client
from cpslam.common.bus.factory import ANNOUNCE_AFTER_S, STOP_CHECK_S
from cpslam.common.cli import ExitCode
from cpslam.protocol import ProtocolError, keys

if TYPE_CHECKING:
    from cpslam.agent.node import AgentNode
    from cpslam.common.bus import Bus
    from cpslam.common.config import CpslamConfig
    from cpslam.common.datasets import RGBDSequence

__all__ = ["ServerPresence", "run_networked"]

logger = logging.getLogger(__name__)


class ServerPresence:
    """Tracks the server's liveliness token: whether it is up, how often it (re)appeared, the
    state id it came with, and how many appearances the agent has answered (`handled`).
    `wait_for` blocks until a condition on these holds; waiters wake whenever the token comes
    or goes."""

    def __init__(self, bus: Bus, session: str) -> None:
        self._cond = threading.Condition()
        self.session = session
        self.up = False
        self.joins = 0
        self.handled = 0
        self.state: int | None = None
        self._watch = bus.watch_liveliness(keys.alive_servers(session), on_join=self._join,
                                           on_leave=self._leave)

    def _join(self, key: str) -> None:
        try:
            state = keys.parse_alive_server(self.session, key)
        except ProtocolError as exc:
            logger.warning("ignoring server liveliness token %s: %s", key, exc)
            return
        with self._cond:
            self.up, self.joins, self.state = True, self.joins + 1, state
            self._cond.notify_all()

    def _leave(self, _key: str) -> None:
        with self._cond:
            self.up = False
            self._cond.notify_all()

    def settled(self) -> bool:
        """The server is up and its latest appearance was answered (messages may go out)."""
        return self.up and self.handled == self.joins

    def wait(self, timeout_s: float, stop: threading.Event | None = None) -> bool:
        """Block until the server is present (True), or `timeout_s` passed or `stop` was set
        (False; `stop` is looked at every `STOP_CHECK_S`)."""
        return self.wait_for(lambda p: p.up, timeout_s, stop)

    def wait_for(self, predicate: Callable[[ServerPresence], bool], timeout_s: float,
                 stop: threading.Event | None = None) -> bool:
        """Block until `predicate(self)` holds (True; it is called with the lock held, after
        each change of the token), or `timeout_s` passed or `stop` was set (False; `stop` is
        looked at every `STOP_CHECK_S`)."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while not predicate(self):
                remaining = deadline - time.monotonic()
                if remaining <= 0 or (stop is not None and stop.is_set()):
                    return False
                self._cond.wait(remaining if stop is None else min(remaining, STOP_CHECK_S))
            return True

    def close(self) -> None:
        self._watch.close()


def run_networked(cfg: CpslamConfig, seq: RGBDSequence, agent_id: str, run_dir: Path,
                  device: str, wait_timeout_s: float = 300.0, ack_timeout_s: float = 120.0,
                  show_progress: bool = True, stop: threading.Event | None = None,
                  on_frame: Callable[..., None] | None = None, bus: Bus | None = None,
                  resume: Path | None = None) -> int:
    """Run one agent against a server; returns the exit code (see the module docstring).
    `on_frame(frame, result, odometry)` is called after each frame (`run.rerun`). `bus`: an
    open bus to use (not closed here) instead of a client session to the configured endpoints;
    `resume`: an earlier run's ``agent_<id>/state.pt`` to continue (same incarnation, seq
    counter and outbox, `AgentNode.resume`); without it the agent is a new incarnation."""
    import torch

    from cpslam.agent.node import AgentNode
    from cpslam.common.logs import make_progress

    stop = stop if stop is not None else threading.Event()
    own_bus = bus is None
    if bus is None:
        bus = open_client(cfg.transport, wait_timeout_s, f"agent {agent_id}", stop,
                          cfg.limits)
    if bus is None:
        if stop.is_set():
            logger.info("agent %s: interrupted while waiting for the server", agent_id)
            return ExitCode.INTERRUPTED
        return ExitCode.NO_SERVER
    with bus if own_bus else contextlib.nullcontext(bus):
        presence = ServerPresence(bus, cfg.transport.session)
        t_wait = time.monotonic()
        found = presence.wait(min(ANNOUNCE_AFTER_S, wait_timeout_s), stop)
        if not found and not stop.is_set():
            logger.info("agent %s: connected to %s; waiting for a cpslam-server on session %r "
                        "(up to %.0f s) …", agent_id, ", ".join(cfg.transport.connect) or
                        "tcp/127.0.0.1:7447", cfg.transport.session, wait_timeout_s)
            found = presence.wait(max(t_wait + wait_timeout_s - time.monotonic(), 0.0), stop)
        if not found:
            presence.close()
            if stop.is_set():
                logger.info("agent %s: interrupted while waiting for the server", agent_id)
                return ExitCode.INTERRUPTED
            logger.error("agent %s: connected, but no cpslam-server on session %r within %.0f s",
                         agent_id, cfg.transport.session, wait_timeout_s)
            return ExitCode.NO_SERVER
        logger.info("agent %s: server found (%.1f s); streaming %d frames", agent_id,
                    time.monotonic() - t_wait, len(seq))
        node = AgentNode(cfg, seq, bus, agent_id, run_dir, device)
        if resume is not None:
            node.resume(resume)
        node.start()
        node.online = presence.settled
        # A resumed agent resends its earlier run's outbox (the server may never have had it),
        # or its whole state to a server that lost it.
        _answer_server(node, presence, resend=resume is not None)
        torch.manual_seed(cfg.run.seed)
        interrupted = False
        acked = False
        try:
            with make_progress(disable=not show_progress) as bar:
                task = bar.add_task(f"agent {agent_id}", total=len(seq), info="")
                t0 = time.perf_counter()
                for i, frame in enumerate(node.frames()):
                    if stop.is_set():
                        interrupted = True
                        break
                    _answer_server(node, presence)
                    node.poll()
                    if presence.settled():
                        node.resend_due()
                    _wait_for_room(node, presence, stop)
                    if node.refused is not None or stop.is_set():
                        interrupted = node.refused is None
                        break
                    result = node.step(frame)
                    if on_frame is not None:
                        on_frame(frame, result, node.odometry)
                    fps = (i + 1) / max(time.perf_counter() - t0, 1e-9)
                    away = "" if presence.up else "  (server away)"
                    bar.update(task, advance=1, info=f"{fps:.2f} fps  loss "
                               f"{result.track_loss:.4f}  outbox {len(node.link.outbox)}{away}")
            if node.refused is None and not interrupted:
                node.flush()
                acked = _wait_acked(node, presence, ack_timeout_s, stop)
        finally:
            node.write_outputs(extra={"bus": bus.stats(),
                                      "sent_bytes_per_sensor_s": node.sent_per_sensor_s(
                                          bus.stats()),
                                      "unacknowledged": len(node.link.outbox),
                                      "resent": node.link.outbox.resent,
                                      "ignored_acks": node.link.outbox.ignored_acks,
                                      "dropped_by_server": len(node.link.outbox.dropped_by_server),
                                      "incarnation": node.incarnation,
                                      "server_rejoins": max(presence.joins - 1, 0),
                                      "stream_restarts": node.restarts})
            node.close()
            presence.close()
    if node.refused is not None:
        logger.error("agent %s: refused by the server (%s)", agent_id, node.refused)
        return ExitCode.REFUSED
    if interrupted or stop.is_set():
        return ExitCode.INTERRUPTED
    if not acked:
        logger.error("agent %s: %d messages were never acknowledged", agent_id,
                     len(node.link.outbox))
        return ExitCode.UNACKNOWLEDGED
    logger.info("agent %s: done, everything acknowledged", agent_id)
    return 0


def _answer_server(node: AgentNode, presence: ServerPresence, resend: bool = True) -> None:
    """Once per appearance of the server: under the state id the stream went to (or the first
    time, with `resend`), resend what it has not acknowledged; under another one, stream the
    whole state again (`AgentNode.restart_stream`)."""
    joins, state = presence.joins, presence.state
    if joins == presence.handled or not presence.up:
        return
    link = node.link
    old = link.server_state
    lost = old is not None and state != old and link.next_seq > 0
    link.server_state = state
    presence.handled = joins  # before sending: `node.online` lets the messages out
    if lost:
        logger.warning("agent %s: the server came back as state %d, the stream went to state "
                       "%d: what it acknowledged is gone; streaming everything again",
                       node.agent_id, state, old)
        n = node.restart_stream()
        logger.info("agent %s: sent %d messages as incarnation %d", node.agent_id, n,
                    node.incarnation)
    elif resend and (n := node.resend()):
        logger.info("agent %s: server is back; resent %d unacknowledged messages",
                    node.agent_id, n)


def _wait_for_room(node: AgentNode, presence: ServerPresence, stop: threading.Event) -> None:
    """While the outbox is full: apply what arrives, resend what is due."""
    outbox = node.link.outbox
    if not outbox.full():
        return
    logger.warning("agent %s: outbox full (%d messages, %.1f MiB unacknowledged); waiting for "
                   "acks before the next frame", node.agent_id, len(outbox), outbox.bytes / 2**20)
    t0 = time.monotonic()
    while outbox.full() and node.refused is None and not stop.is_set():
        _answer_server(node, presence)
        if not node.poll():
            node.wait_for_server_message(0.1)
        if presence.settled():
            node.resend_due()
    logger.info("agent %s: outbox has room again after %.1f s", node.agent_id,
                time.monotonic() - t0)


def _wait_acked(node: AgentNode, presence: ServerPresence, timeout_s: float,
                stop: threading.Event) -> bool:
    """Until the outbox is empty: apply what arrives, answer a server that came back and resend
    what is unacknowledged ``transport.resend_after_s`` after it was sent (a lost ack)."""
    link = node.link
    deadline = time.monotonic() + timeout_s
    while (link.outbox and time.monotonic() < deadline and not stop.is_set()
           and node.refused is None):
        _answer_server(node, presence)
        if not node.poll():
            node.wait_for_server_message(0.1)
        if link.outbox and presence.settled():
            node.resend_due()
    return not link.outbox

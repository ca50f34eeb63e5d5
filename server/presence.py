"""Which agents' liveliness tokens the server sees, fed by the bus's liveliness callbacks.

The callbacks run on the bus's threads; `AgentPresence` records each join or leave under its
own lock and queues the event for the poll loop (`take_events`). Presence is keyed by peers'
tokens, so it is bounded like the registry: at most ``max_agents`` agents, further ones are
refused with a throttled warning, and malformed keys keep a log line only while there is
room (``4 * max_agents`` queued events).
"""

from __future__ import annotations

import logging
import threading

from cpslam.common.bounds import LogThrottle
from cpslam.protocol import ProtocolError, keys

__all__ = ["AgentPresence"]

logger = logging.getLogger(__name__)


class AgentPresence:
    """Agents' liveliness as the callbacks saw it, and the events the poll loop has not taken.

    Args:
        session: the session whose ``alive/agent/<id>`` keys are parsed.
        max_agents: most agents tracked.
    """

    def __init__(self, session: str, max_agents: int) -> None:
        self.session, self.max_agents = session, max_agents
        self._alive: dict[str, bool] = {}
        self._events: list[tuple[str, str]] = []  # (join|leave, key)
        self._lock = threading.Lock()
        self._log = LogThrottle()

    def joined(self, key: str) -> None:
        """Liveliness callback: a token appeared on `key`."""
        self._event("join", key, True)

    def left(self, key: str) -> None:
        """Liveliness callback: the token on `key` went away."""
        self._event("leave", key, False)

    def gone(self, agent: str) -> bool:
        """Whether `agent`'s token was seen and has gone."""
        with self._lock:
            return self._alive.get(agent) is False

    def alive(self) -> dict[str, bool]:
        """Agent -> whether its token is there now (a copy)."""
        with self._lock:
            return dict(self._alive)

    def take_events(self) -> list[tuple[str, str]]:
        """The (join|leave, agent) events since the last call; malformed keys are logged."""
        with self._lock:
            events, self._events = self._events, []
        out = []
        for kind, key in events:
            try:
                agent = keys.parse_alive_agent(self.session, key)
            except ProtocolError as exc:
                logger.warning("liveliness key %s: %s", key, exc)
                continue
            logger.info("agent %s %s", agent, "joined" if kind == "join" else "left")
            out.append((kind, agent))
        return out

    def _event(self, kind: str, key: str, alive: bool) -> None:
        try:
            agent = keys.parse_alive_agent(self.session, key)
        except ProtocolError:
            agent = None  # reported when the event is taken
        with self._lock:
            refused = (agent is not None and agent not in self._alive
                       and len(self._alive) >= self.max_agents)
            if not refused:
                if agent is not None:
                    self._alive[agent] = alive
                # An admitted agent's event is always kept (a lost leave would keep a round
                # waiting for it); a malformed key only gets its log line while there is room.
                if agent is not None or len(self._events) < 4 * self.max_agents:
                    self._events.append((kind, key))
        if refused and self._log.allow("presence cap") is not None:
            logger.warning("liveliness of agent %s ignored: already %d agents (limits."
                           "max_agents)", agent, self.max_agents)

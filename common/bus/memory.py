"""The bus inside one process: several sessions on a shared hub, Zenoh's semantics without sockets.

Agents and the server of an integration test each get their own `InMemoryBus` attached to one
`InMemoryNetwork`. Like Zenoh, a session also receives its own publications, queries reach
matching queryables of every session including the querier's, and a session's liveliness
tokens vanish when it closes. Samples and liveliness changes are delivered by the network's
dispatcher thread, never on the publisher's thread, so code that silently relies on synchronous
delivery fails here as it would over Zenoh.
"""

from __future__ import annotations

import itertools
import logging
import queue
import threading
import time
from collections import Counter
from collections.abc import Callable

from cpslam.common.bus.interface import Bus, Reply
from cpslam.common.bus.keyexpr import intersects
from cpslam.common.bus.liveliness import LivelinessWatcher

logger = logging.getLogger(__name__)

__all__ = ["InMemoryNetwork", "InMemoryBus"]

Receive = Callable[[str, bytes], None]
Serve = Callable[[str, bytes | None], Reply | None]


class InMemoryNetwork:
    """The shared hub: routing tables plus one dispatcher thread (started while sessions exist)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._ids = itertools.count()
        self._sessions: set[int] = set()
        self._subs: dict[int, tuple[int, str, Receive]] = {}
        self._queryables: dict[int, tuple[int, str, Serve]] = {}
        self._tokens: dict[int, tuple[int, str]] = {}
        self._token_count: Counter[str] = Counter()
        self._watchers: dict[int, tuple[int, LivelinessWatcher]] = {}
        self._events: queue.SimpleQueue[Callable[[], None] | None] = queue.SimpleQueue()
        self._dispatcher: threading.Thread | None = None

    # -- sessions ----------------------------------------------------------------------------

    def attach(self) -> int:
        """Register a session; returns its id."""
        with self._lock:
            session = next(self._ids)
            self._sessions.add(session)
            if self._dispatcher is None:
                # A fresh queue per dispatcher: a previous one may still be draining its own.
                self._events = queue.SimpleQueue()
                self._dispatcher = threading.Thread(
                    target=_dispatch, args=(self._events,), name="inmemory-bus", daemon=True
                )
                self._dispatcher.start()
        return session

    def detach(self, session: int) -> None:
        """Drop everything a session declared (its tokens leave); idempotent."""
        with self._lock:
            if session not in self._sessions:
                return
            self._sessions.discard(session)
            for table in (self._subs, self._queryables, self._watchers):
                for entry in [e for e, v in table.items() if v[0] == session]:
                    del table[entry]
            for entry in [e for e, (owner, _) in self._tokens.items() if owner == session]:
                self._remove_token_locked(entry)
            if not self._sessions and self._dispatcher is not None:
                # Pending events are still delivered: the sentinel queues up behind them.
                self._events.put(None)
                self._dispatcher = None

    # -- routing -------------------------------------------------------------------------------

    def publish(self, key: str, payload: bytes) -> None:
        with self._lock:
            targets = [recv for _, expr, recv in self._subs.values() if intersects(expr, key)]
            if targets:
                self._events.put(lambda: _deliver_all(targets, key, payload))

    def add_subscription(self, session: int, key_expr: str, receive: Receive) -> int:
        with self._lock:
            entry = next(self._ids)
            self._subs[entry] = (session, key_expr, receive)
        return entry

    def add_queryable(self, session: int, key_expr: str, serve: Serve) -> int:
        with self._lock:
            entry = next(self._ids)
            self._queryables[entry] = (session, key_expr, serve)
        return entry

    def matching_queryables(self, key_expr: str) -> list[Serve]:
        with self._lock:
            return [s for _, expr, s in self._queryables.values() if intersects(expr, key_expr)]

    def add_token(self, session: int, key: str) -> int:
        with self._lock:
            entry = next(self._ids)
            self._tokens[entry] = (session, key)
            self._token_count[key] += 1
            if self._token_count[key] == 1:
                self._notify_locked(key, joined=True)
        return entry

    def add_watcher(self, session: int, watcher: LivelinessWatcher) -> int:
        with self._lock:
            entry = next(self._ids)
            self._watchers[entry] = (session, watcher)
            present = [k for k in self._token_count if intersects(watcher.key_expr, k)]
            # Queued under the lock, so history always precedes later joins/leaves.
            self._events.put(lambda: [watcher.joined(k) for k in present])
        return entry

    def remove(self, entry: int) -> None:
        """Undeclare a subscription, queryable, token or watcher by its entry id."""
        with self._lock:
            self._subs.pop(entry, None)
            self._queryables.pop(entry, None)
            self._watchers.pop(entry, None)
            if entry in self._tokens:
                self._remove_token_locked(entry)

    def _remove_token_locked(self, entry: int) -> None:
        _, key = self._tokens.pop(entry)
        self._token_count[key] -= 1
        if self._token_count[key] == 0:
            del self._token_count[key]
            self._notify_locked(key, joined=False)

    def _notify_locked(self, key: str, joined: bool) -> None:
        watchers = [w for _, w in self._watchers.values() if intersects(w.key_expr, key)]
        if watchers:
            if joined:
                self._events.put(lambda: [w.joined(key) for w in watchers])
            else:
                self._events.put(lambda: [w.left(key) for w in watchers])


def _dispatch(events: queue.SimpleQueue[Callable[[], None] | None]) -> None:
    while True:
        event = events.get()
        if event is None:
            return
        try:
            event()
        except Exception:
            logger.exception("in-memory bus delivery failed")


def _deliver_all(targets: list[Receive], key: str, payload: bytes) -> None:
    for receive in targets:
        try:
            receive(key, payload)
        except Exception:
            logger.exception("in-memory bus delivery of %r failed", key)


class InMemoryBus(Bus):
    """One session on an `InMemoryNetwork` (a private network when none is given); the other
    arguments are `Bus`'s."""

    def __init__(self, network: InMemoryNetwork | None = None, close_timeout_s: float = 5.0,
                 max_payload_bytes: int | None = None, max_queue_bytes: int | None = None,
                 max_counter_keys: int = 1024) -> None:
        super().__init__(close_timeout_s, max_payload_bytes, max_queue_bytes, max_counter_keys)
        self.network = network if network is not None else InMemoryNetwork()
        self._session = self.network.attach()

    def _transport_publish(self, key: str, payload: bytes) -> None:
        self.network.publish(key, payload)

    def _transport_subscribe(self, key_expr: str, receive: Receive) -> Callable[[], None]:
        entry = self.network.add_subscription(self._session, key_expr, receive)
        return lambda: self.network.remove(entry)

    def _transport_queryable(self, key_expr: str, serve: Serve) -> Callable[[], None]:
        entry = self.network.add_queryable(self._session, key_expr, serve)
        return lambda: self.network.remove(entry)

    def _transport_query(
        self, key_expr: str, payload: bytes | None, timeout_s: float
    ) -> list[Reply]:
        serves = self.network.matching_queryables(key_expr)
        if not serves:
            return []
        results: queue.SimpleQueue[Reply | None] = queue.SimpleQueue()

        def run(serve: Serve) -> None:
            reply = None
            try:
                reply = serve(key_expr, payload)
            except Exception:
                logger.exception("in-memory queryable for %r failed", key_expr)
            results.put(reply)

        # One thread per queryable, as Zenoh serves each on its own: a hung handler only costs
        # the querier its timeout, and a handler may itself use the bus.
        for serve in serves:
            threading.Thread(target=run, args=(serve,), name="inmemory-query", daemon=True).start()
        replies: list[Reply] = []
        deadline = time.monotonic() + timeout_s
        for _ in serves:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                break
            try:
                reply = results.get(timeout=remaining)
            except queue.Empty:
                break
            if reply is not None:
                replies.append(reply)
        return replies

    def _transport_token(self, key: str) -> Callable[[], None]:
        entry = self.network.add_token(self._session, key)
        return lambda: self.network.remove(entry)

    def _transport_watch(self, watcher: LivelinessWatcher) -> Callable[[], None]:
        entry = self.network.add_watcher(self._session, watcher)
        return lambda: self.network.remove(entry)

    def _transport_close(self, deadline: float) -> None:
        self.network.detach(self._session)  # immediate: nothing here can hang

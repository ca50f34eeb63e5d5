"""The bus both daemons talk through: publish/subscribe, query/reply and liveliness over bytes.

`Bus` does everything that must behave the same whatever carries the bytes — key validation,
byte counters, wrapping user handlers, the bounded subscription queues, idempotent and ordered
closing — and leaves only the transport to `ZenohBus` and `InMemoryBus` (the `_transport_*`
methods). That is what keeps the in-memory fake from drifting away from the real thing; the
contract test suite runs against both.

Counters (`stats()`) are kept under the key expression the *local* call named: publications
under their key, subscriptions under the subscribed expression, queries under the queried
expression (request payloads sent, reply payloads received) and queryables under their declared
expression (request payloads received, reply payloads sent).
"""

from __future__ import annotations

import logging
import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass

from cpslam.common.bounds import CappedCounter
from cpslam.common.bus.keyexpr import reply_key, validate_key, validate_key_expr
from cpslam.common.bus.liveliness import LivelinessToken, LivelinessWatcher, MemberCallback
from cpslam.common.bus.subscription import Sample, Subscription

logger = logging.getLogger(__name__)

__all__ = [
    "Bus",
    "BusError",
    "BusClosedError",
    "Reply",
    "Queryable",
    "QueryHandler",
]

# (query key expression, request payload or None) -> reply payload, or None for no reply.
QueryHandler = Callable[[str, bytes | None], bytes | None]


class BusError(RuntimeError):
    """The transport failed (could not open, could not reach the other side)."""


class BusClosedError(BusError):
    """An operation on a bus that was closed."""


@dataclass(frozen=True)
class Reply:
    """One answer to a query. `ok` is False when the queryable's handler raised; the payload
    then holds the error text (UTF-8)."""

    key: str
    payload: bytes
    ok: bool = True


class Queryable:
    """A declared queryable; `close()` withdraws it."""

    def __init__(self, key_expr: str, undeclare: Callable[[], None]) -> None:
        self.key_expr = key_expr
        self._undeclare = undeclare
        self._lock = threading.Lock()
        self._closed = False

    @property
    def closed(self) -> bool:
        return self._closed

    def close(self) -> None:
        """Withdraw the queryable. Idempotent."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
        self._undeclare()

    def __enter__(self) -> Queryable:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class _Traffic:
    """Thread-safe message and byte counters per key expression."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._sent: dict[str, list[int]] = {}
        self._received: dict[str, list[int]] = {}

    def sent(self, key: str, nbytes: int) -> None:
        self._add(self._sent, key, nbytes)

    def received(self, key: str, nbytes: int) -> None:
        self._add(self._received, key, nbytes)

    def _add(self, table: dict[str, list[int]], key: str, nbytes: int) -> None:
        with self._lock:
            entry = table.setdefault(key, [0, 0])
            entry[0] += 1
            entry[1] += nbytes

    def snapshot(self) -> dict[str, dict[str, dict[str, int]]]:
        with self._lock:
            return {
                name: {k: {"messages": m, "bytes": b} for k, (m, b) in table.items()}
                for name, table in (("sent", self._sent), ("received", self._received))
            }


def _as_bytes(payload: object, what: str) -> bytes:
    if isinstance(payload, bytes):
        return payload
    if isinstance(payload, bytearray | memoryview):
        # Copy: the caller may reuse its buffer as soon as publish() returns.
        return bytes(payload)
    raise TypeError(f"{what} must be bytes, bytearray or memoryview, got {type(payload).__name__}")


class Bus(ABC):
    """A session on the message bus. Thread-safe; use as a context manager or call `close()`.

    Args:
        close_timeout_s: `close()` returns within this long, whatever hangs (the transport's
            own close and busy subscription callbacks share the one deadline).
        max_payload_bytes: larger payloads are refused by `publish` (`ValueError`) and
            dropped on receive (counted in `stats()["oversized"]`, logged); None: no limit.
        max_queue_bytes: payload bytes each subscription queue may hold besides its sample
            count (`Subscription`); None: no byte limit.
        max_counter_keys: distinct keys the oversized-message counter keeps (the rest count
            as "other"), so a peer inventing keys cannot grow it.
    """

    def __init__(self, close_timeout_s: float = 5.0,
                 max_payload_bytes: int | None = None, max_queue_bytes: int | None = None,
                 max_counter_keys: int = 1024) -> None:
        if close_timeout_s <= 0:
            raise ValueError(f"close_timeout_s must be > 0, got {close_timeout_s}")
        if max_payload_bytes is not None and max_payload_bytes <= 0:
            raise ValueError(f"max_payload_bytes must be > 0, got {max_payload_bytes}")
        self.close_timeout_s = float(close_timeout_s)
        self.max_payload_bytes = max_payload_bytes
        self.max_queue_bytes = max_queue_bytes
        self._lock = threading.RLock()
        self._closing = False
        self._traffic = _Traffic()
        self._subscriptions: set[Subscription] = set()
        self._queryables: set[Queryable] = set()
        self._tokens: set[LivelinessToken] = set()
        self._watchers: set[LivelinessWatcher] = set()
        self._sub_undeclare: dict[Subscription, Callable[[], None]] = {}
        self._dropped_by_closed: dict[str, int] = {}
        self._dropped_oversized = CappedCounter(max_counter_keys)

    # -- public interface ----------------------------------------------------------------

    def publish(self, key: str, payload: bytes) -> None:
        """Send `payload` to every subscription whose key expression matches `key` (concrete)."""
        validate_key(key, "publish key")
        data = _as_bytes(payload, "payload")
        if self.max_payload_bytes is not None and len(data) > self.max_payload_bytes:
            raise ValueError(f"publish on {key!r}: {len(data)} bytes exceed the bus limit of "
                             f"{self.max_payload_bytes} (transport.max_message_mb)")
        self._check_open("publish")
        self._transport_publish(key, data)
        self._traffic.sent(key, len(data))

    def subscribe(
        self,
        key_expr: str,
        callback: Callable[[Sample], object] | None = None,
        queue_size: int = 64,
    ) -> Subscription:
        """Receive publications matching `key_expr` into a bounded drop-oldest queue.

        With `callback`, samples are handed to it on the subscription's own thread; without,
        pull them with `Subscription.get()` or iterate.
        """
        validate_key_expr(key_expr, "subscription key expression")
        with self._lock:
            self._check_open("subscribe")
            sub = Subscription(key_expr, queue_size, callback, on_close=self._forget_subscription,
                               max_bytes=self.max_queue_bytes)
            undeclare = self._transport_subscribe(key_expr, self._make_receiver(sub))
            self._subscriptions.add(sub)
            self._sub_undeclare[sub] = self._guard(undeclare, f"subscription on {key_expr!r}")
        return sub

    def declare_queryable(self, key_expr: str, handler: QueryHandler) -> Queryable:
        """Answer queries matching `key_expr` with `handler(query_key, payload) -> bytes|None`.

        The handler runs on the transport's thread; an exception becomes an error reply
        (`Reply.ok == False`) and is logged; returning None sends no reply.
        """
        validate_key_expr(key_expr, "queryable key expression")
        if not callable(handler):
            raise TypeError(f"queryable handler for {key_expr!r} must be callable")
        with self._lock:
            self._check_open("declare_queryable")

            def serve(query_key: str, payload: bytes | None) -> Reply | None:
                return self._serve(key_expr, handler, query_key, payload)

            undeclare = self._guard(
                self._transport_queryable(key_expr, serve), f"queryable {key_expr!r}"
            )

            def withdraw() -> None:
                with self._lock:
                    self._queryables.discard(queryable)
                undeclare()

            queryable = Queryable(key_expr, withdraw)
            self._queryables.add(queryable)
        return queryable

    def query(
        self, key_expr: str, payload: bytes | None = None, timeout_s: float = 5.0
    ) -> list[Reply]:
        """Ask every queryable matching `key_expr`; returns the replies that arrived in time.

        Returns an empty list when nothing matches (at once) or nothing answered in time.
        """
        validate_key_expr(key_expr, "query key expression")
        data = None if payload is None else _as_bytes(payload, "query payload")
        if timeout_s <= 0:
            raise ValueError(f"timeout_s must be > 0, got {timeout_s}")
        self._check_open("query")
        self._traffic.sent(key_expr, len(data or b""))
        replies = self._transport_query(key_expr, data, timeout_s)
        for reply in replies:
            self._traffic.received(key_expr, len(reply.payload))
        return replies

    def declare_liveliness(self, key: str) -> LivelinessToken:
        """Announce presence on `key` until `undeclare()` or until this bus closes or dies."""
        validate_key(key, "liveliness key")
        with self._lock:
            self._check_open("declare_liveliness")
            undeclare = self._guard(self._transport_token(key), f"liveliness token {key!r}")

            def withdraw() -> None:
                with self._lock:
                    self._tokens.discard(token)
                undeclare()

            token = LivelinessToken(key, withdraw)
            self._tokens.add(token)
        return token

    def watch_liveliness(
        self,
        key_expr: str,
        on_join: MemberCallback | None = None,
        on_leave: MemberCallback | None = None,
    ) -> LivelinessWatcher:
        """Follow the tokens matching `key_expr`: current members first, then joins/leaves."""
        validate_key_expr(key_expr, "liveliness key expression")
        with self._lock:
            self._check_open("watch_liveliness")
            watcher = LivelinessWatcher(key_expr, on_join, on_leave)
            undeclare = self._guard(self._transport_watch(watcher), f"watcher on {key_expr!r}")
            self._watchers.add(watcher)

        def stop() -> None:
            with self._lock:
                self._watchers.discard(watcher)
            undeclare()

        watcher.attach(stop)
        return watcher

    def stats(self) -> dict[str, dict]:
        """{"sent"|"received": {key: {"messages", "bytes"}}, "dropped": {key_expr: count}
        (queue overflows), "oversized": {key: count} (over `max_payload_bytes`)}."""
        out: dict[str, dict] = self._traffic.snapshot()
        with self._lock:
            dropped = dict(self._dropped_by_closed)
            for sub in self._subscriptions:
                dropped[sub.key_expr] = dropped.get(sub.key_expr, 0) + sub.dropped
            out["oversized"] = dict(self._dropped_oversized)
        out["dropped"] = dropped
        return out

    @property
    def closed(self) -> bool:
        return self._closing

    def close(self) -> None:
        """Withdraw everything this session declared and release the transport.

        Idempotent, and returns within `close_timeout_s` even when the other side is gone or
        subscription callbacks hang: everything is signalled first, then the transport and
        the callback workers are waited for against one shared deadline.
        """
        deadline = time.monotonic() + self.close_timeout_s
        with self._lock:
            if self._closing:
                return
            self._closing = True
            subscriptions = list(self._subscriptions)
            handles = [*self._queryables, *self._watchers]
            tokens = list(self._tokens)
        # Handles only flip their state here: the transport tears its side down in one go.
        for sub in subscriptions:
            sub.close(timeout=0)
        for handle in handles:
            handle.close()
        for token in tokens:
            token.undeclare()
        # Transport first: a callback blocked in a publish is released when the session goes.
        self._transport_close(deadline)
        for sub in subscriptions:
            sub.join(deadline)

    def __enter__(self) -> Bus:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- transport, provided by subclasses -----------------------------------------------

    @abstractmethod
    def _transport_publish(self, key: str, payload: bytes) -> None: ...

    @abstractmethod
    def _transport_subscribe(
        self, key_expr: str, receive: Callable[[str, bytes], None]
    ) -> Callable[[], None]:
        """Start delivering `receive(key, payload)` for matches; return the undeclare function.
        `receive` never blocks."""

    @abstractmethod
    def _transport_queryable(
        self, key_expr: str, serve: Callable[[str, bytes | None], Reply | None]
    ) -> Callable[[], None]:
        """Route matching queries to `serve(query_key, payload)` and send back what it returns."""

    @abstractmethod
    def _transport_query(
        self, key_expr: str, payload: bytes | None, timeout_s: float
    ) -> list[Reply]: ...

    @abstractmethod
    def _transport_token(self, key: str) -> Callable[[], None]: ...

    @abstractmethod
    def _transport_watch(self, watcher: LivelinessWatcher) -> Callable[[], None]:
        """Call `watcher.joined/left(key)` for current and future tokens."""

    @abstractmethod
    def _transport_close(self, deadline: float) -> None:
        """Drop every declaration of this session and release it; return by `deadline`
        (`time.monotonic()`), abandoning what is not done by then."""

    # -- helpers -------------------------------------------------------------------------

    def _check_open(self, what: str) -> None:
        if self._closing:
            raise BusClosedError(f"{what}: the {type(self).__name__} is closed")

    def _guard(self, undeclare: Callable[[], None], what: str) -> Callable[[], None]:
        """Undeclare only while the bus is open (closing tears everything down at once), and
        never let a transport error escape from a close()."""

        def run() -> None:
            if self._closing:
                return
            try:
                undeclare()
            except Exception:
                logger.exception("could not undeclare %s", what)

        return run

    def _make_receiver(self, sub: Subscription) -> Callable[[str, bytes], None]:
        traffic = self._traffic

        limit = self.max_payload_bytes

        def receive(key: str, payload: bytes) -> None:
            if sub.closed:
                return
            traffic.received(sub.key_expr, len(payload))
            if limit is not None and len(payload) > limit:
                self._oversized(key, len(payload))
                return
            sub.deliver(Sample(key, payload, time.time()))

        return receive

    def _oversized(self, key: str, nbytes: int) -> None:
        with self._lock:
            counted = self._dropped_oversized.add(key)
            count = self._dropped_oversized[counted]
        if count == 1 or count % 100 == 0:  # a flood must not become a flood of logs
            logger.warning("dropped a %d-byte message on %r: over the bus limit of %d bytes "
                           "(%d so far)", nbytes, key, self.max_payload_bytes, count)

    def _forget_subscription(self, sub: Subscription) -> None:
        with self._lock:
            self._subscriptions.discard(sub)
            self._dropped_by_closed[sub.key_expr] = (
                self._dropped_by_closed.get(sub.key_expr, 0) + sub.dropped
            )
            undeclare = self._sub_undeclare.pop(sub, None)
        if undeclare is not None:
            undeclare()

    def _serve(
        self, queryable_key_expr: str, handler: QueryHandler, query_key: str, payload: bytes | None
    ) -> Reply | None:
        self._traffic.received(queryable_key_expr, len(payload or b""))
        key = reply_key(query_key, queryable_key_expr)
        try:
            result = handler(query_key, payload)
            if result is None:
                return None
            reply = Reply(key, _as_bytes(result, f"reply of queryable {queryable_key_expr!r}"))
        except Exception as exc:
            logger.exception("queryable %r failed on query %r", queryable_key_expr, query_key)
            # Error replies carry no key on the wire: report the query's own expression.
            reply = Reply(query_key, f"{type(exc).__name__}: {exc}".encode(), ok=False)
        self._traffic.sent(queryable_key_expr, len(reply.payload))
        return reply

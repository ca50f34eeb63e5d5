"""The bus over Eclipse Zenoh (zenoh-python 1.x).

Topology (measured, see DESIGN §6): no router binary; the server's session listens in `router`
(or `peer`) mode and agents connect to it in `client` mode. Multicast scouting is off unless
asked for, so nothing is discovered behind the user's back. Zenoh runs Python callbacks on its
own threads and swallows their exceptions: every callback here is wrapped so failures are
logged, and subscription callbacks only enqueue (see `Subscription`), so a slow consumer never
backs up the network.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Callable, Sequence

import zenoh

from cpslam.common.bus.interface import Bus, BusClosedError, BusError, Reply
from cpslam.common.bus.liveliness import LivelinessWatcher
from cpslam.common.bus.zenoh_security import ZenohSecurity

logger = logging.getLogger(__name__)

__all__ = ["ZenohBus", "zenoh_config"]

MODES = ("peer", "client", "router")
# Declared publishers are cached per key (cheaper puts); beyond this many keys fall back to
# session.put so an unbounded key space (e.g. per-keyframe keys) cannot grow the cache forever.
_MAX_CACHED_PUBLISHERS = 256
# Zenoh's own framing around a payload (key expression, attachments, headers).
_RX_HEADROOM = 64 * 1024
# Marks error replies sent by a cpslam queryable (handler raised), as opposed to the errors
# Zenoh itself reports to a querier.
_ERROR_ENCODING = zenoh.Encoding.TEXT_PLAIN.with_schema("cpslam-error")


def zenoh_config(
    mode: str = "peer",
    listen: Sequence[str] = (),
    connect: Sequence[str] = (),
    shared_memory: bool = False,
    lease_s: float = 3.0,
    multicast_scouting: bool = False,
    open_timeout_s: float = 5.0,
    security: ZenohSecurity | None = None,
    max_payload_bytes: int | None = None,
    max_sessions: int | None = None,
) -> zenoh.Config:
    """The zenoh.Config for these settings (arguments as in `ZenohBus`)."""
    if mode not in MODES:
        raise ValueError(f"zenoh mode must be one of {MODES}, got {mode!r}")
    listen, connect = _endpoints(listen, "listen"), _endpoints(connect, "connect")
    if mode == "client" and listen:
        raise ValueError(f"a zenoh client cannot listen (listen={listen}); use mode 'peer'")
    if mode == "client" and not connect and not multicast_scouting:
        raise ValueError("a zenoh client needs connect endpoints (or multicast_scouting=True)")
    if lease_s <= 0 or open_timeout_s <= 0:
        raise ValueError(f"lease_s and open_timeout_s must be > 0, got {lease_s}, {open_timeout_s}")
    security = security if security is not None else ZenohSecurity()
    conf = security.base_config()
    settings: dict[str, object] = {
        "mode": mode,
        "connect/endpoints": connect,
        "listen/endpoints": listen,
        "scouting/multicast/enabled": multicast_scouting,
        "transport/shared_memory/enabled": shared_memory,
        "transport/link/tx/lease": int(lease_s * 1000),
    }
    if max_payload_bytes is not None:
        # Zenoh reassembles a fragmented message up to this size (default 1 GiB) before any
        # of our checks see it: a peer's huge message is refused by the transport itself.
        settings["transport/link/rx/max_message_size"] = int(max_payload_bytes) + _RX_HEADROOM
    if max_sessions is not None:
        settings["transport/unicast/max_sessions"] = int(max_sessions)
    if not multicast_scouting:
        # The default 500 ms scouting delay only waits for multicast answers that cannot come.
        settings["scouting/delay"] = 0
    if mode == "client":
        # Keep retrying the server for open_timeout_s instead of failing on the first refusal,
        # so agents may start before the server.
        settings["connect/timeout_ms"] = int(open_timeout_s * 1000)
        settings["connect/retry"] = {
            "period_init_ms": 100,
            "period_max_ms": 1000,
            "period_increase_factor": 2,
        }
    settings.update(security.settings(mode, [*listen, *connect]))
    for key, value in settings.items():
        conf.insert_json5(key, json.dumps(value))
    return conf


def _endpoints(endpoints: Sequence[str], what: str) -> list[str]:
    if isinstance(endpoints, str):
        raise TypeError(f"{what} must be a list of endpoints, got the string {endpoints!r}")
    out = list(endpoints)
    for endpoint in out:
        if not isinstance(endpoint, str) or "/" not in endpoint:
            raise ValueError(
                f"{what} endpoint {endpoint!r} is not of the form '<proto>/<address>', "
                "e.g. 'tcp/127.0.0.1:7447'"
            )
    return out


class ZenohBus(Bus):
    """A Zenoh session behind the `Bus` interface.

    Args:
        mode: "router" or "peer" for the listening side (server), "client" for agents.
        listen: endpoints to listen on, e.g. ["tcp/0.0.0.0:7447"].
        connect: endpoints to connect to, e.g. ["tcp/127.0.0.1:7447"].
        shared_memory: Zenoh's same-host shared-memory transport (off: bytes go through TCP,
            which is what remote machines get, and what benchmarks should measure).
        lease_s: a peer silent this long is declared dead (its tokens leave).
        multicast_scouting: discover peers by UDP multicast.
        open_timeout_s: how long a client keeps trying to reach `connect` before failing.
        block_on_congestion: block the publisher while Zenoh's send queue is full (reliable:
            map deltas must not vanish) instead of dropping the message. Only a peer that
            stops reading its socket can cause that, and at most until its lease expires.
        close_timeout_s: `close()` returns within this long: Zenoh's own close (which can
            wait on a vanished peer) and busy subscription callbacks share the deadline.
        max_payload_bytes: larger payloads are refused on publish and dropped on receive
            (see `Bus`), and Zenoh's receive limit (``transport/link/rx/max_message_size``)
            follows it; None: no limit.
        max_queue_bytes: payload bytes each subscription queue may hold (see `Bus`).
        max_sessions: Zenoh sessions a listening session admits at once
            (``transport/unicast/max_sessions``); None: Zenoh's default (1000).
        security: TLS / mutual TLS, user-password authentication, access control and a base
            Zenoh config file (`ZenohSecurity`); None: plain Zenoh.
    """

    def __init__(
        self,
        mode: str = "peer",
        listen: Sequence[str] = (),
        connect: Sequence[str] = (),
        shared_memory: bool = False,
        lease_s: float = 3.0,
        multicast_scouting: bool = False,
        open_timeout_s: float = 5.0,
        block_on_congestion: bool = True,
        close_timeout_s: float = 2.0,
        max_payload_bytes: int | None = None,
        security: ZenohSecurity | None = None,
        max_queue_bytes: int | None = None,
        max_sessions: int | None = None,
        max_counter_keys: int = 1024,
    ) -> None:
        super().__init__(close_timeout_s, max_payload_bytes, max_queue_bytes, max_counter_keys)
        config = zenoh_config(
            mode, listen, connect, shared_memory, lease_s, multicast_scouting, open_timeout_s,
            security, max_payload_bytes, max_sessions,
        )
        self.mode = mode
        self.listen = list(listen)
        self.connect = list(connect)
        self._congestion = (
            zenoh.CongestionControl.BLOCK if block_on_congestion else zenoh.CongestionControl.DROP
        )
        try:
            self._session = zenoh.open(config)
        except zenoh.ZError as exc:
            raise BusError(
                f"could not open a zenoh session (mode={mode}, listen={self.listen}, "
                f"connect={self.connect}): {exc}"
            ) from exc
        self.zid = str(self._session.zid())
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._publishers_lock = threading.Lock()
        logger.info(
            "zenoh session %s open (mode=%s, listen=%s, connect=%s, shm=%s)",
            self.zid,
            mode,
            self.listen,
            self.connect,
            shared_memory,
        )

    def _transport_publish(self, key: str, payload: bytes) -> None:
        try:
            publisher = self._publisher(key)
            if publisher is None:
                self._session.put(key, payload, congestion_control=self._congestion)
            else:
                publisher.put(payload)
        except zenoh.ZError as exc:
            if self._closing:
                raise BusClosedError(f"publish on {key!r}: the ZenohBus is closed") from exc
            raise BusError(f"zenoh could not publish on {key!r}: {exc}") from exc

    def _publisher(self, key: str) -> zenoh.Publisher | None:
        with self._publishers_lock:
            publisher = self._publishers.get(key)
            if publisher is None and len(self._publishers) < _MAX_CACHED_PUBLISHERS:
                publisher = self._session.declare_publisher(
                    key, congestion_control=self._congestion
                )
                self._publishers[key] = publisher
            return publisher

    def _transport_subscribe(
        self, key_expr: str, receive: Callable[[str, bytes], None]
    ) -> Callable[[], None]:
        def on_sample(sample: zenoh.Sample) -> None:
            try:
                if sample.kind == zenoh.SampleKind.PUT:
                    receive(str(sample.key_expr), sample.payload.to_bytes())
            except Exception:
                logger.exception("receiving on %r failed", key_expr)

        return self._session.declare_subscriber(key_expr, on_sample).undeclare

    def _transport_queryable(
        self, key_expr: str, serve: Callable[[str, bytes | None], Reply | None]
    ) -> Callable[[], None]:
        def on_query(query: zenoh.Query) -> None:
            # The context manager drops the query on exit: without that the querier would
            # wait for its timeout even after the reply arrived.
            with query:
                try:
                    payload = query.payload
                    reply = serve(
                        str(query.key_expr), None if payload is None else payload.to_bytes()
                    )
                    if reply is None:
                        return
                    if reply.ok:
                        query.reply(reply.key, reply.payload)
                    else:
                        query.reply_err(reply.payload, encoding=_ERROR_ENCODING)
                except Exception:
                    logger.exception(
                        "answering query %r on %r failed", str(query.key_expr), key_expr
                    )

        return self._session.declare_queryable(key_expr, on_query).undeclare

    def _transport_query(
        self, key_expr: str, payload: bytes | None, timeout_s: float
    ) -> list[Reply]:
        try:
            answers = self._session.get(
                key_expr,
                payload=payload,
                target=zenoh.QueryTarget.ALL,
                consolidation=zenoh.ConsolidationMode.NONE,
                timeout=timeout_s,
            )
            replies = []
            # Iteration ends when every queryable has finished or the timeout has passed.
            for answer in answers:
                if answer.ok is not None:
                    sample = answer.ok
                    replies.append(Reply(str(sample.key_expr), sample.payload.to_bytes()))
                elif answer.err is not None and answer.err.encoding == _ERROR_ENCODING:
                    # Other errors are Zenoh's own (a "Timeout" marker, from the querier or a
                    # router on the way): not answers; a timed-out query returns what arrived.
                    replies.append(Reply(key_expr, answer.err.payload.to_bytes(), ok=False))
            return replies
        except zenoh.ZError as exc:
            if self._closing:
                raise BusClosedError(f"query {key_expr!r}: the ZenohBus is closed") from exc
            raise BusError(f"zenoh query {key_expr!r} failed: {exc}") from exc

    def _transport_token(self, key: str) -> Callable[[], None]:
        return self._session.liveliness().declare_token(key).undeclare

    def _transport_watch(self, watcher: LivelinessWatcher) -> Callable[[], None]:
        def on_change(sample: zenoh.Sample) -> None:
            try:
                key = str(sample.key_expr)
                if sample.kind == zenoh.SampleKind.PUT:
                    watcher.joined(key)
                else:
                    watcher.left(key)
            except Exception:
                logger.exception("liveliness change on %r failed", watcher.key_expr)

        subscriber = self._session.liveliness().declare_subscriber(
            watcher.key_expr, on_change, history=True
        )
        return subscriber.undeclare

    def _transport_close(self, deadline: float) -> None:
        session = self._session
        done = threading.Event()

        def close() -> None:
            try:
                session.close()
            except Exception:
                logger.exception("closing the zenoh session failed")
            finally:
                done.set()

        # Zenoh's close can wait on a vanished peer; never let that hang a daemon's shutdown.
        threading.Thread(target=close, name="zenoh-close", daemon=True).start()
        if not done.wait(max(deadline - time.monotonic(), 0.0)):
            logger.warning(
                "zenoh session %s did not close within %.1f s; abandoning it",
                self.zid,
                self.close_timeout_s,
            )
        with self._publishers_lock:
            self._publishers.clear()

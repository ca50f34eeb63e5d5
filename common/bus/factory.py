"""Build the bus a daemon asked for from the config's `transport` section: `bus_from_config`
opens it once, `open_client` retries a client session until the server is reachable (agents
and the `cpslam status` / `cpslam finalise` clients both wait for it).
"""

from __future__ import annotations

import logging
import threading
import time
from typing import TYPE_CHECKING, Literal

from cpslam.common.bus.interface import Bus, BusError
from cpslam.common.bus.memory import InMemoryBus, InMemoryNetwork
from cpslam.common.bus.zenoh_bus import ZenohBus
from cpslam.common.bus.zenoh_security import ZenohSecurity

if TYPE_CHECKING:
    from cpslam.common.config import LimitsConfig, TransportConfig

Role = Literal["server", "agent"]

logger = logging.getLogger(__name__)

# A signal handler that sets a stop event cannot wake a thread blocked on another event or
# condition, so waits that must honour `stop` block in slices of this length.
STOP_CHECK_S = 0.2
# Waits longer than this are announced in the log; shorter ones stay quiet.
ANNOUNCE_AFTER_S = 1.0

DEFAULT_PORT = 7447
_ROLE_DEFAULTS: dict[str, dict[str, object]] = {
    # The server hosts the Zenoh endpoint itself: no separate router process is needed.
    "server": {"mode": "router", "listen": [f"tcp/0.0.0.0:{DEFAULT_PORT}"], "connect": []},
    # Agents in client mode reach each other through the server (peer mode did not, here).
    "agent": {"mode": "client", "listen": [], "connect": [f"tcp/127.0.0.1:{DEFAULT_PORT}"]},
}


def bus_from_config(
    transport: TransportConfig, role: Role, network: InMemoryNetwork | None = None,
    limits: LimitsConfig | None = None,
) -> Bus:
    """A `ZenohBus` (or an `InMemoryBus` on `network` for backend "memory") for `role`.

    Unset mode/listen/connect take the role's defaults: the server is a router listening on
    tcp/0.0.0.0:7447, an agent a client connecting to tcp/127.0.0.1:7447. `listen` is ignored
    in client mode; a server with `connect` set also reaches an existing Zenoh router.
    ``max_message_mb`` bounds the payloads of either bus (and Zenoh's receive limit);
    ``queue_size`` is the nodes' to use when they subscribe, ``session`` their key prefix.
    `limits` (the ``limits`` section; None: its defaults) bounds each subscription queue in
    bytes (``queue_mb``), the bus's counters (``max_counter_keys``) and, for the listening
    server, the Zenoh sessions admitted (``zenoh_max_sessions``).
    """
    from cpslam.common.config.limits import LimitsConfig

    limits = limits if limits is not None else LimitsConfig()
    queue_bytes = int(limits.queue_mb * 2**20)
    if role not in _ROLE_DEFAULTS:
        raise ValueError(f"bus_from_config: role must be 'server' or 'agent', got {role!r}")
    max_payload = int(transport.max_message_mb * 2**20)
    if transport.backend == "memory":
        if network is None:
            raise ValueError("transport.backend 'memory' needs the InMemoryNetwork shared by "
                             "every bus of the process")
        return InMemoryBus(network, max_payload_bytes=max_payload, max_queue_bytes=queue_bytes,
                           max_counter_keys=limits.max_counter_keys)
    defaults = _ROLE_DEFAULTS[role]
    mode = transport.mode or defaults["mode"]
    # A client never listens, so one config file with `listen` set serves both daemons.
    listen = [] if mode == "client" else (transport.listen or defaults["listen"])
    connect = transport.connect or defaults["connect"]
    return ZenohBus(
        mode=str(mode),
        listen=list(listen),  # type: ignore[arg-type]
        connect=list(connect),  # type: ignore[arg-type]
        shared_memory=transport.shared_memory,
        lease_s=transport.lease_s,
        multicast_scouting=transport.multicast_scouting,
        open_timeout_s=transport.open_timeout_s,
        max_payload_bytes=max_payload,
        security=ZenohSecurity.from_transport(transport),
        max_queue_bytes=queue_bytes,
        max_sessions=limits.zenoh_max_sessions if role == "server" else None,
        max_counter_keys=limits.max_counter_keys,
    )


def open_client(transport: TransportConfig, wait_timeout_s: float, what: str = "agent",
                stop: threading.Event | None = None,
                limits: LimitsConfig | None = None) -> Bus | None:
    """A client bus to the configured endpoints, retried until `wait_timeout_s`; None if the
    server could not be reached, or at once when `stop` is set (the caller tells which).
    `what` names the caller in the log lines ("agent 0", "client"); `limits` as in
    `bus_from_config`."""
    t0 = time.monotonic()
    deadline = t0 + wait_timeout_s
    endpoints = ", ".join(transport.connect) or f"tcp/127.0.0.1:{DEFAULT_PORT}"
    stop = stop if stop is not None else threading.Event()
    announced = False

    def announce() -> None:
        nonlocal announced
        if not announced:
            logger.info("%s: waiting for the server at %s (up to %.0f s) …", what, endpoints,
                        wait_timeout_s)
            announced = True

    while not stop.is_set():
        attempt = _OpenAttempt(transport, limits)
        while not attempt.done.wait(STOP_CHECK_S):
            if stop.is_set():
                attempt.abandon()
                return None
            if time.monotonic() - t0 >= ANNOUNCE_AFTER_S:
                announce()
        if attempt.bus is not None:
            return attempt.bus
        if not isinstance(attempt.error, BusError):
            raise attempt.error  # a configuration error, not an absent server
        if time.monotonic() >= deadline:
            logger.error("%s: no server at %s after %.0f s (%s)", what, endpoints,
                         wait_timeout_s, attempt.error)
            return None
        announce()
        stop.wait(min(1.0, max(deadline - time.monotonic(), 0.0)))
    return None


class _OpenAttempt:
    """One `bus_from_config` on its own thread: opening a client session blocks for up to
    ``transport.open_timeout_s``, and a stop request must not wait for that."""

    def __init__(self, transport: TransportConfig, limits: LimitsConfig | None = None) -> None:
        self.done = threading.Event()
        self.bus: Bus | None = None
        self.error: Exception | None = None
        self._lock = threading.Lock()
        self._abandoned = False
        threading.Thread(target=self._run, args=(transport, limits), name="bus-open",
                         daemon=True).start()

    def _run(self, transport: TransportConfig, limits: LimitsConfig | None) -> None:
        bus = None
        try:
            bus = bus_from_config(transport, "agent", limits=limits)
        except Exception as err:  # noqa: BLE001 - handed to the waiting thread
            self.error = err
        with self._lock:
            abandoned = self._abandoned
            if not abandoned:
                self.bus = bus
        if abandoned and bus is not None:
            bus.close()  # opened after its caller gave up
        self.done.set()

    def abandon(self) -> None:
        """Nobody wants the session any more: close it, now or when it opens."""
        with self._lock:
            self._abandoned = True
            bus, self.bus = self.bus, None
        if bus is not None:
            bus.close()

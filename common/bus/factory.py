"""Build the bus a daemon asked for from the config's `transport` section."""

from __future__ import annotations

from typing import TYPE_CHECKING, Literal

from cpslam.common.bus.interface import Bus
from cpslam.common.bus.memory import InMemoryBus, InMemoryNetwork
from cpslam.common.bus.zenoh_bus import ZenohBus

if TYPE_CHECKING:
    from cpslam.common.config import TransportConfig

Role = Literal["server", "agent"]

DEFAULT_PORT = 7447
_ROLE_DEFAULTS: dict[str, dict[str, object]] = {
    # The server hosts the Zenoh endpoint itself: no separate router process is needed.
    "server": {"mode": "router", "listen": [f"tcp/0.0.0.0:{DEFAULT_PORT}"], "connect": []},
    # Agents in client mode reach each other through the server (peer mode did not, here).
    "agent": {"mode": "client", "listen": [], "connect": [f"tcp/127.0.0.1:{DEFAULT_PORT}"]},
}


def bus_from_config(
    transport: TransportConfig, role: Role, network: InMemoryNetwork | None = None
) -> Bus:
    """A `ZenohBus` (or an `InMemoryBus` on `network` for backend "memory") for `role`.

    Unset mode/listen/connect take the role's defaults: the server is a router listening on
    tcp/0.0.0.0:7447, an agent a client connecting to tcp/127.0.0.1:7447. `listen` is ignored
    in client mode; a server with `connect` set also reaches an existing Zenoh router.
    ``max_message_mb`` bounds the payloads of either bus; ``queue_size`` is the nodes' to use
    when they subscribe, ``session`` their key prefix.
    """
    if role not in _ROLE_DEFAULTS:
        raise ValueError(f"bus_from_config: role must be 'server' or 'agent', got {role!r}")
    max_payload = int(transport.max_message_mb * 2**20)
    if transport.backend == "memory":
        if network is None:
            raise ValueError("transport.backend 'memory' needs the InMemoryNetwork shared by "
                             "every bus of the process")
        return InMemoryBus(network, max_payload_bytes=max_payload)
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
    )

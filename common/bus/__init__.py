"""The message bus: bytes over Zenoh between processes, or in memory inside one process.

    from cpslam.common.bus import ZenohBus
    with ZenohBus(mode="client", connect=["tcp/127.0.0.1:7447"]) as bus:
        bus.publish("cpslam/demo/agent/0/keyframe", payload)

The bus knows nothing of message types; `cpslam.protocol` encodes and decodes.
"""

from cpslam.common.bus.factory import bus_from_config, open_client
from cpslam.common.bus.interface import (
    Bus,
    BusClosedError,
    BusError,
    Queryable,
    QueryHandler,
    Reply,
)
from cpslam.common.bus.keyexpr import intersects, is_concrete, validate_key_expr
from cpslam.common.bus.liveliness import LivelinessToken, LivelinessWatcher
from cpslam.common.bus.memory import InMemoryBus, InMemoryNetwork
from cpslam.common.bus.subscription import Sample, Subscription
from cpslam.common.bus.zenoh_bus import ZenohBus, zenoh_config
from cpslam.common.bus.zenoh_security import ZenohSecurity

__all__ = [
    "Bus",
    "BusClosedError",
    "BusError",
    "InMemoryBus",
    "InMemoryNetwork",
    "LivelinessToken",
    "LivelinessWatcher",
    "Queryable",
    "QueryHandler",
    "Reply",
    "Sample",
    "Subscription",
    "ZenohBus",
    "ZenohSecurity",
    "bus_from_config",
    "intersects",
    "is_concrete",
    "open_client",
    "validate_key_expr",
    "zenoh_config",
]

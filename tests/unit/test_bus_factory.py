import socket

import pytest

from cpslam.common.bus import InMemoryBus, InMemoryNetwork, ZenohBus, bus_from_config
from cpslam.common.config import load_config, override_config


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_memory_backend_needs_and_uses_the_network() -> None:
    cfg = override_config(load_config("tiny", env={}), ["transport.backend=memory"])
    with pytest.raises(ValueError, match="InMemoryNetwork"):
        bus_from_config(cfg.transport, "agent")
    net = InMemoryNetwork()
    with bus_from_config(cfg.transport, "server", net) as bus:
        assert isinstance(bus, InMemoryBus)


def test_server_and_agent_defaults_meet_over_tcp() -> None:
    port = _free_port()
    cfg = override_config(
        load_config("tiny", env={}),
        [f"transport.listen=tcp/127.0.0.1:{port}", f"transport.connect=tcp/127.0.0.1:{port}"],
    )
    with bus_from_config(cfg.transport, "server") as server:
        assert isinstance(server, ZenohBus)
        assert server.max_payload_bytes == int(cfg.transport.max_message_mb * 2**20)
        sub = server.subscribe("cpslam/t/**")
        with bus_from_config(cfg.transport, "agent") as agent:
            agent.publish("cpslam/t/x", b"hello")
            sample = sub.get(timeout=5)
            assert sample is not None and sample.payload == b"hello"


def test_unknown_role() -> None:
    cfg = load_config("tiny", env={})
    with pytest.raises(ValueError, match="role"):
        bus_from_config(cfg.transport, "robot")  # type: ignore[arg-type]


def test_transport_settings_reach_the_bus() -> None:
    cfg = override_config(load_config("tiny", env={}),
                          ["transport.backend=memory", "transport.max_message_mb=0.001"])
    net = InMemoryNetwork()
    limit = int(0.001 * 2**20)
    with bus_from_config(cfg.transport, "server", net) as bus, InMemoryBus(net) as other:
        assert bus.max_payload_bytes == limit
        with pytest.raises(ValueError, match="max_message_mb"):
            bus.publish("cpslam/t/big", bytes(limit + 1))
        bus.publish("cpslam/t/ok", bytes(limit))
        sub = bus.subscribe("cpslam/t/*")
        other.publish("cpslam/t/big", bytes(limit + 1))  # the sender has no limit
        other.publish("cpslam/t/small", b"x")
        sample = sub.get(timeout=2.0)
        assert sample is not None and sample.key == "cpslam/t/small"
        assert bus.stats()["oversized"] == {"cpslam/t/big": 1}

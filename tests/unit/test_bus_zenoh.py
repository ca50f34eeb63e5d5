"""ZenohBus specifics the contract suite cannot express: configuration and failing to connect."""

from __future__ import annotations

import json
import socket
import time

import pytest

from cpslam.common.bus import BusError, ZenohBus, zenoh_config


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def setting(conf, key: str):
    return json.loads(conf.get_json(key))  # zenoh hands settings back as JSON text


def test_config_reflects_arguments() -> None:
    conf = zenoh_config(
        mode="client", connect=["tcp/127.0.0.1:7447"], shared_memory=False, lease_s=2.5
    )
    assert setting(conf, "mode") == "client"
    assert setting(conf, "connect/endpoints") == ["tcp/127.0.0.1:7447"]
    assert setting(conf, "transport/shared_memory/enabled") is False
    assert setting(conf, "scouting/multicast/enabled") is False
    assert setting(conf, "transport/link/tx/lease") == 2500
    assert setting(conf, "connect/timeout_ms") == 5000
    peer = zenoh_config(mode="peer", shared_memory=True)
    assert setting(peer, "transport/shared_memory/enabled") is True


@pytest.mark.parametrize(
    ("kwargs", "error", "message"),
    [
        ({"mode": "server"}, ValueError, "mode"),
        (
            {"mode": "client", "listen": ["tcp/0.0.0.0:7447"], "connect": ["tcp/h:1"]},
            ValueError,
            "cannot listen",
        ),
        ({"mode": "client"}, ValueError, "connect endpoints"),
        ({"connect": "tcp/127.0.0.1:7447"}, TypeError, "list of endpoints"),
        ({"connect": ["127.0.0.1:7447"]}, ValueError, "<proto>/<address>"),
        ({"lease_s": 0}, ValueError, "lease_s"),
    ],
)
def test_bad_arguments_raise_clear_errors(kwargs: dict, error: type, message: str) -> None:
    with pytest.raises(error, match=message):
        ZenohBus(**kwargs)


def test_client_without_server_fails_within_open_timeout() -> None:
    start = time.monotonic()
    with pytest.raises(BusError, match="could not open"):
        ZenohBus(mode="client", connect=[f"tcp/127.0.0.1:{free_port()}"], open_timeout_s=0.5)
    # A real socket: the bound only catches an open that ignores its timeout (hangs), with
    # room for a loaded machine; the timeout itself is 0.5 s.
    assert time.monotonic() - start < 10.0


def test_client_started_before_server_connects_once_it_listens() -> None:
    import threading

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    holder: dict[str, ZenohBus] = {}

    def start_server() -> None:
        time.sleep(0.4)
        holder["server"] = ZenohBus(mode="router", listen=[endpoint])

    thread = threading.Thread(target=start_server)
    thread.start()
    client = ZenohBus(mode="client", connect=[endpoint], open_timeout_s=5.0)
    thread.join()
    server = holder["server"]
    try:
        server.declare_queryable("ping", lambda key, payload: b"pong")
        time.sleep(0.3)
        assert [r.payload for r in client.query("ping", timeout_s=2.0)] == [b"pong"]
    finally:
        client.close()
        server.close()


def test_listening_on_a_taken_port_is_a_clear_error() -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with ZenohBus(mode="router", listen=[endpoint]):
        with pytest.raises(BusError, match=endpoint.split("/")[1]):
            ZenohBus(mode="router", listen=[endpoint])


def test_the_server_session_admits_at_most_max_sessions() -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with ZenohBus(mode="router", listen=[endpoint], max_sessions=1), ZenohBus(
        mode="client", connect=[endpoint], open_timeout_s=2.0
    ):
        with pytest.raises(BusError, match="could not open"):
            ZenohBus(mode="client", connect=[endpoint], open_timeout_s=1.0)

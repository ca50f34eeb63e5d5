"""Two OS processes over Zenoh TCP on 127.0.0.1 (random port, shared memory off).

This process plays the server (router, listening); `bus_peer.py` plays an agent (client).
"""

from __future__ import annotations

import json
import signal
import time
from collections.abc import Callable, Iterator

import pytest

from cpslam import protocol
from cpslam.common.bus import Sample, ZenohBus
from cpslam.protocol import keys
from cpslam.protocol.samples import sample, samples

pytestmark = pytest.mark.loopback

SESSION = "lb"
AGENT = "agent-0"


def wait_until(predicate: Callable[[], bool], timeout: float = 5.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.01)
    return predicate()


def lb_key(name: str) -> str:
    return f"cpslam/{SESSION}/test/{name}"


class Joined:
    """Liveliness events seen by a watcher, with their arrival times."""

    def __init__(self) -> None:
        self.joins: dict[str, float] = {}
        self.leaves: dict[str, float] = {}

    def on_join(self, key: str) -> None:
        self.joins[key] = time.monotonic()

    def on_leave(self, key: str) -> None:
        self.leaves[key] = time.monotonic()


@pytest.fixture
def server_and_agent(spawn, endpoint: str) -> Iterator[tuple[ZenohBus, object, Joined]]:
    server = ZenohBus(mode="router", listen=[endpoint], shared_memory=False, lease_s=2.0)
    seen = Joined()
    server.watch_liveliness(keys.alive_agents(SESSION), seen.on_join, seen.on_leave)
    peer = spawn("bus_peer.py", "--connect", endpoint)
    peer.expect("READY")
    agent_token = keys.alive_agent(SESSION, AGENT)
    # The token is the peer's last declaration: once it is here, everything else is too.
    assert wait_until(lambda: agent_token in seen.joins, timeout=5.0)
    yield server, peer, seen
    server.close()


def test_every_message_type_round_trips(server_and_agent) -> None:
    server, _, _ = server_and_agent
    echoes = server.subscribe(lb_key("echo/*"), queue_size=256)
    messages = [*samples(seed=1), sample("submap_delta", seed=2, n_points=10_000)]
    assert {type(m).type_name() for m in messages} == set(protocol.MESSAGE_TYPES)
    sent: dict[str, list[bytes]] = {}
    for msg in messages:
        name = type(msg).type_name()
        payload = protocol.encode(msg)
        sent.setdefault(name, []).append(payload)
        server.publish(lb_key(f"roundtrip/{name}"), payload)
    server.publish(lb_key("roundtrip/ack"), b"\x81\xa4type\xa3ack")  # truncated: invalid

    received: dict[str, list[bytes]] = {}
    deadline = time.monotonic() + 10.0
    while sum(map(len, received.values())) < len(messages) + 1 and time.monotonic() < deadline:
        s: Sample | None = echoes.get(timeout=0.5)
        if s is not None:
            received.setdefault(s.key.rsplit("/", 1)[-1], []).append(s.payload)
    assert len(received.pop("invalid", [])) == 1
    assert received == sent  # decoded in the peer, re-encoded bit for bit
    for name, payloads in received.items():
        for payload in payloads:
            assert type(protocol.decode(payload)).type_name() == name


def test_keyframe_image_query_is_answered(server_and_agent) -> None:
    server, _, _ = server_and_agent
    request = protocol.KeyframeImageRequest(agent_id=AGENT, kf_id=17)
    start = time.monotonic()
    replies = server.query(
        keys.agent_image(SESSION, AGENT, 17), protocol.encode(request), timeout_s=5.0
    )
    elapsed = time.monotonic() - start
    assert len(replies) == 1 and replies[0].ok
    assert replies[0].key == keys.agent_image(SESSION, AGENT, 17)
    image = protocol.decode(replies[0].payload, expected=protocol.KeyframeImage)
    assert (image.agent_id, image.kf_id) == (AGENT, 17)
    assert image.rgb is not None and image.rgb.shape == (48, 64, 3)
    assert elapsed < 2.0
    # Nobody serves another agent's images: an empty answer, not a wait for the timeout.
    start = time.monotonic()
    assert server.query(keys.agent_image(SESSION, "agent-9", 1), timeout_s=5.0) == []
    assert time.monotonic() - start < 1.0


def test_slow_subscriber_drops_without_blocking_publisher(server_and_agent) -> None:
    server, _, _ = server_and_agent
    n = 300
    start = time.perf_counter()
    for i in range(n):
        server.publish(lb_key("flood"), i.to_bytes(4, "little") + bytes(10_000))
    publish_s = time.perf_counter() - start
    assert publish_s < 2.0  # the peer needs 300 x 20 ms = 6 s to handle them all

    def peer_stats() -> dict:
        [reply] = server.query(lb_key("stats"), timeout_s=2.0)
        return json.loads(reply.payload)

    assert wait_until(
        lambda: peer_stats()["stats"]["received"].get(lb_key("flood"), {}).get("messages") == n,
        timeout=10.0,
    )
    time.sleep(0.2)  # let the peer's worker finish the sample in hand
    report = peer_stats()
    dropped = report["stats"]["dropped"][lb_key("flood")]
    assert dropped > 0
    assert report["handled"] + dropped in (n, n - 1)  # one may still be in the callback
    assert report["stats"]["received"][lb_key("flood")]["bytes"] == n * 10_004


@pytest.mark.parametrize("peer_role", ["client", "router"])
def test_killed_process_leaves_within_3_s(spawn, endpoint: str, peer_role: str) -> None:
    """SIGKILL an agent (client) or the server (router): the other side sees it leave."""
    if peer_role == "router":
        peer = spawn("bus_peer.py", "--mode", "router", "--listen", endpoint)
        peer.expect("READY")
        bus = ZenohBus(mode="client", connect=[endpoint], lease_s=2.0)
    else:
        bus = ZenohBus(mode="router", listen=[endpoint], lease_s=2.0)
        peer = spawn("bus_peer.py", "--connect", endpoint)
        peer.expect("READY")
    seen = Joined()
    token = keys.alive_agent(SESSION, AGENT)
    bus.watch_liveliness(keys.alive_all(SESSION), seen.on_join, seen.on_leave)
    assert wait_until(lambda: token in seen.joins, timeout=5.0)

    killed_at = time.monotonic()
    peer.kill()
    assert wait_until(lambda: token in seen.leaves, timeout=3.0)
    assert seen.leaves[token] - killed_at < 3.0
    start = time.monotonic()
    bus.close()
    assert time.monotonic() - start < 3.0


def test_peer_exits_cleanly_and_its_token_leaves(server_and_agent) -> None:
    _, peer, seen = server_and_agent
    assert peer.stop() == 0
    peer.expect("CLOSED", timeout=1.0)
    assert wait_until(lambda: keys.alive_agent(SESSION, AGENT) in seen.leaves, timeout=3.0)


def test_hung_process_leaves_after_its_lease(spawn, endpoint: str) -> None:
    """SIGSTOP (hung, socket still open): only the lease (2 s in bus_peer) can tell."""
    bus = ZenohBus(mode="router", listen=[endpoint], lease_s=2.0)
    peer = spawn("bus_peer.py", "--connect", endpoint)
    peer.expect("READY")
    seen = Joined()
    token = keys.alive_agent(SESSION, AGENT)
    bus.watch_liveliness(keys.alive_agents(SESSION), seen.on_join, seen.on_leave)
    assert wait_until(lambda: token in seen.joins, timeout=5.0)
    stopped_at = time.monotonic()
    peer.proc.send_signal(signal.SIGSTOP)
    try:
        assert wait_until(lambda: token in seen.leaves, timeout=6.0)
        assert 1.0 < seen.leaves[token] - stopped_at < 5.0
        # Publishing towards the hung peer must not wedge the publisher for long.
        start = time.monotonic()
        bus.publish(lb_key("flood"), bytes(1000))
        assert time.monotonic() - start < 1.0
    finally:
        peer.proc.send_signal(signal.SIGCONT)
    bus.close()

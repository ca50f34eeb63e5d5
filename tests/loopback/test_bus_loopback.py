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


# Two real processes over real sockets, so no fake clock: the upper bounds below are generous
# (several times what the design allows) and only tell "prompt" from "hung" on a loaded runner.
PROMPT_S = 10.0


def wait_until(predicate: Callable[[], bool], timeout: float = 30.0) -> bool:
    """Poll until `predicate` holds; the timeout only bounds a failure, so it is generous."""
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
        keys.agent_image(SESSION, AGENT, 17), protocol.encode(request), timeout_s=30.0
    )
    elapsed = time.monotonic() - start
    assert len(replies) == 1 and replies[0].ok
    assert replies[0].key == keys.agent_image(SESSION, AGENT, 17)
    image = protocol.decode(replies[0].payload, expected=protocol.KeyframeImage)
    assert (image.agent_id, image.kf_id) == (AGENT, 17)
    assert image.rgb is not None and image.rgb.shape == (48, 64, 3)
    assert elapsed < PROMPT_S  # the answer ends the query, not its timeout
    # Nobody serves another agent's images: an empty answer, not a wait for the timeout.
    start = time.monotonic()
    assert server.query(keys.agent_image(SESSION, "agent-9", 1), timeout_s=30.0) == []
    assert time.monotonic() - start < PROMPT_S


def test_slow_subscriber_drops_without_blocking_publisher(server_and_agent) -> None:
    server, _, _ = server_and_agent
    n = 300
    start = time.perf_counter()
    for i in range(n):
        server.publish(lb_key("flood"), i.to_bytes(4, "little") + bytes(10_000))
    publish_s = time.perf_counter() - start
    # The peer needs 300 x FLOOD_SLEEP_S = 30 s to handle them all; publishing takes well
    # under a second, so the bound only catches a publisher that waits for the peer.
    assert publish_s < PROMPT_S

    def peer_stats() -> dict:
        [reply] = server.query(lb_key("stats"), timeout_s=30.0)
        return json.loads(reply.payload)

    assert wait_until(
        lambda: peer_stats()["stats"]["received"].get(lb_key("flood"), {}).get("messages") == n,
        timeout=60.0,
    )

    def settled() -> bool:  # every sample handled or dropped, none left in the queue
        report = peer_stats()
        return report["handled"] + report["stats"]["dropped"].get(lb_key("flood"), 0) == n

    assert wait_until(settled, timeout=60.0)
    report = peer_stats()
    dropped = report["stats"]["dropped"][lb_key("flood")]
    assert dropped > 0
    assert report["handled"] + dropped == n
    assert report["stats"]["received"][lb_key("flood")]["bytes"] == n * 10_004


@pytest.mark.parametrize("peer_role", ["client", "router"])
def test_killed_process_leaves_promptly(spawn, endpoint: str, peer_role: str) -> None:
    """SIGKILL an agent (client) or the server (router): the other side sees it leave (the
    socket closes; at the latest the 2 s lease ends)."""
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
    assert wait_until(lambda: token in seen.joins)

    killed_at = time.monotonic()
    peer.kill()
    assert wait_until(lambda: token in seen.leaves)
    assert seen.leaves[token] - killed_at < PROMPT_S
    start = time.monotonic()
    bus.close()
    assert time.monotonic() - start < bus.close_timeout_s + PROMPT_S


def test_peer_exits_cleanly_and_its_token_leaves(server_and_agent) -> None:
    _, peer, seen = server_and_agent
    assert peer.stop() == 0
    peer.expect("CLOSED", timeout=30.0)
    assert wait_until(lambda: keys.alive_agent(SESSION, AGENT) in seen.leaves)


def test_hung_process_leaves_after_its_lease(spawn, endpoint: str) -> None:
    """SIGSTOP (hung, socket still open): only the lease (2 s in bus_peer) can tell."""
    bus = ZenohBus(mode="router", listen=[endpoint], lease_s=2.0)
    peer = spawn("bus_peer.py", "--connect", endpoint)
    peer.expect("READY")
    seen = Joined()
    token = keys.alive_agent(SESSION, AGENT)
    bus.watch_liveliness(keys.alive_agents(SESSION), seen.on_join, seen.on_leave)
    assert wait_until(lambda: token in seen.joins)
    stopped_at = time.monotonic()
    peer.proc.send_signal(signal.SIGSTOP)
    try:
        assert wait_until(lambda: token in seen.leaves)
        # Not before the lease could have run out (load only makes it later); the upper
        # bound is generous: the lease plus room for a loaded machine.
        assert 1.0 < seen.leaves[token] - stopped_at < 2.0 + PROMPT_S
        # Publishing towards the hung peer must not wedge the publisher for long.
        start = time.monotonic()
        bus.publish(lb_key("flood"), bytes(1000))
        assert time.monotonic() - start < PROMPT_S
    finally:
        peer.proc.send_signal(signal.SIGCONT)
    bus.close()

"""A hostile peer on the server's bus does no harm: a flood of malformed messages on distinct
keys, thousands of invented agent ids and a sub-map delta removing a million ids leave the
server's memory under a fixed budget, every poll short and the status query answering."""

from __future__ import annotations

import time
import tracemalloc
from pathlib import Path

import numpy as np
import pytest

from cpslam import protocol
from cpslam.common.bus import InMemoryBus, InMemoryNetwork, bus_from_config
from cpslam.common.config import load_config
from cpslam.protocol import FramePoses, Status, SubmapDelta, keys
from cpslam.server.node import ServerNode

SESSION = "default"
MALFORMED = 100_000
AGENT_IDS = 10_000
REMOVED = 1_000_000
# Messages offered between two polls: below the server's queue (transport.queue_size, at
# least 1024), so nothing is lost and every message is counted; a poll decodes what is queued,
# so its time is bounded by the queue, a well-formed message costing far more than a byte.
CHUNK = 1_000
AGENT_CHUNK = 250
# Generous bounds valid on any machine: what the server holds is capped by the limits
# section (about 40 MiB here, the 8 MB delta encoded and decoded included); what the flood
# offered would take far more if it were kept.
MEMORY_BUDGET_MB = 96
POLL_BUDGET_S = 1.0


def _settle(bus: InMemoryBus) -> None:
    """Everything sent before has been delivered (the network's one dispatcher is ordered)."""
    with bus.subscribe("test/settle") as marker:
        bus.publish("test/settle", b"")
        assert marker.get(timeout=60.0) is not None


@pytest.mark.slow
def test_flood_of_bad_input_stays_bounded_and_status_answers(tmp_path: Path) -> None:
    cfg = load_config("tiny", overrides=["transport.backend=memory"], env={})
    network = InMemoryNetwork()
    server_bus = bus_from_config(cfg.transport, "server", network, cfg.limits)
    attacker, client = InMemoryBus(network), InMemoryBus(network)
    node = ServerNode(cfg, server_bus, tmp_path).start()
    polls: list[float] = []
    # The attacker writes straight onto the wire (the network hub), not through a `Bus` of
    # ours: only the server's bookkeeping is under test.
    wire = network.publish

    def poll() -> None:
        _settle(attacker)
        t0 = time.perf_counter()
        node.poll()
        polls.append(time.perf_counter() - t0)

    tracemalloc.start()
    try:
        # 1. One-byte malformed messages, each on a key of its own.
        for start in range(0, MALFORMED, CHUNK):
            for i in range(start, start + CHUNK):
                wire(keys.agent_topic(SESSION, f"m{i}", "keyframe"), b"\x00")
            poll()
        # 2. Well-formed messages from ten thousand invented agent ids.
        for start in range(0, AGENT_IDS, AGENT_CHUNK):
            for i in range(start, start + AGENT_CHUNK):
                msg = FramePoses(
                    agent_id=f"fake{i}",
                    seq=0,
                    frame_indices=[0],
                    stamps=[0.0],
                    kf_ids=[0],
                    T_kf_frame=np.eye(4)[None],
                )
                wire(keys.agent_topic(SESSION, f"fake{i}", "frames"), protocol.encode(msg))
            poll()
        # 3. One sub-map delta (8 MB) removing a million point ids, from an admitted agent.
        delta = SubmapDelta(
            agent_id="fake0",
            seq=1,
            point_ids=np.zeros(0, np.int64),
            anchor_kf_ids=np.zeros(0, np.int32),
            xyz_local=np.zeros((0, 3), np.float32),
            features=np.zeros((0, cfg.field.feature_dim), np.float16),
            colors=np.zeros((0, 3), np.uint8),
            removed_ids=np.arange(REMOVED, dtype=np.int64),
        )
        wire(keys.agent_submap(SESSION, "fake0"), protocol.encode(delta))
        poll()
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()

    replies = client.query(keys.server_status(SESSION), timeout_s=30.0)
    assert len(replies) == 1 and replies[0].ok
    assert len(replies[0].payload) <= cfg.limits.status_reply_kb * 1024
    summary = protocol.decode(replies[0].payload, expected=Status).summary

    limits = cfg.limits
    registry = node.backend.registry
    assert len(registry.agents) == limits.max_agents
    assert registry.refused_agents == AGENT_IDS - limits.max_agents
    assert len(node.dropped) <= limits.max_counter_keys
    assert node.dropped.total() == MALFORMED
    assert len(node._received.table()) <= limits.max_counter_keys + 1
    assert not registry.agents["fake0"].points.tombstones  # refused, not processed
    assert any("removed_ids has 1000000 ids" in r for r in registry.dropped)
    assert summary["dropped"]["agent cap reached"] == AGENT_IDS - limits.max_agents

    print(
        f"flood: {len(polls)} polls, worst {max(polls):.3f} s, "
        f"tracemalloc peak {peak / 2**20:.1f} MiB, status {len(replies[0].payload)} bytes"
    )
    assert max(polls) < POLL_BUDGET_S
    assert peak < MEMORY_BUDGET_MB * 2**20
    node.close()
    for bus in (attacker, client, server_bus):
        bus.close()

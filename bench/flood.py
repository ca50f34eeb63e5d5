"""What a hostile peer's flood costs the server: memory, poll time and the status reply.

A `ServerNode` (tiny preset, in-memory bus) is offered, straight on the wire: `--malformed`
one-byte messages each on a key of its own, well-formed frame poses from `--agents` invented
agent ids, and one sub-map delta removing `--removed` point ids. Between two polls at most
`--chunk` messages arrive (below the server's queue, so every message is handled). Per phase
the bench records the worst poll, and over the whole flood the tracemalloc peak, what the
server holds (agents, counter keys, tombstones) and the size of its status reply.

`--caps off` raises every cap of the `limits` section out of reach (what the server did before
it had them); compare it with the default `--caps on` at the same sizes. Polls are timed with
tracemalloc on, which slows them (a few times) alike in both settings.

Usage: python bench/flood.py [--malformed 100000] [--agents 10000] [--removed 1000000]
           [--chunk 1000] [--caps on|off] [--json bench/results/flood.json]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchinfo import bench_header  # noqa: E402

UNCAPPED = [
    "limits.max_agents=1000000000",
    "limits.max_counter_keys=1000000000",
    "limits.max_removed_per_message=1000000000",
    "limits.max_tombstones=1000000000",
    "limits.max_seq_ahead=1000000000",
]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--malformed", type=int, default=100_000)
    parser.add_argument("--agents", type=int, default=10_000)
    parser.add_argument("--removed", type=int, default=1_000_000)
    parser.add_argument("--chunk", type=int, default=1_000)
    parser.add_argument("--caps", choices=("on", "off"), default="on")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    report = bench_header("flood", sys.argv)
    report["caps"] = args.caps
    report["offered"] = {
        "malformed": args.malformed,
        "agents": args.agents,
        "removed_ids": args.removed,
    }
    report["result"] = flood(
        args.malformed,
        args.agents,
        args.removed,
        args.chunk,
        UNCAPPED if args.caps == "off" else [],
    )
    print(json.dumps(report["result"], indent=2))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(report, indent=2) + "\n")
        print(f"wrote {args.json}")


def flood(malformed: int, agents: int, removed: int, chunk: int, overrides: list[str]) -> dict:
    """Run the three phases; the figures of the result JSON."""
    import logging

    import numpy as np

    from cpslam import protocol
    from cpslam.common.bus import InMemoryBus, InMemoryNetwork, bus_from_config
    from cpslam.common.config import load_config
    from cpslam.protocol import FramePoses, SubmapDelta, keys
    from cpslam.server.node import ServerNode

    logging.disable(logging.WARNING)  # the drops are the point; their lines are not
    cfg = load_config("tiny", overrides=["transport.backend=memory", *overrides], env={})
    s = cfg.transport.session
    network = InMemoryNetwork()
    server_bus = bus_from_config(cfg.transport, "server", network, cfg.limits)
    probe, client = InMemoryBus(network), InMemoryBus(network)
    worst: dict[str, float] = {}
    with tempfile.TemporaryDirectory(prefix="bench-flood-") as tmp:
        node = ServerNode(cfg, server_bus, tmp).start()

        def poll(phase: str) -> None:
            with probe.subscribe("bench/settle") as marker:  # everything sent has arrived
                probe.publish("bench/settle", b"")
                marker.get(timeout=600.0)
            t0 = time.perf_counter()
            node.poll()
            worst[phase] = max(worst.get(phase, 0.0), time.perf_counter() - t0)

        t_start = time.perf_counter()
        tracemalloc.start()
        for start in range(0, malformed, chunk):
            for i in range(start, min(start + chunk, malformed)):
                network.publish(keys.agent_topic(s, f"m{i}", "keyframe"), b"\x00")
            poll("malformed")
        step = max(chunk // 4, 1)  # a well-formed message costs the poll far more
        for start in range(0, agents, step):
            for i in range(start, min(start + step, agents)):
                msg = FramePoses(
                    agent_id=f"fake{i}",
                    seq=0,
                    frame_indices=[0],
                    stamps=[0.0],
                    kf_ids=[0],
                    T_kf_frame=np.eye(4)[None],
                )
                network.publish(keys.agent_topic(s, f"fake{i}", "frames"), protocol.encode(msg))
            poll("agent_ids")
        delta = SubmapDelta(
            agent_id="fake0",
            seq=1,
            point_ids=np.zeros(0, np.int64),
            anchor_kf_ids=np.zeros(0, np.int32),
            xyz_local=np.zeros((0, 3), np.float32),
            features=np.zeros((0, cfg.field.feature_dim), np.float16),
            colors=np.zeros((0, 3), np.uint8),
            removed_ids=np.arange(removed, dtype=np.int64),
        )
        network.publish(keys.agent_submap(s, "fake0"), protocol.encode(delta))
        poll("removed_ids")
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
        seconds = time.perf_counter() - t_start
        t0 = time.perf_counter()
        replies = client.query(keys.server_status(s), timeout_s=60.0)
        status_s = time.perf_counter() - t0
        registry = node.backend.registry
        out = {
            "worst_poll_s": {k: round(v, 4) for k, v in worst.items()},
            "tracemalloc_peak_mb": round(peak / 2**20, 1),
            "seconds": round(seconds, 1),
            "agents_held": len(registry.agents),
            "drop_counter_keys": len(node.dropped),
            "tombstones": sum(len(r.points.tombstones) for r in registry.agents.values()),
            "status_bytes": len(replies[0].payload) if replies else None,
            "status_s": round(status_s, 3),
        }
        node.close()
    for bus in (probe, client, server_bus):
        bus.close()
    return out


if __name__ == "__main__":
    main()

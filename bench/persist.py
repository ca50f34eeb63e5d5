"""How long persisting the server state stalls the poll loop as the state grows: the worst
and median `ServerNode.poll` time with the state written in the loop
(``persist_background=False``: serialise, write, fsync before the poll returns), by the
writer thread (the poll only snapshots; `cpslam.server.persist.StateWriter`) and not at all
(no state file: the poll's own work, the baseline).

One agent's keyframes and map points are fed to a real node on the in-memory bus until it
holds each of `--keyframes` sizes (`--points-per-kf` points per keyframe, the preset's
feature size); then `--polls` polls each receive one more keyframe and snapshot the state
(``persist_every_s=0``). Loops are switched off (both thresholds 1.0) so a poll's time is
the message, the back-end step and persistence. The state file goes to `--dir` (default: a
temporary folder; pick a real disk, a tmpfs fsync costs nothing).

Usage: python bench/persist.py [--keyframes 10 100 1000] [--points-per-kf 500] [--polls 5]
           [--preset cpu] [--dir DIR] [--json bench/results/persist.json]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchinfo import bench_header  # noqa: E402

SESSION = "bench"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--keyframes", type=int, nargs="+", default=[10, 100, 1000])
    parser.add_argument("--points-per-kf", type=int, default=500)
    parser.add_argument("--polls", type=int, default=5)
    parser.add_argument("--preset", default="cpu")
    parser.add_argument("--dir", type=Path, help="folder for the state file (default: temp)")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()

    import torch

    torch.set_num_threads(1)
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench-persist-", dir=args.dir) as tmp:
        for mode in ("off", "loop", "thread"):
            rows += _grow(Path(tmp) / mode, mode, args)
    report = {
        **bench_header("persist", sys.argv),
        "preset": args.preset,
        "points_per_kf": args.points_per_kf,
        "polls": args.polls,
        "rows": rows,
    }
    print(json.dumps(rows, indent=1))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(report, indent=1) + "\n")
        print(f"wrote {args.json}")


def _grow(folder: Path, mode: str, args: argparse.Namespace) -> list[dict]:
    """Grow one node's state through the sizes; measure `--polls` polls at each."""
    from cpslam.common.bus import InMemoryBus, InMemoryNetwork
    from cpslam.common.config import load_config
    from cpslam.protocol import keys
    from cpslam.server.node import ServerNode

    cfg = load_config(
        args.preset,
        env={},
        overrides=[
            f"transport.session={SESSION}",
            "loop.lambda_fine=1.0",
            "loop.lambda_coarse=1.0",
        ],
    )
    network = InMemoryNetwork()
    server_bus, agent_bus = InMemoryBus(network), InMemoryBus(network)
    node = ServerNode(
        cfg,
        server_bus,
        folder,
        state_path=None if mode == "off" else folder / "state.pt",
        persist_every_s=0.0,
        persist_background=mode == "thread",
    ).start()
    from cpslam.common.place_recognition import descriptor_dim

    feature_dim, args.descriptor_dim = cfg.field.feature_dim, descriptor_dim(cfg.place_recognition)
    key_kf, key_pts = keys.agent_keyframe(SESSION, "a"), keys.agent_submap(SESSION, "a")
    sent = [0, 0]  # next seq, next keyframe id
    rows = []
    for size in args.keyframes:
        # Bulk growth: keyframes and their points in one poll, persisted once, not timed.
        _send(agent_bus, key_kf, key_pts, sent, size - args.polls - sent[1], args, feature_dim)
        node.poll()
        node.persist()
        held = len(node.backend.registry.agents["a"].keyframes)
        if held != sent[1]:  # a bench whose messages are dropped measures nothing
            raise SystemExit(f"the server holds {held} of {sent[1]} keyframes: see its log")
        times = []
        for _ in range(args.polls):
            _send(agent_bus, key_kf, key_pts, sent, 1, args, feature_dim)
            t0 = time.perf_counter()
            node.poll()
            times.append(time.perf_counter() - t0)
            if mode == "thread":
                node.writer.wait(node.writer.durable_gen + 1, timeout_s=600.0)
        node.persist()
        state = folder / "state.pt"
        rows.append(
            {
                "mode": mode,
                "keyframes": sent[1],
                "state_mb": round(state.stat().st_size / 1e6, 2) if state.is_file() else None,
                "poll_max_s": round(max(times), 4),
                "poll_median_s": round(statistics.median(times), 4),
                "write_s": round(node.writer.seconds_last, 4) if node.writer else None,
            }
        )
        print(rows[-1], flush=True)
    node.close()
    server_bus.close()
    agent_bus.close()
    return rows


def _send(bus, key_kf: str, key_pts: str, sent: list[int], n: int, args, feature_dim: int) -> None:
    """`n` keyframes of agent "a" and `--points-per-kf` points anchored to each."""
    from cpslam import protocol
    from cpslam.protocol import KeyframeMsg, SubmapDelta

    if n <= 0:
        return
    rng = np.random.default_rng(sent[1])
    kf_ids = np.arange(sent[1], sent[1] + n)
    for kf in kf_ids:
        d = rng.standard_normal(args.descriptor_dim).astype(np.float32)
        msg = KeyframeMsg(
            agent_id="a",
            seq=sent[0],
            kf_id=int(kf),
            frame_index=int(kf) * 5,
            stamp=float(kf) / 6.0,
            world_epoch=0,
            T_world_cam=np.eye(4),
            T_prev_kf_kf=np.eye(4),
            descriptor=d / np.linalg.norm(d),
            n_points=args.points_per_kf,
        )
        bus.publish(key_kf, protocol.encode(msg))
        sent[0] += 1
    m = n * args.points_per_kf
    first_id = sent[1] * args.points_per_kf
    points = SubmapDelta(
        agent_id="a",
        seq=sent[0],
        point_ids=np.arange(first_id, first_id + m),
        anchor_kf_ids=np.repeat(kf_ids, args.points_per_kf).astype(np.int32),
        xyz_local=rng.uniform(-2, 2, (m, 3)).astype(np.float32),
        features=rng.standard_normal((m, feature_dim)).astype(np.float16),
        colors=rng.integers(0, 256, (m, 3), dtype=np.uint8),
        removed_ids=np.zeros(0, np.int64),
    )
    bus.publish(key_pts, protocol.encode(points))
    sent[0] += 1
    sent[1] += n
    with bus.subscribe("bench/settle") as marker:  # everything sent before has arrived
        bus.publish("bench/settle", b"")
        marker.get(timeout=60.0)


if __name__ == "__main__":
    main()

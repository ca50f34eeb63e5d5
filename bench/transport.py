"""Transport figures of the Zenoh bus between two processes on this machine, printed as JSON.

- latency: publish S bytes, the other process answers with an 8-byte ack; median and p95 of
  that round trip (about one-way delivery of S), for S = 1 kB, 1 MB, 10 MB;
- keyframe pull: a query answered with an encoded 640x480 KeyframeImage (what the server
  does for a loop candidate);
- throughput: N messages of S bytes published back to back until the other side has all;
- encoded sizes (and encode/decode times) of typical messages from `cpslam.protocol`.

Both processes use TCP on 127.0.0.1 with shared memory off (what two machines would see,
minus the wire), unless --shm. This process listens in router mode, the peer connects as client.
With --tls DIR (a folder made by `cpslam secure init`) the link is Zenoh mutual TLS instead:
this process listens with DIR/server.pem, the peer presents DIR/agent-0.pem. With
--compare-tls DIR both are measured in one run, TCP first, and the ratios TLS / TCP reported
(--json writes the report for docs/results.md).

Usage: python bench/transport.py [--quick] [--shm] [--tls DIR | --compare-tls DIR]
           [--json bench/results/transport.json]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import socket
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchinfo import bench_header  # noqa: E402

from cpslam import protocol
from cpslam.common.bus import Sample, ZenohBus, ZenohSecurity
from cpslam.protocol.samples import sample

ALIVE = "bench/alive/peer"
KB, MB = 1000, 1_000_000


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer repetitions")
    parser.add_argument("--shm", action="store_true", help="allow Zenoh shared memory")
    parser.add_argument("--tls", type=Path, metavar="DIR",
                        help="mutual TLS with the certificates of `cpslam secure init` in DIR")
    parser.add_argument("--compare-tls", type=Path, metavar="DIR",
                        help="measure TCP, then mutual TLS with the certificates in DIR")
    parser.add_argument("--json", type=Path, help="also write the report here")
    parser.add_argument("--peer", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--connect", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.peer:
        run_peer(args.connect, args.shm, args.tls)
        return

    if args.compare_tls is not None:
        links = {"tcp": measure(args.quick, args.shm, None),
                 "tls": measure(args.quick, args.shm, args.compare_tls)}
        report = {**bench_header("transport", sys.argv), "links": links,
                  "ratio_tls_over_tcp": ratios(links["tcp"], links["tls"])}
    else:
        report = measure(args.quick, args.shm, args.tls)
    text = json.dumps(report, indent=2)
    if args.json is not None:
        args.json.write_text(text + "\n")
    print(text)


def measure(quick: bool, shm: bool, tls: Path | None) -> dict:
    """The figures of one link (TCP, or mutual TLS with the certificates in `tls`)."""
    # "localhost" is a name in the server certificate of `cpslam secure init`.
    endpoint = f"tls/localhost:{free_port()}" if tls else f"tcp/127.0.0.1:{free_port()}"
    bus = ZenohBus(mode="router", listen=[endpoint], shared_memory=shm,
                   security=security(tls, "server"))
    present = threading.Event()
    bus.watch_liveliness(ALIVE, on_join=lambda key: present.set())
    cmd = [sys.executable, __file__, "--peer", "--connect", endpoint,
           *(["--tls", str(tls)] if tls else [])]
    peer = subprocess.Popen(cmd + (["--shm"] if shm else []), stdin=subprocess.PIPE)
    try:
        if not present.wait(30.0):
            raise RuntimeError("the benchmark peer did not come up within 30 s")
        scale = 0.25 if quick else 1.0
        return {
            "machine": machine(),
            "transport": {"endpoint": endpoint, "mutual_tls": tls is not None,
                          "shared_memory": shm},
            "latency_ms": {
                label: latency(bus, size, max(5, int(rounds * scale)))
                for label, size, rounds in (
                    ("1kB", KB, 200),
                    ("1MB", MB, 40),
                    ("10MB", 10 * MB, 20),
                )
            },
            "keyframe_image_query_ms": image_query(bus, max(5, int(30 * scale))),
            "throughput_MB_per_s": {
                label: throughput(bus, size, max(4, int(count * scale)))
                for label, size, count in (("1MB", MB, 100), ("10MB", 10 * MB, 20))
            },
            "encoded": encoded_sizes(),
        }
    finally:
        peer.stdin.close()
        try:
            peer.wait(10.0)
        except subprocess.TimeoutExpired:
            peer.kill()
        bus.close()


def ratios(tcp: dict, tls: dict) -> dict:
    """TLS / TCP of the median latencies and the throughputs."""
    return {
        "latency_median": {k: round(tls["latency_ms"][k]["median"] / v["median"], 3)
                           for k, v in tcp["latency_ms"].items()},
        "throughput": {k: round(tls["throughput_MB_per_s"][k] / v, 3)
                       for k, v in tcp["throughput_MB_per_s"].items()},
    }


# -- the peer process --------------------------------------------------------------------------


def security(folder: Path | None, name: str) -> ZenohSecurity | None:
    """Mutual TLS with `name`'s certificate from a `cpslam secure init` folder (None: TCP)."""
    if folder is None:
        return None
    return ZenohSecurity(root_ca=folder / "ca.pem", cert=folder / f"{name}.pem",
                         key=folder / f"{name}-key.pem", mtls=True)


def run_peer(connect: str, shm: bool, tls: Path | None) -> None:
    bus = ZenohBus(mode="client", connect=[connect], shared_memory=shm,
                   security=security(tls, "agent-0"))
    counts = {"messages": 0, "bytes": 0}
    image = protocol.encode(sample("keyframe_image", width=640, height=480, rgb_codec="png"))

    def ack(s: Sample) -> None:
        bus.publish("bench/ack", s.payload[:8])

    def count(s: Sample) -> None:
        counts["messages"] += 1
        counts["bytes"] += len(s.payload)
        expected = int.from_bytes(s.payload[8:16], "little")
        if counts["messages"] == expected:
            bus.publish("bench/done", json.dumps(counts).encode())
            counts.update(messages=0, bytes=0)

    bus.subscribe("bench/ping", callback=ack, queue_size=1024)
    # Large enough that the throughput run never drops: we measure the link, not the queue.
    bus.subscribe("bench/flood", callback=count, queue_size=4096)
    bus.declare_queryable("bench/image/*", lambda key, payload: image)
    bus.declare_liveliness(ALIVE)
    sys.stdin.read()
    bus.close()


# -- measurements --------------------------------------------------------------------------------


def latency(bus: ZenohBus, size: int, rounds: int) -> dict[str, float]:
    acks = bus.subscribe("bench/ack", queue_size=16)
    payload = bytearray(size)
    times = []
    try:
        for i in range(rounds + 2):  # two warm-up rounds
            payload[:8] = i.to_bytes(8, "little")
            start = time.perf_counter()
            bus.publish("bench/ping", payload)
            while True:
                s = acks.get(timeout=10.0)
                if s is None:
                    raise RuntimeError(f"no ack for a {size}-byte message within 10 s")
                if int.from_bytes(s.payload, "little") == i:
                    break
            if i >= 2:
                times.append(time.perf_counter() - start)
    finally:
        acks.close()
    return summary(times)


def image_query(bus: ZenohBus, rounds: int) -> dict[str, float]:
    times, size = [], 0
    for i in range(rounds + 2):
        start = time.perf_counter()
        replies = bus.query(f"bench/image/{i}", timeout_s=10.0)
        if len(replies) != 1:
            raise RuntimeError(f"keyframe image query got {len(replies)} replies")
        if i >= 2:
            times.append(time.perf_counter() - start)
        size = len(replies[0].payload)
    return {**summary(times), "reply_bytes": size}


def throughput(bus: ZenohBus, size: int, count: int) -> float:
    done = bus.subscribe("bench/done", queue_size=4)
    payload = bytearray(size)
    payload[8:16] = count.to_bytes(8, "little")
    try:
        start = time.perf_counter()
        for _ in range(count):
            bus.publish("bench/flood", payload)
        s = done.get(timeout=120.0)
        elapsed = time.perf_counter() - start
    finally:
        done.close()
    if s is None:
        raise RuntimeError(f"the peer did not receive {count} x {size} bytes within 120 s")
    received = json.loads(s.payload)
    if received["bytes"] != size * count:
        raise RuntimeError(f"the peer received {received} instead of {count} x {size} bytes")
    return round(size * count / elapsed / MB, 1)


def encoded_sizes() -> dict[str, dict[str, float]]:
    decoder = sample("decoder_weights", n_params=100_000)
    n_params = sum(t.size for t in decoder.tensors.values())
    messages = {
        "keyframe (1024-d descriptor)": sample("keyframe", descriptor_dim=1024),
        "submap_delta (10k points, 32-d f16 features)": sample("submap_delta", n_points=10_000),
        f"decoder_weights ({n_params} params)": decoder,
        "frame_poses (50 frames)": sample("frame_poses", n_frames=50),
        "keyframe_image (640x480, png rgb + depth)": sample(
            "keyframe_image", width=640, height=480, rgb_codec="png"
        ),
        "keyframe_image (640x480, jpeg rgb + depth)": sample(
            "keyframe_image", width=640, height=480, rgb_codec="jpeg"
        ),
        "server_update (1k foreign points)": sample("server_update", n_points=1000),
    }
    out = {}
    for name, msg in messages.items():
        encode_s = timed(lambda m=msg: protocol.encode(m))
        data = protocol.encode(msg)
        decode_s = timed(lambda d=data: protocol.decode(d))
        out[name] = {
            "bytes": len(data),
            "encode_ms": round(encode_s * 1e3, 2),
            "decode_ms": round(decode_s * 1e3, 2),
        }
    return out


# -- helpers ------------------------------------------------------------------------------------


def summary(seconds: list[float]) -> dict[str, float]:
    ms = sorted(t * 1e3 for t in seconds)
    p95 = ms[min(len(ms) - 1, int(round(0.95 * (len(ms) - 1))))]
    return {"median": round(statistics.median(ms), 3), "p95": round(p95, 3), "n": len(ms)}


def timed(fn, repeat: int = 5) -> float:
    best = float("inf")
    for _ in range(repeat):
        start = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - start)
    return best


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def machine() -> dict[str, object]:
    return {
        "cpu": platform.processor() or platform.machine(),
        "cores": os.cpu_count(),
        "python": platform.python_version(),
        "system": platform.platform(),
    }


if __name__ == "__main__":
    main()

"""How the server scales with agents: one recorded agent replayed as N agents over Zenoh TCP.

Sixteen real agents do not fit on two cores, so the bench records one real agent once (a
tiny-preset `cpslam run` with ``link.record`` on, cached under ``--cache``; ``--sources K``:
K pieces of one sequence, each overlapping the next by half, recorded alone, replica k
replaying piece k mod K) and, per N in ``--agents``, starts a real
``cpslam-server`` process (tiny preset, Zenoh TCP on a free 127.0.0.1 port, shared memory
off) and replays the recordings as N agents (`cpslam.tools.replay`): distinct ids and
incarnations, each in its own world (a random rigid transform of seed ``--seed``), at the
recorded rate times ``--speed`` (``--clock sensor``: as an agent keeping up with its 30 Hz
camera; ``wall``: as fast as the recording ran), acks and image requests answered. Replicas
are maps of one scene in N frames: the server must find the loops between them and merge
them. Once everything is acknowledged the replicas stay up (answering image requests) until
the server has no loop candidate left to verify (at most ``--linger`` seconds: a pair whose
images can no longer be pulled is never verified); the replay figures cover that whole
time (``--server-set KEY=VALUE``: a config override for the server). Then it finalises
(``cpslam finalise``) and the bench reads the server's ``metrics.json`` and trajectories.

Per N: messages the server handled per second of replay; the server's CPU share over the
replay (``/proc/<pid>/stat``, 1.0 = one core); the worst and 99th-percentile poll (a message
that arrives as a poll begins waits that long) and the deepest queue at the start of a poll
(``metrics.json`` process.poll); the server's peak RSS; merges, when the last one happened
(seconds into the replay, seen by polling the status every 0.5 s) and the time spent
verifying loops; loops found/accepted; the joint ATE (one se3 alignment, metres) of every
replica's final global trajectory against its recorded sequence's ground truth (replica k's
ground truth is the recorded one moved by its transform T_k; in the group frame the true
alignment C inv(T_k) takes it back to C times the recorded one, one C for all replicas; the
pieces' ground truths share the sequence's frame);
and bytes per agent per key expression, both ways, averaged over the replicas (resends
included: ``resent`` counts the messages the replicas published again).

Usage: python bench/scale.py [--agents 1 2 4 8 16] [--frames 30] [--speed 1.0] [--seed 0]
           [--clock sensor|wall] [--linger 120] [--sources 1] [--seq PATH] [--cache DIR]
           [--json bench/results/scale.json]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchinfo import bench_header  # noqa: E402
from scale_report import print_row, summarise  # noqa: E402

SESSION = "scale"
ENV = {**os.environ, "OMP_NUM_THREADS": "1", "CPSLAM_RUN__NUM_THREADS": "1"}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--agents", type=int, nargs="+", default=[1, 2, 4, 8, 16])
    parser.add_argument("--frames", type=int, default=30, help="frames of each recorded piece")
    parser.add_argument(
        "--seq", type=Path, help="record this sequence instead (with ground truth for the ATE)"
    )
    parser.add_argument(
        "--sources",
        type=int,
        default=1,
        help="record this many pieces of --frames frames of one sequence, each overlapping "
        "the next by half, each alone; replica k replays recording k mod sources",
    )
    parser.add_argument("--speed", type=float, default=1.0)
    parser.add_argument(
        "--clock",
        choices=("sensor", "wall"),
        default="sensor",
        help="replay at the frames' sensor time or at the recording's wall time",
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--linger",
        type=float,
        default=120.0,
        help="after everything is acknowledged, keep the replicas up at most "
        "this long while the server still has loop candidates to verify",
    )
    parser.add_argument(
        "--server-set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="config override for the server (repeatable), e.g. loop.spacing=3",
    )
    parser.add_argument("--cache", type=Path, default=Path(tempfile.gettempdir()) / "cpslam-scale")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    if min(args.agents) < 1 or args.speed <= 0 or args.frames < 2 or not 1 <= args.sources <= 8:
        parser.error("--agents must be >= 1, --speed > 0, --frames >= 2, --sources in [1, 8]")
    report = bench_header("scale", sys.argv)
    sources = record(args.cache, args.frames, args.seq, args.sources)
    report.update(
        {
            "frames": args.frames if args.seq is None else None,
            "speed": args.speed,
            "clock": args.clock,
            "linger_max_s": args.linger,
            "seed": args.seed,
            "server_sets": args.server_set,
            "sequence": "synthetic room" if args.seq is None else args.seq.name,
            "sources": len(sources),
            "runs": [],
        }
    )
    for n in args.agents:
        row = run_one(
            n, sources, args.cache / f"n{n}", args.speed, args.seed, args.clock, args.linger,
            args.server_set,
        )
        report["runs"].append(row)
        print_row(row)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(report, indent=1) + "\n")
        print(f"wrote {args.json}")


def record(
    cache: Path, frames: int, seq: Path | None, sources: int = 1
) -> list[tuple[Path, str, Path]]:
    """The recorded pieces and their wire recordings, ``[(sequence, frames, wire.rec)]``:
    `seq`, or a synthetic room cut into `sources` pieces of `frames` frames, each
    overlapping the next by half (two agents that walk one path in turn and share views),
    each recorded alone (made once per cache folder and protocol version)."""
    from cpslam.common.config import load_config, override_config
    from cpslam.common.datasets import open_sequence
    from cpslam.protocol import PROTOCOL_VERSION
    from cpslam.run import run_collab

    step = frames // 2
    cache = cache / f"protocol{PROTOCOL_VERSION}"  # a recording holds encoded messages
    if seq is not None:
        base = cache / f"seq-{seq.resolve().name}"
    else:
        base = cache / (f"synth-room-{frames}" + (f"-x{sources}" if sources > 1 else ""))
        seq = base / "room" / "agent_0"
    out = [
        (
            seq,
            f"{i * step}:{i * step + frames}",
            base / ("run" if i == 0 else f"run{i}") / "agent_0" / "wire.rec",
        )
        for i in range(sources)
    ]
    if all(rec.is_file() for _, _, rec in out):
        return out
    if not seq.exists():
        from cpslam.tools.synth import generate

        generate(
            base / "room",
            scene="room",
            frames=frames + (sources - 1) * step,
            width=160,
            height=120,
            seed=0,
            overwrite=True,
        )
    from cpslam.common.device import configure_torch

    cfg = override_config(load_config("tiny"), ["mapping.iters_first=30", "link.record=true"])
    configure_torch(cfg.run.num_threads, cfg.run.deterministic)  # as `cpslam run` does
    for path, piece, rec in out:
        print(f"recording {path} frames {piece} ...", flush=True)
        run_collab(cfg, [open_sequence(path).select(piece)], rec.parent.parent, show_progress=False)
    return out


def run_one(
    n: int,
    sources: list[tuple[Path, str, Path]],
    out: Path,
    speed: float,
    seed: int,
    clock: str,
    linger_s: float,
    server_sets: tuple[str, ...] | list[str] = (),
) -> dict:
    from cpslam.agent.daemon import ServerPresence
    from cpslam.agent.recording import read_recording
    from cpslam.common.bus import open_client
    from cpslam.common.config import load_config, override_config
    from cpslam.common.config.cli import transport_sets
    from cpslam.demo import free_port
    from cpslam.tools.replay import ReplayAgent, Replica, random_rigid, replay

    recordings = [read_recording(rec) for _, _, rec in sources]
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    # a fresh server: one finding its earlier state there would resume it (and refuse the
    # replicas' new incarnations under the same ids)
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    server_dir = out / "server"
    log = (out / "server.log").open("w")
    server = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "cpslam.server.cli",
            "--listen",
            endpoint,
            "--session",
            SESSION,
            "--preset",
            "tiny",
            "--out",
            str(server_dir),
            "--no-report",
            "--persist-every",
            "0.2",
            *(arg for kv in server_sets for arg in ("--set", kv)),
        ],
        stdout=log,
        stderr=subprocess.STDOUT,
        env=ENV,
    )
    cfg = override_config(
        load_config("tiny"), [*transport_sets(SESSION, None, [endpoint]), "transport.mode=client"]
    )
    buses = []
    try:
        rng = np.random.default_rng(seed)
        replicas = [
            Replica(f"r{k}", recordings[k % len(recordings)], random_rigid(rng)) for k in range(n)
        ]
        for _ in range(n + 1):
            bus = open_client(cfg.transport, 60.0, "scale bench", limits=cfg.limits)
            if bus is None:
                raise RuntimeError(f"no cpslam-server at {endpoint}; see {out / 'server.log'}")
            buses.append(bus)
        presence = ServerPresence(buses[0], SESSION)
        if not presence.wait(60.0):
            raise RuntimeError(f"the server never showed its token; see {out / 'server.log'}")
        presence.close()
        agents = [
            ReplayAgent(r, bus, SESSION, speed, zstd_level=cfg.link.zstd_level, clock=clock).start()
            for r, bus in zip(replicas, buses[1:], strict=True)
        ]
        time.sleep(0.5)  # let the server see the tokens before the first messages
        watch = MergeWatch(buses[0])
        cpu0, t0 = cpu_seconds(server.pid), time.monotonic()
        watch.start(t0)
        played = replay(agents)
        linger(agents, watch, linger_s)
        cpu1, wall = cpu_seconds(server.pid), time.monotonic() - t0
        watch.stop()
        for agent in agents:
            agent.close()
        subprocess.run(
            [
                sys.executable,
                "-m",
                "cpslam",
                "finalise",
                "--connect",
                endpoint,
                "--session",
                SESSION,
                "--timeout",
                "600",
            ],
            env=ENV,
            check=True,
            capture_output=True,
            timeout=660,
        )
        server.wait(120)
    finally:
        for bus in buses:
            bus.close()
        if server.poll() is None:
            server.kill()
            server.wait(10)
        log.close()
    metrics = json.loads((server_dir / "metrics.json").read_text())
    return summarise(
        n,
        metrics,
        server_dir,
        [sources[k % len(sources)][:2] for k in range(n)],
        replicas,
        played,
        wall,
        cpu1 - cpu0,
        watch.merged_at,
        sum(a.skipped for a in agents),
        sum(a.stats["resent"] for a in agents),
    )


class MergeWatch:
    """Polls the server's status every `every_s` for the time each merge appeared and for
    the loop candidates still waiting for verification."""

    def __init__(self, bus, every_s: float = 0.5) -> None:
        self.bus, self.every_s = bus, every_s
        self.merged_at: list[float] = []
        self.waiting: int | None = None
        """Loop candidates pending or retrying at the last status (None: no status yet)."""
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def start(self, t0: float) -> None:
        self.t0 = t0
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(10)

    def _run(self) -> None:
        from cpslam import protocol
        from cpslam.protocol import Status, keys

        while not self._stop.wait(self.every_s):
            for reply in self.bus.query(keys.server_status(SESSION), None, timeout_s=5.0):
                try:
                    summary = protocol.decode(reply.payload, expected=Status).summary
                    merges = summary["merges"]
                    loops = summary["loops"]
                    self.waiting = int(loops["pending"]) + int(loops["retrying"])
                except Exception:  # noqa: BLE001 - a late or trimmed reply: next poll
                    continue
                while len(self.merged_at) < int(merges):
                    self.merged_at.append(time.monotonic() - self.t0)


def linger(agents: list, watch: MergeWatch, max_s: float) -> None:
    """Keep the replicas up (answering image requests and updates) until the server has no
    loop candidate waiting, seen on two status polls in a row, or `max_s` passed: a pair
    whose images can no longer be pulled is never verified."""
    deadline = time.monotonic() + max_s
    quiet = 0
    while time.monotonic() < deadline and quiet < 2:
        for agent in agents:
            agent.poll()
        time.sleep(watch.every_s)
        quiet = quiet + 1 if watch.waiting == 0 else 0


def cpu_seconds(pid: int) -> float:
    """User plus system CPU seconds of a process (all threads) from /proc."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


if __name__ == "__main__":
    main()

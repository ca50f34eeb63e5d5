"""What a group's pose graph costs as the group grows: agents x keyframes per agent.

    python bench/pose_graph_cost.py                         # N = 2 4 8 16, K = 30 100 300
    python bench/pose_graph_cost.py --agents 16 --keyframes 1000 --json /tmp/pg.json

The server rebuilds a group's graph from its members' keyframe tracks and accepted loops and
optimises it whole once per poll step in which the group accepted loops (`Backend.optimise`,
docs/pose_graph.md). This
bench builds the same kind of graph with `PoseGraph` and the preset's `pose_graph` section:
N agents, each K keyframes along its own noisy walk (tracking drift: 1 mm and 0.05 degrees
per keyframe, a random walk), one loop every `--loop-every` keyframes to the next agent and
one within the agent (the true relative pose plus 5 mm / 0.1 degrees of noise, 5 % of them
replaced by false loops 0.5 m off). Per size it reports the seconds to build the graph and
to optimise it (best of `--repeats`), the nodes, edges and Levenberg-Marquardt iterations,
and the keyframe error against the truth before and after (the translation RMSE, m, of each
agent's track aligned at its first keyframe: the drift the loops take out).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchinfo import bench_header  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--agents", type=int, nargs="+", default=[2, 4, 8, 16])
    parser.add_argument("--keyframes", type=int, nargs="+", default=[30, 100, 300])
    parser.add_argument("--loop-every", type=int, default=10)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--preset", default="cpu")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    from cpslam.common.config import load_config

    cfg = load_config(args.preset, env={}).pose_graph
    rows = []
    for n in args.agents:
        for k in args.keyframes:
            rows.append(measure(cfg, n, k, args.loop_every, args.repeats, args.seed))
            print(json.dumps(rows[-1]), flush=True)
    report = {**bench_header("pose_graph_cost", sys.argv), "preset": args.preset,
              "loop_every": args.loop_every, "rows": rows}
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(report, indent=1) + "\n")
        print(f"wrote {args.json}")


def measure(cfg, n_agents: int, n_kf: int, loop_every: int, repeats: int, seed: int) -> dict:
    """Build and optimise one N x K graph `repeats` times; the best times and the errors."""
    from cpslam.server.pose_graph import PoseGraph

    rng = np.random.default_rng(seed)
    truth = [_walk(n_kf, offset=3.0 * a) for a in range(n_agents)]
    tracked = [_drift(rng, T) for T in truth]
    loops = _loops(rng, truth, loop_every)
    build_s, solve_s = [], []
    for _ in range(repeats):
        t0 = time.perf_counter()
        graph = PoseGraph.from_config(cfg)
        for a, T in enumerate(tracked):
            graph.add_trajectory(f"a{a}", _trajectory(T))
        for (a, i, b, j, T_ij) in loops:
            graph.add_loop(f"a{a}", i, f"a{b}", j, T_ij)
        t1 = time.perf_counter()
        result = graph.optimize()
        build_s.append(t1 - t0)
        solve_s.append(time.perf_counter() - t1)
    before = _rmse(truth, {(f"a{a}", i): T[i] for a, T in enumerate(tracked) for i in range(n_kf)})
    return {
        "agents": n_agents, "keyframes_per_agent": n_kf, "nodes": graph.num_nodes,
        "edges": graph.num_edges, "loops": len(loops),
        "build_s": round(min(build_s), 4), "optimise_s": round(min(solve_s), 4),
        "iterations": result.iterations,
        "outlier_loops": len(result.outlier_loops),
        "rmse_before_m": round(before, 4), "rmse_after_m": round(_rmse(truth, result.poses), 4),
    }


def _walk(n: int, offset: float) -> np.ndarray:
    """True keyframe poses [n, 4, 4]: a smooth loop of radius 1.5 m around x = offset."""
    from cpslam.common.geometry import se3_exp

    out = np.empty((n, 4, 4))
    for i in range(n):
        angle = 2 * np.pi * i / max(n, 1)
        T = se3_exp(np.array([0.0, 0.0, 0.0, 0.0, angle, 0.0]))
        T[:3, 3] = [offset + 1.5 * np.cos(angle), 0.1 * np.sin(3 * angle), 1.5 * np.sin(angle)]
        out[i] = T
    return out


def _drift(rng: np.random.Generator, truth: np.ndarray) -> np.ndarray:
    """The truth's relative poses with a random walk of tracking error composed in."""
    from cpslam.common.geometry import compose, invert, se3_exp

    out = [truth[0].copy()]
    for i in range(1, len(truth)):
        rel = compose(invert(truth[i - 1]), truth[i])
        noise = np.concatenate([rng.normal(0, 1e-3, 3), rng.normal(0, np.radians(0.05), 3)])
        out.append(compose(out[-1], compose(rel, se3_exp(noise))))
    return np.stack(out)


def _loops(rng: np.random.Generator, truth: list[np.ndarray], every: int) -> list[tuple]:
    from cpslam.common.geometry import compose, invert, se3_exp

    n_agents, n_kf = len(truth), len(truth[0])
    out = []
    for a in range(n_agents):
        for i in range(every // 2, n_kf, every):
            j = (i + n_kf // 2) % n_kf
            for b, jj in (((a + 1) % n_agents, i), (a, j)):
                if (b, jj) == (a, i):
                    continue
                T = compose(invert(truth[a][i]), truth[b][jj])
                if rng.random() < 0.05:  # a false loop
                    T = compose(T, se3_exp(np.array([0.5, 0.0, 0.0, 0.0, 0.0, 0.0])))
                noise = np.concatenate([rng.normal(0, 5e-3, 3), rng.normal(0, np.radians(0.1), 3)])
                out.append((a, i, b, jj, compose(T, se3_exp(noise))))
    return out


def _trajectory(T_world_kf: np.ndarray):
    from cpslam.server.pose_graph import AgentTrajectory

    k = len(T_world_kf)
    ids = np.arange(k)
    return AgentTrajectory(kf_ids=ids, kf_frame_indices=10 * ids, T_world_kf=T_world_kf,
                           frame_indices=np.zeros(0, np.int64), frame_kf_ids=np.zeros(0, np.int64),
                           T_kf_frame=np.zeros((0, 4, 4)))


def _rmse(truth: list[np.ndarray], poses: dict) -> float:
    """Keyframe translation RMSE (m), each agent's track aligned to the truth at its first
    keyframe: the drift along each track, which the loops are there to take out."""
    from cpslam.common.geometry import compose, invert

    err = []
    for a, T in enumerate(truth):
        T_fix = compose(T[0], invert(poses[(f"a{a}", 0)]))
        err += [np.linalg.norm(compose(T_fix, poses[(f"a{a}", i)])[:3, 3] - T[i, :3, 3])
                for i in range(len(T))]
    return float(np.sqrt(np.mean(np.square(err))))


if __name__ == "__main__":
    main()

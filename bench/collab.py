"""Collaboration quality: merges, loop edges and the pose graph, as a table and JSON.

    python bench/collab.py                      # apartment, 2 agents x 300 frames, cpu preset
    python bench/collab.py --frames 150 --skip-loop --preset tiny   # a quick look
    python bench/collab.py --real --skip-collab --skip-loop        # the 7-Scenes frames only
    python bench/collab.py --scene-seeds 0 1 2                      # several apartments

Every run also reports its loop edges against the ground truth (read after the run): for
each accepted loop of the final pose graph its translation and rotation error, its sigma
(from the edge's information), chi2 of the ground-truth residual whitened by that
information, whether the pose graph kept it (its chi2 after optimisation within the 95 %
bound), and for a loop within one agent the error of the odometry over the same span.

`--real`: ../shared/data/7scenes-kitchen-0-299 as two agents (frames 0-149 and 150-299: the
second starts where the first ends, in a frame of its own) and as one agent with loops.

Two-agent part: `cpslam dataset synth --scene apartment --agents 2 --frames N` (320x240,
cached under runs/bench-data/), `cpslam run` with the preset; reports whether and when the
agents merged, the joint se3 ATE of both global trajectories (one alignment for both), each
agent's origin-aligned ATE (the paper's), the same without any pose-graph correction (odometry
chained in the group frame by the merge alignment), and the false-loop test: the final pose
graph gets false loop edges (random keyframe pairs, neither loop pairs nor neighbours, with
the measured relative pose of a true loop), 20 % of all loop edges, straight into the graph
without verification; optimised again from the odometry; the ATE change is reported.

Single-agent part: `room --loop` sequence, `cpslam run` with one agent: ATE with loop closure
and pose graph versus the odometry alone.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def _data(scene: str, agents: int, frames: int, loop: bool, seed: int) -> list[Path]:
    from cpslam.demo import scene_data

    return scene_data(ROOT / "runs" / "bench-data", scene, agents, frames, 320, 240, seed,
                      show_progress=False, loop=loop)


def _run(paths: list[Path], preset: str, sets: list[str], out: Path, seed: int):
    from cpslam.agent.standalone import open_for_config
    from cpslam.common.config import load_config
    from cpslam.run import run_collab

    cfg = load_config(preset, overrides=[*sets, f"run.seed={seed}"], env={})
    seqs = [open_for_config(cfg, p) for p in paths]
    return run_collab(cfg, seqs, out, "cpu", show_progress=False), seqs


def loop_edges(result, seqs) -> dict:
    """Each loop edge of the final pose graph against the ground truth (see the docstring)."""
    from cpslam.common.eval import reference_jumps
    from cpslam.common.geometry import invert, se3_log
    from cpslam.server.pose_graph import CHI2_6DOF_95

    graph = result.final.pose_graph
    if graph is None:
        return {"edges": []}
    gt = {}
    for aid, seq in zip(result.agent_ids, seqs, strict=True):
        poses = seq.gt_poses()
        piece = np.searchsorted(reference_jumps(poses), np.arange(len(poses)), side="left")
        gt[aid] = {int(i): (T, int(k)) for i, T, k in zip(seq.indices, poses, piece,
                                                          strict=True)}
    kf_frames = {aid: dict(zip(t.kf_ids.tolist(), t.kf_frame_indices.tolist(), strict=True))
                 for aid, t in graph._trajectories.items()}  # noqa: SLF001 - bench only
    records = {lp["loop_id"]: lp for lp in result.final.metrics["loops"].get("list", [])}
    names = graph._names  # noqa: SLF001
    rows = []
    for e in graph._edges:  # noqa: SLF001
        if e.loop_id is None:
            continue
        (a, _, ka), (b, _, kb) = names[e.key_a], names[e.key_b]
        (Ta, pa), (Tb, pb) = gt[a][kf_frames[a][ka]], gt[b][kf_frames[b][kb]]
        if a == b and pa != pb:
            continue  # the ground truth jumps between the two: no truth to compare with
        err = se3_log(invert(invert(Ta) @ Tb) @ e.T_a_b)
        cov = np.linalg.inv(e.information)
        row = {"loop": str(e.loop_id), "agents": [a, b], "keyframes": [int(ka), int(kb)],
               "trans_cm": round(100 * float(np.linalg.norm(err[:3])), 3),
               "rot_deg": round(float(np.degrees(np.linalg.norm(err[3:]))), 3),
               "sigma_t_cm": round(100 * float(np.sqrt(np.trace(cov[:3, :3]) / 3)), 3),
               "chi2_gt": round(float(err @ e.information @ err), 3),
               "kept": not records.get(e.loop_id, {}).get("outlier", False)}
        odo = result.odometry.get(a)
        if a == b and odo is not None:
            stamps = dict(zip(np.round(odo[0], 6).tolist(), range(len(odo[0]))))
            ia, ib = (stamps.get(round(float(_stamp(seqs, result, a, f)), 6))
                      for f in (kf_frames[a][ka], kf_frames[a][kb]))
            if ia is not None and ib is not None:
                odo_err = se3_log(invert(invert(Ta) @ Tb) @ (invert(odo[1][ia]) @ odo[1][ib]))
                row["odometry_trans_cm"] = round(100 * float(np.linalg.norm(odo_err[:3])), 3)
        rows.append(row)
    out = {"edges": rows, "chi2_95": CHI2_6DOF_95}
    if rows:
        t = np.array([r["trans_cm"] for r in rows])
        out.update(trans_cm_median=round(float(np.median(t)), 3),
                   trans_cm_p90=round(float(np.percentile(t, 90)), 3),
                   trans_cm_max=round(float(t.max()), 3),
                   rot_deg_median=round(float(np.median([r["rot_deg"] for r in rows])), 3),
                   chi2_gt_median=round(float(np.median([r["chi2_gt"] for r in rows])), 3),
                   kept=sum(r["kept"] for r in rows))
        odo = [r["odometry_trans_cm"] for r in rows if "odometry_trans_cm" in r]
        if odo:
            out["odometry_same_span_trans_cm_median"] = round(float(np.median(odo)), 3)
    return out


def _stamp(seqs, result, agent: str, frame_index: int) -> float:
    seq = seqs[result.agent_ids.index(agent)]
    return float(seq.timestamps[int(np.searchsorted(seq.indices, frame_index))])


def _false_loops(result, seqs, fraction: float, seed: int) -> dict:
    """Inject false loop edges into the final pose graph, optimise again from the odometry
    (not from the already corrected poses), joint ATE again."""
    from cpslam.common.eval import joint_ate

    graph = result.final.pose_graph
    if graph is None:
        return {}
    rng = np.random.default_rng(seed)
    true = [e for e in graph._edges if e.loop_id is not None]  # noqa: SLF001 - bench only
    n_false = max(1, round(fraction * len(true) / (1 - fraction)))
    nodes = _kf_nodes(graph)
    taken = {(e.key_a, e.key_b) for e in true}
    graph.reset_estimate()
    for i in range(n_false):
        # A plausible but wrong measurement: the relative pose of a true loop, claimed
        # between two keyframes that are not a loop pair and not neighbours.
        while True:
            (a, ka), (b, kb) = (nodes[j] for j in rng.choice(len(nodes), 2, replace=False))
            keys = (graph._key(a, "kf", ka), graph._key(b, "kf", kb))  # noqa: SLF001
            if keys not in taken and (a != b or abs(ka - kb) > 1):
                break
        taken.add(keys)
        T = true[rng.integers(len(true))].T_a_b
        graph.add_loop(a, ka, b, kb, T, sigma_t=0.05, sigma_r=0.05, loop_id=f"false{i}")
    opt = graph.optimize()
    gts = {aid: (np.asarray(s.timestamps), s.gt_poses()) for aid, s in zip(result.agent_ids,
                                                                           seqs, strict=True)}
    pairs = []
    for a in result.final.agents:
        traj = graph._trajectories.get(a.agent_id)  # noqa: SLF001 - bench only
        if traj is None:
            continue
        poses = graph.corrected_frames(opt, a.agent_id)
        stamps = _stamps_of(a, traj.frame_indices)
        pairs.append((gts[a.agent_id], (stamps, poses)))
    if not pairs:
        return {}
    ate = joint_ate(pairs, align="se3").overall.rmse
    flagged = [lp for lp in opt.outlier_loops if str(lp).startswith("false")]
    return {"false_loops": n_false, "true_loops": len(true), "joint_se3_rmse_m": float(ate),
            "outliers_flagged": len(opt.outlier_loops), "false_flagged": len(flagged)}


def _kf_nodes(graph) -> list[tuple[str, int]]:
    return [(agent, int(node)) for agent, kind, node in graph._names  # noqa: SLF001
            if kind == "kf"]


def _stamps_of(agent_result, frame_indices) -> np.ndarray:
    """Stamps of the graph's frames (the exported trajectory lists every frame in order)."""
    stamps = agent_result.stamps
    if len(stamps) != len(frame_indices):
        raise ValueError("frame count of the graph and the trajectory differ")
    return stamps


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--loop-frames", type=int, default=300)
    ap.add_argument("--preset", default="cpu")
    ap.add_argument("--set", action="append", default=[], dest="sets")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--false-fraction", type=float, default=0.2)
    ap.add_argument("--skip-loop", action="store_true")
    ap.add_argument("--skip-collab", action="store_true")
    ap.add_argument("--out", type=Path, default=ROOT / "runs" / "bench-collab")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    import torch

    torch.set_num_threads(1)
    report: dict = {"preset": args.preset, "sets": args.sets, "seed": args.seed}
    if not args.skip_collab:
        t0 = time.perf_counter()
        paths = _data("apartment", 2, args.frames, False, args.seed)
        result, seqs = _run(paths, args.preset, args.sets, args.out / "apartment", args.seed)
        ev = result.evaluation
        merges = result.final.metrics.get("merges", [])
        report["apartment"] = {
            "merged": bool(merges), "merge_time_s": [m["time"] for m in merges],
            "merge_frame": [round(m["time"] * 30) for m in merges], **ev,
            "loops": {k: v for k, v in result.final.metrics["loops"].items() if k != "list"},
            "false_loop_test": _false_loops(result, seqs, args.false_fraction, args.seed),
            "wall_s": time.perf_counter() - t0,
        }
    if not args.skip_loop:
        t0 = time.perf_counter()
        paths = _data("room", 1, args.loop_frames, True, args.seed)
        result, _ = _run(paths, args.preset, args.sets, args.out / "room-loop", args.seed)
        report["room_loop"] = {**result.evaluation, "wall_s": time.perf_counter() - t0,
                               "loops": {k: v for k, v in result.final.metrics["loops"].items()
                                         if k != "list"}}
    _print(report)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "collab.json").write_text(json.dumps(report, indent=2, default=float))


def _print(report: dict) -> None:
    def cm(v):
        return "-" if v is None else f"{100 * v:.2f} cm"

    rows = []
    apt = report.get("apartment")
    if apt:
        fl = apt.get("false_loop_test", {})
        base = apt.get("global_joint_se3_rmse_m")
        change = (abs(fl["joint_se3_rmse_m"] - base) / base * 100) if fl and base else None
        rows += [
            ("apartment merged (frame)", f"{apt['merged']} {apt['merge_frame']}"),
            ("joint se3 ATE, global (bar <= 2 cm)", cm(base)),
            ("joint se3 ATE, no pose graph", cm(apt.get("odometry_joint_se3_rmse_m"))),
            ("origin ATE per agent", ", ".join(f"{a}: {cm(v)}" for a, v in
                                               apt.get("global_origin_rmse_m", {}).items())),
            ("origin ATE per agent, no pose graph", ", ".join(
                f"{a}: {cm(v)}" for a, v in apt.get("odometry_origin_rmse_m", {}).items())),
            ("false loops injected / true", f"{fl.get('false_loops')} / {fl.get('true_loops')}"),
            ("false loops flagged as outliers", f"{fl.get('false_flagged')} of "
                                                f"{fl.get('false_loops')}"),
            ("joint ATE with false loops (change, bar < 10 %)",
             f"{cm(fl.get('joint_se3_rmse_m'))} ({'-' if change is None else f'{change:.1f} %'})"),
            ("wall time", f"{apt['wall_s']:.0f} s"),
        ]
    loop = report.get("room_loop")
    if loop:
        rows += [
            ("room loop: ATE with loop closure + PGO", cm(loop.get("global_joint_se3_rmse_m"))),
            ("room loop: ATE odometry alone", cm(loop.get("odometry_joint_se3_rmse_m"))),
            ("room loop: loops accepted / found",
             f"{loop['loops'].get('accepted')} / {loop['loops'].get('found')}"),
            ("room loop wall time", f"{loop['wall_s']:.0f} s"),
        ]
    width = max(len(r[0]) for r in rows) if rows else 0
    for name, value in rows:
        sys.stdout.write(f"{name:<{width}}  {value}\n")


if __name__ == "__main__":
    main()

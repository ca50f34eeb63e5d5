"""Collaboration quality: merges, loop edges and the pose graph, as a table and JSON.

    python bench/collab.py                      # apartment, 2 agents x 300 frames, cpu preset
    python bench/collab.py --frames 150 --skip-loop --preset tiny   # a quick look
    python bench/collab.py --real --skip-collab --skip-loop        # the 7-Scenes frames only
    python bench/collab.py --scene-seeds 0 1 2                      # several apartments
    python bench/collab.py --step 3 --skip-loop --set loop.image_scale=0.5   # demo rate

Every run also reports its loop edges against the ground truth (read after the run): for
each accepted loop of the final pose graph its translation and rotation error, its sigma
(from the edge's information), chi2 of the ground-truth residual whitened by that
information, whether the pose graph kept it (its chi2 after optimisation within the 95 %
bound), and for a loop within one agent the error of the odometry over the same span.

`--real`: ../shared/data/7scenes-kitchen-0-299 as two agents (frames 0-149 and 150-299: the
second starts where the first ends, in a frame of its own) and as one agent with loops.

Two-agent part: `cpslam dataset synth --scene apartment --agents 2 --num-frames N` (320x240,
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
from odometry_runs import KITCHEN

ROOT = Path(__file__).resolve().parents[1]


def _data(scene: str, agents: int, frames: int, loop: bool, seed: int) -> list[Path]:
    from cpslam.demo import scene_data

    return scene_data(ROOT / "runs" / "bench-data", scene, agents, frames, 320, 240, seed,
                      show_progress=False, loop=loop)


def _run(paths: list[Path], preset: str, sets: list[str], out: Path, seed: int,
         frames: str | None = None):
    from cpslam.agent.standalone import open_for_config
    from cpslam.common.config import load_config
    from cpslam.run import run_collab

    cfg = load_config(preset, overrides=[*sets, f"run.seed={seed}"], env={})
    seqs = [open_for_config(cfg, p, frames=frames) for p in paths]
    return run_collab(cfg, seqs, out, "cpu", show_progress=False), seqs


def loop_edges(result, seqs, same_source: bool = False) -> dict:
    """Each loop edge of the final pose graph against the ground truth (see the docstring).

    same_source: the agents' sequences are slices of one recording, so the ground truth's
    jumps are found on their union by frame index; an edge whose two keyframes lie on either
    side of a jump has no truth to compare with and is only counted (`no_truth`)."""
    from cpslam.common.geometry import invert, se3_log
    from cpslam.server.pose_graph import CHI2_6DOF_95
    from cpslam.tools.eval import reference_jumps

    graph = result.final.pose_graph
    if graph is None:
        return {"edges": []}
    gt = {}
    union = {}
    if same_source:
        for seq in seqs:
            union.update(zip(np.asarray(seq.indices).tolist(), seq.gt_poses(), strict=True))
        order = sorted(union)
        jumps = reference_jumps(np.stack([union[i] for i in order]))
        union = dict(zip(order, np.searchsorted(jumps, np.arange(len(order)), side="left")
                         .tolist(), strict=True))
    for aid, seq in zip(result.agent_ids, seqs, strict=True):
        poses = seq.gt_poses()
        piece = np.searchsorted(reference_jumps(poses), np.arange(len(poses)), side="left")
        if same_source:
            piece = [union[int(i)] for i in seq.indices]
        gt[aid] = {int(i): (T, int(k)) for i, T, k in zip(seq.indices, poses, piece,
                                                          strict=True)}
    kf_frames = {aid: dict(zip(t.kf_ids.tolist(), t.kf_frame_indices.tolist(), strict=True))
                 for aid, t in graph._trajectories.items()}  # noqa: SLF001 - bench only
    records = {lp["loop_id"]: lp for lp in result.final.metrics["loops"].get("list", [])}
    names = graph._names  # noqa: SLF001
    rows = []
    no_truth = 0
    for e in graph._edges:  # noqa: SLF001
        if e.loop_id is None:
            continue
        (a, _, ka), (b, _, kb) = names[e.key_a], names[e.key_b]
        (Ta, pa), (Tb, pb) = gt[a][kf_frames[a][ka]], gt[b][kf_frames[b][kb]]
        if pa != pb:  # the ground truth jumps between the two: no truth to compare with
            no_truth += 1
            continue
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
            stamps = {s: i for i, s in enumerate(np.round(odo[0], 6).tolist())}
            ia, ib = (stamps.get(round(float(_stamp(seqs, result, a, f)), 6))
                      for f in (kf_frames[a][ka], kf_frames[a][kb]))
            if ia is not None and ib is not None:
                odo_err = se3_log(invert(invert(Ta) @ Tb) @ (invert(odo[1][ia]) @ odo[1][ib]))
                row["odometry_trans_cm"] = round(100 * float(np.linalg.norm(odo_err[:3])), 3)
        rows.append(row)
    out = {"edges": rows, "no_truth": no_truth, "chi2_95": CHI2_6DOF_95}
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
    from cpslam.tools.eval import joint_ate

    graph = result.final.pose_graph
    if graph is None:
        return {}
    rng = np.random.default_rng(seed)
    true = [e for e in graph._edges if e.loop_id is not None]  # noqa: SLF001 - bench only
    if not true:
        return {"skipped": "no loop edges to copy"}
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


def _collab_report(result, seqs, false_fraction: float, seed: int, wall_s: float,
                   same_source: bool = False) -> dict:
    merges = result.final.metrics.get("merges", [])
    return {"merged": bool(merges), "merge_time_s": [m["time"] for m in merges],
            **result.evaluation,
            "loops": {k: v for k, v in result.final.metrics["loops"].items() if k != "list"},
            "loop_edges": loop_edges(result, seqs, same_source),
            "false_loop_test": _false_loops(result, seqs, false_fraction, seed),
            "wall_s": round(wall_s, 1)}


def _run_real(args, frames: list[str], out: Path) -> dict:
    from cpslam.agent.standalone import open_for_config
    from cpslam.common.config import load_config
    from cpslam.run import run_collab

    cfg = load_config(args.preset, overrides=[*args.sets, f"run.seed={args.seed}"], env={})
    seqs = [open_for_config(cfg, KITCHEN, frames=f) for f in frames]
    t0 = time.perf_counter()
    result = run_collab(cfg, seqs, out, "cpu", show_progress=False)
    return {"frames": frames, **_collab_report(result, seqs, args.false_fraction, args.seed,
                                               time.perf_counter() - t0, same_source=True)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=300, help="frames per synthetic agent")
    ap.add_argument("--step", type=int, default=1,
                    help="process every STEP-th synthetic frame (3: the demo's rate)")
    ap.add_argument("--loop-frames", type=int, default=300, help="frames of the room loop")
    ap.add_argument("--preset", default="cpu")
    ap.add_argument("--set", action="append", default=[], dest="sets",
                    help="config override a.b=value (repeat)")
    ap.add_argument("--seed", type=int, default=0, help="run.seed")
    ap.add_argument("--scene-seeds", type=int, nargs="+", default=[0],
                    help="synthetic apartment scene seeds")
    ap.add_argument("--false-fraction", type=float, default=0.2)
    ap.add_argument("--skip-loop", action="store_true", help="leave out the room loop")
    ap.add_argument("--skip-collab", action="store_true",
                    help="leave out the synthetic apartments")
    ap.add_argument("--real", action="store_true", help="also run the 7-Scenes frames")
    ap.add_argument("--real-split", default="0:150,150:300",
                    help="frame slices of the real agents, comma-separated")
    ap.add_argument("--out", type=Path, default=ROOT / "runs" / "bench-collab")
    ap.add_argument("--json", type=Path, default=None, help="also write the JSON here")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    import torch
    from benchinfo import bench_header

    torch.set_num_threads(1)
    report: dict = {**bench_header("collab", sys.argv), "preset": args.preset,
                    "sets": args.sets, "seed": args.seed}
    if not args.skip_collab:
        report["apartment"] = {}
        for scene_seed in args.scene_seeds:
            t0 = time.perf_counter()
            paths = _data("apartment", 2, args.frames, False, scene_seed)
            result, seqs = _run(paths, args.preset, args.sets,
                                args.out / f"apartment-{scene_seed}", args.seed,
                                f"0:{args.frames}:{args.step}")
            report["apartment"][str(scene_seed)] = _collab_report(
                result, seqs, args.false_fraction, args.seed, time.perf_counter() - t0)
    if not args.skip_loop:
        t0 = time.perf_counter()
        paths = _data("room", 1, args.loop_frames, True, args.seed)
        result, seqs = _run(paths, args.preset, args.sets, args.out / "room-loop", args.seed,
                            f"0:{args.loop_frames}:{args.step}")
        report["room_loop"] = {**result.evaluation, "wall_s": round(time.perf_counter() - t0, 1),
                               "loop_edges": loop_edges(result, seqs),
                               "loops": {k: v for k, v in result.final.metrics["loops"].items()
                                         if k != "list"}}
    if args.real:
        split = args.real_split.split(",")
        report["real_split"] = _run_real(args, split, args.out / "real-split")
        whole = f"{split[0].split(':')[0]}:{split[-1].split(':')[1]}"
        report["real_single"] = _run_real(args, [whole], args.out / "real-single")
    _print(report)
    args.out.mkdir(parents=True, exist_ok=True)
    text = json.dumps(report, indent=2, default=float)
    (args.out / "collab.json").write_text(text)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(text)


def _cm(v) -> str:
    return "-" if v is None else f"{100 * v:.2f} cm"


def _section_rows(name: str, sec: dict) -> list[tuple[str, str]]:
    fl = sec.get("false_loop_test") or {}
    base = sec.get("global_joint_se3_rmse_m")
    odo = sec.get("odometry_joint_se3_rmse_m")
    edges = sec.get("loop_edges") or {}
    loops = sec.get("loops") or {}
    rows = [(f"{name}: joint se3 ATE, pose graph / odometry only",
             f"{_cm(base)} / {_cm(odo)}" + (f" ({base / odo:.2f}x)" if base and odo else "")),
            (f"{name}: origin ATE per agent, pose graph", ", ".join(
                f"{a}: {_cm(v)}" for a, v in sec.get("global_origin_rmse_m", {}).items())),
            (f"{name}: origin ATE per agent, odometry only", ", ".join(
                f"{a}: {_cm(v)}" for a, v in sec.get("odometry_origin_rmse_m", {}).items())),
            (f"{name}: loops accepted / found",
             f"{loops.get('accepted')} / {loops.get('found')}")]
    if "merged" in sec:
        rows.insert(0, (f"{name}: merged (time s)", f"{sec['merged']} {sec['merge_time_s']}"))
    if edges.get("edges"):
        rows.append((f"{name}: loop edges vs GT, median / p90 / max",
                     f"{edges['trans_cm_median']:.2f} / {edges['trans_cm_p90']:.2f} / "
                     f"{edges['trans_cm_max']:.2f} cm, {edges['rot_deg_median']:.2f} deg median, "
                     f"chi2 median {edges['chi2_gt_median']:.1f}, kept {edges['kept']} of "
                     f"{len(edges['edges'])}"))
    if fl.get("skipped"):
        rows.append((f"{name}: false loops", f"skipped: {fl['skipped']}"))
    elif fl:
        change = abs(fl["joint_se3_rmse_m"] - base) / base * 100 if base else None
        rows.append((f"{name}: false loops flagged / injected, ATE with them",
                     f"{fl.get('false_flagged')} / {fl.get('false_loops')}, "
                     f"{_cm(fl.get('joint_se3_rmse_m'))}"
                     + ("" if change is None else f" ({change:.1f} % change)")))
    rows.append((f"{name}: wall time", f"{sec.get('wall_s', 0):.0f} s"))
    return rows


def _print(report: dict) -> None:
    rows = []
    for seed, sec in report.get("apartment", {}).items():
        rows += _section_rows(f"apartment {seed}", sec)
    for key in ("room_loop", "real_split", "real_single"):
        if key in report:
            rows += _section_rows(key.replace("_", " "), report[key])
    width = max(len(r[0]) for r in rows) if rows else 0
    for name, value in rows:
        sys.stdout.write(f"{name:<{width}}  {value}\n")


if __name__ == "__main__":
    main()

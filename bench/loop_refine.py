"""Loop relative poses, coarse (geometric registration) versus refined (tracking against the
other sub-map), against ground truth; prints a table and writes JSON.

    python bench/loop_refine.py                              # apartment, 2 agents x 300 frames
    python bench/loop_refine.py --scene room --agents 1 --loop   # intra-agent loops
    python bench/loop_refine.py --first 100 --preset tiny    # a quick look

The sequences are rendered once (`cpslam dataset synth`, 320x240, cached under
runs/bench-data/), then `cpslam run` runs them with the preset and ``loop.refine`` on. The
refiner records the coarse pose it started from and the refined one for every loop it saw
(``metrics.json`` loops, ``refinement``), so one run gives both estimates for the same pairs.
Ground truth is read here only: keyframe k of an agent is processed frame k x keyframes.every.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def _data(scene: str, agents: int, frames: int, loop: bool, seed: int) -> list[Path]:
    from cpslam.demo import scene_data

    return scene_data(ROOT / "runs" / "bench-data", scene, agents, frames, 320, 240, seed,
                      show_progress=False, loop=loop)


def _errors(T: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """Translation (m) and rotation (degrees) of T relative to T_true."""
    E = np.linalg.inv(T_true) @ T
    cos = np.clip((np.trace(E[:3, :3]) - 1) / 2, -1.0, 1.0)
    return float(np.linalg.norm(E[:3, 3])), float(np.degrees(np.arccos(cos)))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", default="apartment", choices=["apartment", "room"])
    ap.add_argument("--agents", type=int, default=2)
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--loop", action="store_true", help="closed trajectories")
    ap.add_argument("--first", type=int, default=None, help="process only the first N frames")
    ap.add_argument("--preset", default="cpu")
    ap.add_argument("--set", dest="sets", action="append", default=[])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=ROOT / "runs" / "bench-loop-refine")
    ap.add_argument("--analyse-only", action="store_true",
                    help="read the metrics.json of an earlier run instead of running")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)

    import torch

    from cpslam.agent.standalone import open_for_config
    from cpslam.common.config import load_config
    from cpslam.run import run_collab

    paths = _data(args.scene, args.agents, args.frames, args.loop, args.seed)
    cfg = load_config(args.preset, overrides=[*args.sets, "loop.refine=true",
                                              f"run.seed={args.seed}"], env={})
    torch.set_num_threads(cfg.run.num_threads or 1)  # as `cpslam run` does
    seqs = [open_for_config(cfg, p, frames=None if args.first is None else f"0:{args.first}")
            for p in paths]
    name = f"{args.scene}-{args.agents}x{args.first or args.frames}{'-loop' if args.loop else ''}"
    run_dir = args.out / name
    if args.analyse_only:
        metrics, wall_s, evaluation = json.loads((run_dir / "metrics.json").read_text()), None, {}
    else:
        result = run_collab(cfg, seqs, run_dir, "cpu", show_progress=False)
        metrics, wall_s, evaluation = result.final.metrics, result.wall_s, result.evaluation
    gts = {str(i): seq.gt_poses() for i, seq in enumerate(seqs)}
    rows = _rows(metrics["loops"]["list"], gts, cfg.keyframes.every)
    report = {"scene": name, "preset": args.preset, "sets": args.sets, "seed": args.seed,
              "torch_threads": torch.get_num_threads(), "wall_s": wall_s, "loops": rows,
              "evaluation": evaluation}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / f"{name}.json").write_text(json.dumps(report, indent=2, default=float))
    _print(rows)


def _rows(loops: list[dict], gts: dict[str, np.ndarray], every: int) -> list[dict]:
    """Errors of the coarse, refined and used pose of every loop the refiner saw."""
    rows = []
    for lp in loops:
        ref = lp.get("refinement")
        if not ref:
            continue
        T_true = np.linalg.inv(gts[lp["agent_a"]][lp["kf_a"] * every]) @ \
            gts[lp["agent_b"]][lp["kf_b"] * every]
        coarse = _errors(np.asarray(ref["T_coarse"]), T_true)
        refined = _errors(np.asarray(ref["T_refined"]), T_true)
        rows.append({
            "pair": f"{lp['agent_a']}/{lp['kf_a']}-{lp['agent_b']}/{lp['kf_b']}",
            "inter_agent": lp["agent_a"] != lp["agent_b"], "accepted": lp["accepted"],
            "used": ref["used"], "note": ref["note"], "coarse": coarse, "refined": refined,
            "final": refined if ref["used"] else coarse, "refine_s": ref["seconds"],
            "loop_s": lp["seconds"], "loss_coarse": ref["loss_coarse"],
            "loss_refined": ref["loss_refined"], "points": ref["points"]})
    return rows


def _print(rows: list[dict]) -> None:
    out = sys.stdout
    out.write("| pair | coarse | refined | kept | refine s | loop s |\n|---|---|---|---|---|---|\n")
    for r in rows:
        (ct, cr), (rt, rr) = r["coarse"], r["refined"]
        out.write(f"| {r['pair']} | {100 * ct:.2f} cm {cr:.2f}° | {100 * rt:.2f} cm {rr:.2f}° | "
                  f"{'refined' if r['used'] else 'coarse'} | {r['refine_s']:.1f} | "
                  f"{r['loop_s']:.1f} |\n")
    if rows:
        for key in ("coarse", "refined", "final"):
            t = np.array([r[key][0] for r in rows]) * 100
            a = np.array([r[key][1] for r in rows])
            out.write(f"{key}: translation median {np.median(t):.2f} cm max {t.max():.2f} cm; "
                      f"rotation median {np.median(a):.2f}° max {a.max():.2f}°\n")
        s = np.array([r["refine_s"] for r in rows])
        out.write(f"refinement: median {np.median(s):.1f} s, max {s.max():.1f} s per loop; "
                  f"{sum(r['used'] for r in rows)} of {len(rows)} refined poses used\n")


if __name__ == "__main__":
    main()

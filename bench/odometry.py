"""Single-agent odometry across scenes, thread counts and CPU code paths: accuracy, failures
and speed, printed as tables and written as JSON.

Runs the agent's front end (`Odometry`: tracking, mapping, keyframes; `--loops off`) and the
standalone agent with loop closure (`cpslam-agent --standalone`: the front end with the
server's back end in one process, closing the agent's own loops; `--loops on`), by default
both, side by side per sequence, on

- synthetic scenes: `--scenes N` scenes with seeds `--scene-base`, `--scene-base` + 1, ...:
  room loops and apartment walks in turn, every other pair with Kinect-like depth noise
  (300 frames at 320x240, generated once under runs/bench-data/); origin- and se3-aligned
  ATE, next to Open3D's frame-to-frame RGB-D odometry on the same frames;
- real frames: ../shared/data/7scenes-kitchen-0-299 (or `--real PATH`; when present) at the
  preset's camera.downscale; se3 ATE and the ATE over the pieces between the ground truth's
  one-frame jumps (it jumps 36 mm between frames 121 and 122, a step the camera did not make),
  next to Open3D at that resolution and at 640x480, with the ratio to the better Open3D;
  and, since that ground truth is itself an estimate (KinectFusion), each source's own error
  (ground truth, Open3D at 640x480, each run) estimated from their pairwise differences
  alone (`cpslam.tools.eval.hat`), in the summary's `ground_truth_error`.

`--synth DIR` takes one synthetic sequence rendered beforehand (`cpslam.tools.synth`, which
renders with Open3D) instead of `--scenes`. Open3D's comparison is left out when open3d is not
installed (the JSON says so).

Every sequence runs once per `--threads` count (torch threads), `--capability` (`default`, or
`avx2`: ATEN_CPU_CAPABILITY=avx2 forces torch's AVX2 kernels on an AVX-512 machine) and
`--seeds` value (run.seed: pixel draws and ray jitter), each run in its own process, as many
at once as the cores allow (`--jobs`). A run "lost track" when a frame's position error,
after the alignment, exceeds 10 cm; the recovery's events (frames found suspect, recovered,
lost: `cpslam.agent.recovery`) are counted per run. With loop closure the ATE is the final
pose graph's trajectory, and the loops found and accepted are counted; the JSON's runs say
`loops` "off" or "on", a sequence's summary is over its runs without loop closure with
`with_loops` (mean, worst, loops) beside it, and `synthetic_with_loops` sums those runs.

Timings are wall-clock on this machine (runs side by side share it; on CUDA synchronised per
frame). The paper's figures on an RTX 3090 (tracking 0.30 s per frame, mapping 10.1 s per
mapping step) are printed beside ours for the `paper` preset on a GPU (`--device cuda`), with
the peak GPU memory. `--max-seconds S` stops each run after the frame that passes S seconds
(the frames done are reported; bench/gpu_check.sh sizes its runs so).

Usage: python bench/odometry.py [--preset cpu] [--scenes 8] [--scene-base 0] [--threads 1 2]
       [--capability default avx2] [--seeds 0] [--frames 300] [--only synth|real]
       [--loops off|on|both] [--set a.b=v ...] [--jobs N] [--device cpu] [--real PATH]
       [--synth DIR] [--max-seconds S] [--json PATH]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchinfo import bench_header  # noqa: E402
from odometry_runs import (  # noqa: E402
    KITCHEN,
    PAPER,
    agreement,
    ensure_scene,
    open3d_available,
    open3d_odometry,
    run_job,
    scene_specs,
)

LOST_CM = 10.0
"""A frame further than this from the ground truth (after alignment) means lost track."""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="cpu")
    parser.add_argument("--frames", type=int, default=300, help="frames of each sequence")
    parser.add_argument("--scenes", type=int, default=8, help="synthetic scenes")
    parser.add_argument("--scene-base", type=int, default=0, help="seed of the first scene")
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--capability", nargs="+", default=["default"],
                        choices=("default", "avx2"))
    parser.add_argument("--seeds", type=int, nargs="+", default=[0], help="run.seed values")
    parser.add_argument("--only", choices=("synth", "real"), default=None)
    parser.add_argument("--loops", choices=("off", "on", "both"), default="both",
                        help="without loop closure (the odometry), with it (the standalone "
                        "agent's back end), or both side by side")
    parser.add_argument("--set", nargs="*", default=[], help="config overrides a.b=value")
    parser.add_argument("--jobs", type=int, default=0,
                        help="runs at once (0: the cores divided by the runs' threads)")
    parser.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N")
    parser.add_argument("--real", type=Path, default=KITCHEN,
                        help="7-Scenes frames folder for the real sequence")
    parser.add_argument("--synth", type=Path, default=None,
                        help="a rendered synthetic sequence (its agent_0 folder's parent) "
                             "instead of --scenes")
    parser.add_argument("--max-seconds", type=float, default=0.0,
                        help="stop each run after the frame that passes this (0: no limit)")
    parser.add_argument("--json", type=Path, default=None, help="also write the JSON here")
    parser.add_argument("--job", default=None, help=argparse.SUPPRESS)  # one run (internal)
    args = parser.parse_args()
    if args.job is not None:
        print(json.dumps(run_job(json.loads(args.job))))
        return
    report = bench_header("odometry", sys.argv)
    report.update(preset=args.preset, overrides=args.set, frames=args.frames,
                  device=args.device, max_seconds=args.max_seconds or None,
                  loops=args.loops, paper_rtx3090=PAPER)
    sequences: list[dict] = []
    if args.only in (None, "synth") and args.synth is not None:
        if not (args.synth / "agent_0").is_dir():
            parser.error(f"--synth {args.synth}: no agent_0 folder (render one with "
                         "cpslam dataset synth)")
        sequences.append({"name": args.synth.name, "kind": "synthetic",
                          "path": str((args.synth / "agent_0").resolve())})
    elif args.only in (None, "synth"):
        for spec in scene_specs(args.scenes, args.scene_base):
            spec["path"] = str(ensure_scene(spec, args.frames))
            sequences.append(spec)
    if args.only in (None, "real"):
        if args.real.is_dir():
            sequences.append({"name": "7scenes-kitchen", "kind": "real",
                              "path": str(args.real.resolve())})
        else:
            report["real_skipped"] = f"no data at {args.real}"
    jobs = [{"sequence": seq, "preset": args.preset, "overrides": args.set,
             "frames": args.frames, "device": args.device, "threads": threads,
             "capability": cap, "seed": seed, "max_seconds": args.max_seconds or None,
             "loops": loops}
            for threads in args.threads for cap in args.capability for seed in args.seeds
            for seq in sequences
            for loops in (("off", "on") if args.loops == "both" else (args.loops,))]
    report["runs"] = _run_all(jobs, args.jobs)
    if open3d_available():
        report["open3d"] = {seq["name"]: open3d_odometry(seq, args.frames) for seq in sequences}
    else:
        report["open3d"], report["open3d_skipped"] = {}, "open3d is not installed"
    report["summary"] = summarise(report["runs"], report["open3d"])
    full = {name: _full_size(sizes) for name, sizes in report["open3d"].items()}
    report["summary"]["ground_truth_error"] = agreement(sequences, report["runs"], full,
                                                        args.frames)
    for entry in [*report["runs"], *(v for o in report["open3d"].values() for v in o.values())]:
        entry.pop("poses", None)  # read by `agreement`; too long for the report
    print_tables(report)
    text = json.dumps(report, indent=2)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(text + "\n")
        print(f"wrote {args.json}")
    else:
        print(text)


def _run_all(jobs: list[dict], jobs_at_once: int) -> list[dict]:
    """Every job in its own process, grouped by thread count so that the cores are shared."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    results: list[dict] = []
    for threads in sorted({j["threads"] for j in jobs}):
        group = [j for j in jobs if j["threads"] == threads]
        width = jobs_at_once or max(1, (cores or 1) // threads)
        with ThreadPoolExecutor(width) as pool:
            results += list(pool.map(_subprocess, group))
    return results


def _subprocess(job: dict) -> dict:
    env = dict(os.environ)
    if job["capability"] != "default":
        env["ATEN_CPU_CAPABILITY"] = job["capability"]
    name = job["sequence"]["name"]
    print(f"  {name}: {job['threads']} thread(s), {job['capability']}, seed {job['seed']}, "
          f"loops {job['loops']}", file=sys.stderr, flush=True)
    done = subprocess.run([sys.executable, __file__, "--job", json.dumps(job)], env=env,
                          capture_output=True, text=True)
    key = {k: job[k] for k in ("threads", "capability", "seed", "loops")}
    if done.returncode != 0:
        return {"sequence": name, **key, "error": done.stderr.strip()[-2000:]}
    return {"sequence": name, "kind": job["sequence"]["kind"], **key,
            **json.loads(done.stdout.strip().splitlines()[-1])}


def summarise(runs: list[dict], open3d: dict) -> dict:
    """Per sequence and over all synthetic runs: mean and worst ATE, runs over the bars,
    lost runs and recovery events; for the real frames the ratio to the better Open3D. Runs
    without loop closure (no `loops` field: older reports) fill the fields; runs with it go
    to `with_loops` beside them, and to `synthetic_with_loops`."""
    out: dict = {"per_sequence": {}}
    for name in dict.fromkeys(r["sequence"] for r in runs):
        mine = [r for r in runs if r["sequence"] == name]
        ok = [r for r in mine if _measured(r) and _loops(r) == "off"]
        on = [r for r in mine if _measured(r) and _loops(r) == "on"]
        entry = _sequence_summary(ok, open3d.get(name, {})) if ok else {}
        if on:
            entry["with_loops"] = _loops_summary(on)
        if not ok and not on:
            entry = {"errors": len(mine)}
        out["per_sequence"][name] = entry
    good = [r for r in runs if r.get("kind") not in (None, "real") and _measured(r)]
    synth = [r for r in good if _loops(r) == "off"]
    if synth:
        values = [r["ate_origin_cm"] for r in synth]
        out["synthetic"] = {"runs": len(synth), "mean_origin_cm": round(float(np.mean(values)), 3),
                            "worst_origin_cm": round(float(np.max(values)), 3),
                            "runs_over_1cm": sum(v > 1.0 for v in values),
                            "lost_runs": sum(r["max_error_cm"] > LOST_CM for r in synth),
                            "events": _sum_events(synth)}
    synth_on = [r for r in good if _loops(r) == "on"]
    if synth_on:
        out["synthetic_with_loops"] = _loops_summary(synth_on)
    out["failed_runs"] = sum("error" in r for r in runs)
    return out


def _measured(run: dict) -> bool:
    """Whether a run has accuracy figures (not failed, not stopped before it could align)."""
    return "error" not in run and "accuracy_error" not in run


def _loops(run: dict) -> str:
    return run.get("loops", "off")


def _metric(runs: list[dict]) -> str:
    return "ate_origin_cm" if runs[0]["kind"] != "real" else "ate_se3_cm"


def _sequence_summary(ok: list[dict], o3d: dict) -> dict:
    key = _metric(ok)
    values = [r[key] for r in ok]
    entry = {"metric": key, "runs": len(ok), "mean": round(float(np.mean(values)), 3),
             "worst": round(float(np.max(values)), 3),
             "lost_runs": sum(r["max_error_cm"] > LOST_CM for r in ok),
             "events": _sum_events(ok),
             "s_per_frame": round(float(np.mean([r["s_per_frame"] for r in ok])), 3)}
    full = _full_size(o3d)
    if full and full.get("s_per_frame"):
        # The speed bar is Open3D's frame-to-frame odometry at the frames' own size, timed in
        # the same bench run on the same machine: the ratio depends on the CPU less than
        # seconds do.
        entry["s_per_frame_over_open3d_full"] = round(entry["s_per_frame"] / full["s_per_frame"], 3)
    if ok[0]["kind"] == "real" and o3d:
        best = min(o3d.values(), key=lambda v: v["ate_se3_cm"])
        entry["ratio_mean_over_best_open3d"] = round(entry["mean"] / best["ate_se3_cm"], 3)
        entry["ratio_worst_over_best_open3d"] = round(entry["worst"] / best["ate_se3_cm"], 3)
        pieces = [r["ate_se3_pieces_cm"] for r in ok]
        best_pieces = min(v["ate_se3_pieces_cm"] for v in o3d.values())
        entry["pieces_mean"] = round(float(np.mean(pieces)), 3)
        entry["ratio_pieces_mean_over_best_open3d"] = round(entry["pieces_mean"] / best_pieces, 3)
    return entry


def _full_size(o3d: dict) -> dict | None:
    """Open3D's entry at the largest resolution it ran (keys "WxH"), or None."""
    if not o3d:
        return None
    return o3d[max(o3d, key=lambda size: int(size.split("x")[0]) * int(size.split("x")[1]))]


def _loops_summary(on: list[dict]) -> dict:
    """Runs with loop closure: their ATE (each run's own metric), lost runs and loops."""
    values = [r[_metric([r])] for r in on]
    return {"metric": _metric(on), "runs": len(on), "mean": round(float(np.mean(values)), 3),
            "worst": round(float(np.max(values)), 3),
            "lost_runs": sum(r["max_error_cm"] > LOST_CM for r in on),
            "loops_found": int(sum(r.get("loops_found", 0) for r in on)),
            "loops_accepted": int(sum(r.get("loops_accepted", 0) for r in on)),
            "s_per_frame": round(float(np.mean([r["s_per_frame"] for r in on])), 3)}


def _sum_events(runs: list[dict]) -> dict:
    keys = ("suspect", "recovered", "lost")
    return {k: int(sum(r.get("events", {}).get(k, 0) for r in runs)) for k in keys}


def print_tables(report: dict) -> None:
    """Per run, per sequence and overall."""
    rows = [("sequence", "loops", "threads", "cpu", "seed", "ATE origin cm", "ATE se3 cm",
             "pieces cm", "max err cm", "RPE1 mm/deg", "events s/r/l", "loops a/f", "s/frame",
             "track s", "map s/call", "frames", "GPU MiB")]
    for r in report["runs"]:
        head = (r["sequence"], _loops(r), str(r["threads"]), r["capability"], str(r["seed"]))
        if "error" in r:
            rows.append((*head, "error", *[""] * 11))
            continue
        ev = r.get("events", {})
        rows.append((*head, str(r.get("ate_origin_cm", "-")), str(r.get("ate_se3_cm", "-")),
                     str(r.get("ate_se3_pieces_cm", "-")), str(r.get("max_error_cm", "-")),
                     f"{r.get('rpe1_mm', '-')}/{r.get('rpe1_deg', '-')}",
                     f"{ev.get('suspect', 0)}/{ev.get('recovered', 0)}/{ev.get('lost', 0)}",
                     (f"{r.get('loops_accepted', 0)}/{r.get('loops_found', 0)}"
                      if _loops(r) == "on" else "-"),
                     str(r["s_per_frame"]), str(r["tracking_s_per_frame"]),
                     str(r["mapping_s_per_call"]), str(r.get("frames", "-")),
                     str(r.get("peak_gpu_memory_mb") or "-")))
    _print_rows(rows)
    print()
    rows = [("sequence", "metric", "runs", "mean", "worst", "lost runs", "Open3D",
             "ratio mean/worst", "pieces ratio", "s/frame / Open3D full", "loops: mean",
             "worst", "lost", "loops a/f")]
    for name, e in report["summary"]["per_sequence"].items():
        lp = e.get("with_loops")
        with_loops = ((str(lp["mean"]), str(lp["worst"]), str(lp["lost_runs"]),
                       f"{lp['loops_accepted']}/{lp['loops_found']}") if lp else ("-",) * 4)
        if "mean" not in e:
            rows.append((name, "error" if not lp else lp["metric"], "", "", "", "", "", "", "",
                         "", *with_loops))
            continue
        o3d = report["open3d"].get(name, {})
        o3d_text = " / ".join(f"{size} {v.get('ate_origin_cm', v['ate_se3_cm'])}"
                              for size, v in o3d.items())
        ratio = (f"{e['ratio_mean_over_best_open3d']}/{e['ratio_worst_over_best_open3d']}"
                 if "ratio_mean_over_best_open3d" in e else "-")
        rows.append((name, e["metric"], str(e["runs"]), str(e["mean"]), str(e["worst"]),
                     str(e["lost_runs"]), o3d_text or "-", ratio,
                     str(e.get("ratio_pieces_mean_over_best_open3d", "-")),
                     str(e.get("s_per_frame_over_open3d_full", "-")), *with_loops))
    _print_rows(rows)
    s = report["summary"].get("synthetic")
    if s:
        print(f"\nsynthetic: {s['runs']} runs, origin ATE mean {s['mean_origin_cm']} cm, worst "
              f"{s['worst_origin_cm']} cm, {s['runs_over_1cm']} over 1 cm, {s['lost_runs']} "
              f"lost track; events {s['events']}")
    s = report["summary"].get("synthetic_with_loops")
    if s:
        print(f"synthetic with loop closure: {s['runs']} runs, origin ATE mean {s['mean']} cm, "
              f"worst {s['worst']} cm, {s['lost_runs']} lost track; loops accepted "
              f"{s['loops_accepted']} of {s['loops_found']} found")
    for name, e in report["summary"].get("ground_truth_error", {}).items():
        print(f"\n{name}: own error (mm) of the ground truth, Open3D and cpslam estimated from "
              "their pairwise differences (three-cornered hat), mean over the runs")
        _print_rows([("metric", "ground truth", "Open3D", "cpslam"),
                     *((m, *(str(v[k]) for k in ("ground_truth", "open3d", "cpslam")))
                       for m, v in e["own_error_mean_mm"].items())])


def _print_rows(rows: list[tuple[str, ...]]) -> None:
    widths = [max(len(row[i]) for row in rows) for i in range(len(rows[0]))]
    for row in rows:
        print("  ".join(cell.ljust(w) for cell, w in zip(row, widths, strict=True)))


if __name__ == "__main__":
    main()

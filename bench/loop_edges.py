"""Loop-edge accuracy and calibration: how close `register_rgbd`'s relative poses between
revisits come to the ground truth, and whether their information matrices say so.

For every sequence, frames `--step` apart are paired when at least `--min-gap` frames lie
between them and their views overlap by at least `--min-overlap` (by the ground truth: the
share of one view's pixels that land in the other with agreeing depth; ground truth is read
here only). Each pair is registered as the server registers a loop candidate, at each
`--factors` size (1 = the processed frame, 0.5 = the half-size copy keyframes used to keep)
and the accepted ones are compared with the ground truth: translation and rotation error,
and chi2 = e^T I e of the error e = log(T_gt^-1 T) whitened by the edge's information I
(the registration's, times `loop.information_scale`). Calibrated edges give chi2 near 6 (the
degrees of freedom; median 5.35); `--calibrate` prints the scale that puts the median there.

Sequences: synthetic scenes as bench/odometry.py builds them (`--scenes`, `--scene-base`;
exact ground truth) and the shared 7-Scenes frames (KinectFusion ground truth, which the depth
data contradict by several centimetres over half a metre: ICP started at the ground-truth
relative pose moves away from it and lowers its residual, and Open3D's odometry disagrees
with it by as much; pairs across its one-frame jump are left out). For those frames the bench
also reports Open3D's frame-to-frame RGB-D odometry over the same pairs (`odometry_same_span`):
a loop edge should be no worse than chaining odometry between its two frames, and how well
each accepted pair's views fit together at the ground-truth pose and at the registered one
(`truth_fit`: point-to-plane RMS of the overlap and colour agreement, as `verify` measures
them): where the registered pose fits better, the ground truth, not the registration, is
what is off.

Usage: python bench/loop_edges.py [--scenes 4] [--scene-base 100] [--factors 0.5 1]
       [--preset cpu] [--set a.b=v ...] [--wire MM_PER_M2] [--calibrate] [--json PATH]
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
from odometry_runs import KITCHEN, ensure_scene, open3d_chain, scene_specs  # noqa: E402

CHI2_6_MEDIAN = 5.348


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", type=int, default=4)
    parser.add_argument("--scene-base", type=int, default=100)
    parser.add_argument("--no-real", action="store_true", help="leave out the 7-Scenes frames")
    parser.add_argument("--factors", type=float, nargs="+", default=[1.0])
    parser.add_argument("--frames", type=int, default=300)
    parser.add_argument("--step", type=int, default=15)
    parser.add_argument("--min-gap", type=int, default=45)
    parser.add_argument("--min-overlap", type=float, default=0.3)
    parser.add_argument("--preset", default="cpu")
    parser.add_argument("--set", nargs="*", default=[], help="config overrides a.b=value")
    parser.add_argument("--wire", type=float, default=None, metavar="MM_PER_M2",
                        help="register the images as the server receives them: JPEG colour "
                             "and depth in steps of MM_PER_M2 x depth^2 (link."
                             "depth_step_mm_per_m2; 0: every mm)")
    parser.add_argument("--jpeg-quality", type=int, default=90,
                        help="JPEG quality of the colour with --wire (link.jpeg_quality)")
    parser.add_argument("--calibrate", action="store_true",
                        help="print the loop.information_scale that calibrates chi2")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args()
    from cpslam.common.config import load_config

    cfg = load_config(args.preset, overrides=args.set, env={})
    report = bench_header("loop_edges", sys.argv)
    report.update(preset=args.preset, overrides=args.set,
                  information_scale=cfg.loop.information_scale, sequences={})
    sequences = [(s["name"], ensure_scene(s, args.frames))
                 for s in scene_specs(args.scenes, args.scene_base)]
    if KITCHEN.is_dir() and not args.no_real:
        sequences.append(("7scenes-kitchen", KITCHEN))
    for name, path in sequences:
        for factor in args.factors:
            key = f"{name}@{factor:g}"
            report["sequences"][key] = evaluate(path, factor, cfg, args)
            _print_one(key, report["sequences"][key])
    report["summary"] = summarise(report["sequences"], cfg.loop.information_scale)
    print(json.dumps(report["summary"], indent=2))
    if args.calibrate:
        raw = [c for s in report["sequences"].values() if not s["real"]
               for c in s["chi2_raw"]]
        if raw:
            print(f"loop.information_scale for a median chi2 of {CHI2_6_MEDIAN} on the "
                  f"synthetic pairs: {CHI2_6_MEDIAN / float(np.median(raw)):.4g}")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(report, indent=2) + "\n")


def over_the_wire(rgb: np.ndarray, depth: np.ndarray, mm_per_m2: float, jpeg_quality: int):
    """(rgb, depth) as the server decodes an agent's image reply of them."""
    from cpslam import protocol
    from cpslam.protocol import KeyframeImage
    from cpslam.protocol.images import depth_coding

    h, w = depth.shape
    msg = KeyframeImage.from_metres(depth, *depth_coding(mm_per_m2), agent_id="a",
                                    kf_id=0, fx=1.0, fy=1.0, cx=0.0, cy=0.0, width=w,
                                    height=h, rgb=np.ascontiguousarray(rgb),
                                    jpeg_quality=jpeg_quality)
    back = protocol.decode(protocol.encode(msg), expected=KeyframeImage)
    return back.rgb, back.depth_metres()


def evaluate(path: Path, factor: float, cfg, args) -> dict:
    """Register every overlapping pair of the sequence at this size."""
    from cpslam.common.camera import resize_rgbd
    from cpslam.common.datasets import open_sequence
    from cpslam.common.geometry import invert, se3_log
    from cpslam.common.registration import RegistrationParams, register_rgbd, verify
    from cpslam.tools.eval import reference_jumps

    seq = open_sequence(path, frames=slice(0, args.frames))
    gt = seq.gt_poses()
    real = path == KITCHEN
    processed = cfg.camera.downscale if real else 1.0  # the synthetic scenes are 320x240
    size = processed * factor
    intr = seq.intrinsics.scaled(size) if size != 1.0 else seq.intrinsics
    jumps = reference_jumps(gt) if real else np.zeros(0, dtype=np.int64)
    frames = {}

    def frame(i: int):
        if i not in frames:
            f = seq[i]
            frames[i] = (f.rgb, f.depth) if size == 1.0 else resize_rgbd(f.rgb, f.depth, size)
            if args.wire is not None:
                frames[i] = over_the_wire(*frames[i], args.wire, args.jpeg_quality)
        return frames[i]

    params = RegistrationParams.from_config(cfg.loop, seed=cfg.run.seed)
    pairs = [(i, j) for i in range(0, len(seq), args.step)
             for j in range(i + args.min_gap, len(seq), args.step)
             if np.sum(i > jumps) == np.sum(j > jumps)]
    out = {"real": real, "size": f"{intr.width}x{intr.height}", "pairs": 0, "accepted": 0,
           "errors": [], "chi2_raw": []}
    if real:
        out["truth_fit"] = []  # [i, j, RMS mm at GT, registered, colour at GT, registered]
    start = time.perf_counter()
    for i, j in pairs:
        T_i_j = invert(gt[i]) @ gt[j]
        if overlap(frame(j)[1], frame(i)[1], intr, T_i_j) < args.min_overlap:
            continue
        out["pairs"] += 1
        reg = register_rgbd(frame(j), frame(i), intr, params)
        if not reg.success:
            continue
        out["accepted"] += 1
        e = se3_log(invert(T_i_j) @ reg.T_dst_src)
        out["errors"].append([i, j, round(100 * float(np.linalg.norm(e[:3])), 3),
                              round(float(np.degrees(np.linalg.norm(e[3:]))), 3),
                              round(float(reg.fitness), 3)])
        out["chi2_raw"].append(float(e @ reg.information @ e))
        if real:
            at_truth = verify(frame(j), frame(i), intr, T_i_j, params)
            out["truth_fit"].append([i, j, round(1000 * at_truth.inlier_rmse, 2),
                                     round(1000 * reg.inlier_rmse, 2),
                                     round(at_truth.color_consistency, 3),
                                     round(reg.color_consistency, 3)])
    out["seconds_per_pair"] = round((time.perf_counter() - start) / max(out["pairs"], 1), 2)
    out.update(_stats(out, cfg.loop.information_scale))
    if real and out["errors"]:
        out["odometry_same_span"] = _odometry_same_span(seq, intr, size, gt, out["errors"],
                                                        cfg.camera.depth_max)
    return out


def _odometry_same_span(seq, intr, size: float, gt: np.ndarray, errors: list,
                        depth_max: float) -> dict:
    """Open3D's chained odometry between the frames of each accepted pair, against the ground
    truth: translation median / p90 / max (cm) and rotation median (deg)."""
    from cpslam.common.geometry import invert, se3_log

    poses, _, _ = open3d_chain(seq, intr, size, depth_max)
    e = np.array([se3_log(invert(invert(gt[i]) @ gt[j]) @ (invert(poses[i]) @ poses[j]))
                  for i, j, *_ in errors])
    t, r = 100 * np.linalg.norm(e[:, :3], axis=1), np.degrees(np.linalg.norm(e[:, 3:], axis=1))
    return {"trans_cm": {"median": round(float(np.median(t)), 3),
                         "p90": round(float(np.percentile(t, 90)), 3),
                         "max": round(float(t.max()), 3)},
            "rot_deg": {"median": round(float(np.median(r)), 3)}}


def overlap(depth_src: np.ndarray, depth_dst: np.ndarray, intr, T_dst_src: np.ndarray) -> float:
    """Share of src's valid pixels (every 4th) seen by dst with depth within 5 cm."""
    sub = np.zeros_like(depth_src)
    sub[::4, ::4] = depth_src[::4, ::4]
    xyz = intr.backproject(sub)[sub > 0]
    if len(xyz) == 0:
        return 0.0
    xyz = xyz @ T_dst_src[:3, :3].T + T_dst_src[:3, 3]
    uv, z = intr.project(xyz)
    u, v = np.round(uv[:, 0]), np.round(uv[:, 1])
    inside = (u >= 0) & (u < intr.width) & (v >= 0) & (v < intr.height)  # NaN is outside
    seen = np.zeros(len(xyz), dtype=bool)
    d = depth_dst[v[inside].astype(int), u[inside].astype(int)]
    seen[inside] = (d > 0) & (np.abs(d - z[inside]) < 0.05)
    return float(seen.mean())


def _stats(out: dict, scale: float) -> dict:
    if not out["errors"]:
        return {}
    e = np.asarray([row[2:4] for row in out["errors"]])
    chi2 = scale * np.asarray(out["chi2_raw"])
    return {"trans_cm": {"median": round(float(np.median(e[:, 0])), 3),
                         "p90": round(float(np.percentile(e[:, 0], 90)), 3),
                         "max": round(float(e[:, 0].max()), 3)},
            "rot_deg": {"median": round(float(np.median(e[:, 1])), 3),
                        "p90": round(float(np.percentile(e[:, 1], 90)), 3),
                        "max": round(float(e[:, 1].max()), 3)},
            "chi2": {"median": round(float(np.median(chi2)), 3),
                     "mean": round(float(np.mean(chi2)), 3)}}


def summarise(sequences: dict, scale: float) -> dict:
    """Pooled over the synthetic sequences and over the real ones, per size."""
    out = {}
    for real in (False, True):
        for size in sorted({s["size"] for s in sequences.values() if s["real"] == real}):
            parts = [s for s in sequences.values() if s["real"] == real and s["size"] == size]
            pooled = {"errors": [r for s in parts for r in s["errors"]],
                      "chi2_raw": [c for s in parts for c in s["chi2_raw"]]}
            entry = {"pairs": sum(s["pairs"] for s in parts),
                     "accepted": sum(s["accepted"] for s in parts), **_stats(pooled, scale)}
            if len(parts) == 1 and "odometry_same_span" in parts[0]:
                entry["odometry_same_span"] = parts[0]["odometry_same_span"]
            rows = [r for s in parts for r in s.get("truth_fit", [])]
            if rows:
                entry["truth_fit"] = truth_fit(rows)
            out[f"{'real' if real else 'synthetic'}@{size}"] = entry
    return out


def truth_fit(rows: list) -> dict:
    """Of the pairs' `truth_fit` rows: how many fit better (lower point-to-plane RMS) at the
    registered pose than at the ground truth, and the median RMS (mm) and colour agreement
    at each."""
    a = np.asarray([row[2:6] for row in rows], dtype=np.float64)
    return {"pairs": len(rows), "registered_fits_better": int(np.sum(a[:, 1] < a[:, 0])),
            "rmse_mm_median": {"ground_truth": round(float(np.median(a[:, 0])), 2),
                               "registered": round(float(np.median(a[:, 1])), 2)},
            "color_median": {"ground_truth": round(float(np.median(a[:, 2])), 3),
                             "registered": round(float(np.median(a[:, 3])), 3)}}


def _print_one(key: str, s: dict) -> None:
    if "trans_cm" not in s:
        print(f"{key}: {s['accepted']}/{s['pairs']} accepted")
        return
    print(f"{key}: {s['accepted']}/{s['pairs']} accepted, translation median "
          f"{s['trans_cm']['median']} p90 {s['trans_cm']['p90']} max {s['trans_cm']['max']} cm, "
          f"rotation median {s['rot_deg']['median']} max {s['rot_deg']['max']} deg, chi2 median "
          f"{s['chi2']['median']}, {s['seconds_per_pair']} s/pair", flush=True)


if __name__ == "__main__":
    main()

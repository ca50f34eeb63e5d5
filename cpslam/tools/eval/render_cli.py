"""``cpslam eval render``: image quality of renders from a run's final map at the
ground-truth poses, against the captured frames (the paper's rendering table).

1. The final map: `cpslam.tools.runfolder.final_model` (the server's fused map of the main
   group with its decoders, or one agent's own map).
2. Ground truth of each agent the map covers: its recorded sequence or ``--gt``, a dataset
   folder (its images are the reference).
3. One se3 alignment of the agents' estimated trajectories to the ground truth (the joint
   ATE's), so the ground-truth poses can be expressed in the map's frame:
   ``T_map_cam = inv(T_gt_est) @ T_gt_cam``. Rendering at ground-truth poses, not at the
   estimated ones, scores the map and not the tracking error.
4. At up to ``--views`` frames per agent, spread evenly over the frames it processed: render
   (`cpslam.tools.render.render_views`) at the processing resolution, compare with the
   frame resized the same way: PSNR and SSIM (`cpslam.tools.eval.image`), depth L1
   (`cpslam.tools.eval.recon.depth_l1`, pixels valid in both).

LPIPS is not computed: the packages that implement it fetch their network weights on first
use, and nothing here downloads; the output says so.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import typer

from cpslam.common.cli import JsonOpt, OverwriteOpt, check_output, fail, out_option

logger = logging.getLogger(__name__)

__all__ = ["LPIPS_NOTE", "evaluate_renders", "render"]

LPIPS_NOTE = ("LPIPS omitted: no installed package ships its network weights, and cpslam "
              "downloads nothing")
DEFAULT_VIEWS = 10


def evaluate_renders(run: Path, sequences: dict[str, Path], views: int = DEFAULT_VIEWS,
                     device: str = "cpu", show_progress: bool = False,
                     save: Path | None = None) -> dict[str, Any]:
    """PSNR (dB), SSIM, depth L1 (m) per agent of the map and over all rendered frames;
    `save`: also write each render and its reference as PNG
    (``SAVE/agent_<id>/<frame>_render.png`` and ``_gt.png``)."""
    from cpslam.agent.standalone import open_for_config
    from cpslam.common.camera import resize_rgbd
    from cpslam.common.logs import progress
    from cpslam.common.rundir import SCHEMA_VERSION
    from cpslam.tools.eval import associate, joint_ate
    from cpslam.tools.eval.image import psnr, ssim
    from cpslam.tools.eval.recon import depth_l1
    from cpslam.tools.render import render_views
    from cpslam.tools.runfolder import final_model, trajectories

    final = final_model(run, device)
    cfg, intr = final.model.config, final.model.intrinsics
    missing = [m for m in final.members if m not in sequences]
    if missing:
        raise ValueError(f"{run}: no ground truth for agent(s) {', '.join(missing)} of the "
                         f"map ({final.frame}); give --gt ID=DATASET")
    est = trajectories(run, final.members)
    seqs, gts = {}, {}
    for m in final.members:
        if not Path(sequences[m]).is_dir():
            raise ValueError(f"--gt {sequences[m]}: a dataset folder is needed (its images "
                             "are the reference), not a trajectory file")
        seqs[m] = open_for_config(cfg, sequences[m])
        poses = seqs[m].gt_poses()
        if poses is None or est[m]["global"] is None:
            raise ValueError(f"agent {m}: {sequences[m]} has no ground-truth poses or the "
                             "run no trajectory")
        gts[m] = (np.asarray(seqs[m].timestamps, np.float64), np.asarray(poses, np.float64))
    fit = joint_ate([(gts[m], est[m]["global"]) for m in final.members], align="se3").overall
    T_est_gt = np.linalg.inv(fit.T_gt_est)
    scale = cfg.camera.downscale
    rows: dict[str, dict[str, Any]] = {}
    notes = [LPIPS_NOTE]
    for m in final.members:
        _, gt_idx = associate(est[m]["global"][0], gts[m][0])
        pick = gt_idx[np.linspace(0, len(gt_idx) - 1, min(views, len(gt_idx))).round()
                      .astype(int)]
        pick = pick[np.isfinite(gts[m][1][pick]).all(axis=(1, 2))]
        T_map_cam = T_est_gt[None] @ gts[m][1][pick]
        p, s, rendered_depth, ref_depth = [], [], [], []
        renders = progress(render_views(final.model, T_map_cam), total=len(pick),
                           desc=f"render agent {m}", disable=not show_progress)
        for i, (rgb, depth) in zip(pick, renders, strict=True):
            frame = seqs[m][int(i)]
            ref_rgb, ref_d = ((frame.rgb, frame.depth) if scale == 1.0
                              else resize_rgbd(frame.rgb, frame.depth, scale))
            if ref_rgb.shape[:2] != (intr.height, intr.width):
                raise ValueError(f"{sequences[m]}: frames are {ref_rgb.shape[1]}x"
                                 f"{ref_rgb.shape[0]} at the run's scale, the map renders "
                                 f"{intr.width}x{intr.height}: not the run's sequence?")
            if save is not None:
                _save_pair(save / f"agent_{m}", int(frame.index), rgb, ref_rgb)
            p.append(psnr(rgb, ref_rgb))
            s.append(ssim(rgb, ref_rgb))
            rendered_depth.append(depth)
            ref_depth.append(ref_d)
        try:
            l1 = depth_l1(rendered_depth, ref_depth)
        except ValueError:  # the map renders no depth where the frames have some
            l1 = None
            notes.append(f"agent {m}: no depth L1, the renders and frames share no valid "
                         "depth pixel")
        rows[m] = {"frames": [int(seqs[m][int(i)].index) for i in pick],
                   "psnr_db": p, "ssim": s, "depth_l1_m": l1}
    every_psnr = [v for r in rows.values() for v in r["psnr_db"]]
    every_ssim = [v for r in rows.values() for v in r["ssim"]]
    return {
        "schema_version": SCHEMA_VERSION, "run": str(run), "map": final.frame,
        "ground_truth": {m: str(sequences[m]) for m in final.members},
        "alignment_T_gt_est": fit.T_gt_est.tolist(), "alignment_ate_m": fit.rmse,
        "width": intr.width, "height": intr.height,
        "agents": {m: {**r, "mean_psnr_db": float(np.mean(r["psnr_db"])),
                       "mean_ssim": float(np.mean(r["ssim"]))} for m, r in rows.items()},
        "psnr_db": float(np.mean(every_psnr)), "ssim": float(np.mean(every_ssim)),
        "depth_l1_m": _frame_mean(rows), "lpips": None, "notes": notes,
    }


def _frame_mean(rows: dict[str, dict[str, Any]]) -> float | None:
    """Depth L1 over the agents with one, each frame weighing the same (as in depth_l1)."""
    have = [r for r in rows.values() if r["depth_l1_m"] is not None]
    if not have:
        return None
    return float(np.average([r["depth_l1_m"] for r in have],
                            weights=[len(r["ssim"]) for r in have]))


def _cm(value: float | None) -> str:
    return "-" if value is None else f"{100 * value:.2f}"


def _save_pair(folder: Path, index: int, rgb: np.ndarray, ref_rgb: np.ndarray) -> None:
    import cv2

    folder.mkdir(parents=True, exist_ok=True)
    for name, img in (("render", rgb), ("gt", ref_rgb)):
        path = folder / f"{index:06d}_{name}.png"
        if not cv2.imwrite(str(path), np.ascontiguousarray(img[..., ::-1])):
            raise OSError(f"{path}: could not be written")


def render(
    run: Annotated[Path, typer.Argument(help="Finished run folder (any kind).")],
    gt: Annotated[list[Path] | None, typer.Option(
        "--gt", help="Dataset folder of an agent: ID=PATH, or PATH for the next agent in "
        "order (repeat per agent). Default: the sequences the run recorded.",
        show_default=False)] = None,
    views: Annotated[int, typer.Option("--views", min=1, help="Frames per agent, spread "
                                       "evenly over those it processed.")] = DEFAULT_VIEWS,
    device: Annotated[str, typer.Option("--device", help="auto, cpu, cuda or cuda:N "
                                        "(rendering).")] = "cpu",
    as_json: JsonOpt = False,
    out: Annotated[Path | None, out_option("Also write the numbers to this JSON file.")] = None,
    save_images: Annotated[Path | None, typer.Option(
        "--save-images", help="Also write each render and its reference frame as PNG "
        "(DIR/agent_<id>/<frame>_render.png, _gt.png).", show_default=False)] = None,
    overwrite: OverwriteOpt = False,
) -> None:
    """PSNR, SSIM and depth L1 of renders from a run's final map at the ground-truth poses.

    The ground-truth poses are brought into the map's frame by one se3 alignment of the
    agents' trajectories (the joint ATE's), rendered at the run's processing resolution and
    compared with the captured frames resized the same way. LPIPS is omitted (its weights
    would have to be downloaded); the output says so.

    Examples:

      cpslam eval render runs/demo

      cpslam eval render runs/room --gt runs/data/room/agent_0 --views 30

      cpslam eval render runs/apt --gt 1=data/apt/agent_1 --json --out render.json

      cpslam eval render runs/demo --views 3 --save-images runs/demo/render_check
    """
    from rich.console import Console
    from rich.table import Table

    from cpslam.common.device import resolve_device
    from cpslam.tools.eval.cli import write_record
    from cpslam.tools.runfolder import agent_ids, parse_gt_options, recorded_sequences

    for path in (out, save_images):
        if path is not None:
            check_output(path, overwrite)
    if not run.is_dir():
        fail(f"{run}: no such run folder")
    try:
        sequences = {**recorded_sequences(run), **parse_gt_options([str(g) for g in gt or []],
                                                                agent_ids(run))}
        record = evaluate_renders(run, sequences, views, resolve_device(device),
                                  show_progress=not as_json, save=save_images)
    except (OSError, ValueError) as err:
        fail(str(err))
    if as_json:
        typer.echo(json.dumps(record, indent=2))
    else:
        table = Table(title=f"Renders of the final map ({record['map']}) at ground-truth "
                      f"poses, {record['width']}x{record['height']}", title_justify="left")
        for col in ("agent", "frames", "PSNR dB", "SSIM", "depth L1 cm"):
            table.add_column(col, justify="left" if col == "agent" else "right")
        for m, r in record["agents"].items():
            table.add_row(m, str(len(r["frames"])), f"{r['mean_psnr_db']:.2f}",
                          f"{r['mean_ssim']:.3f}", _cm(r["depth_l1_m"]))
        table.add_section()
        table.add_row("all", str(sum(len(r["frames"]) for r in record["agents"].values())),
                      f"{record['psnr_db']:.2f}", f"{record['ssim']:.3f}",
                      _cm(record["depth_l1_m"]))
        console = Console()
        console.print(table)
        console.print("alignment: se3 of the trajectories, ATE "
                      f"{100 * record['alignment_ate_m']:.1f} cm")
        for note in record["notes"]:
            console.print(f"note: {note}")
    if out is not None:
        write_record(out, record, quiet=as_json)

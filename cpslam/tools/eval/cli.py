"""``cpslam eval ate``: score an estimated trajectory against ground truth (ATE, and with
``--rpe`` the relative pose error over given frame spans)."""

from __future__ import annotations

import json
import logging
from enum import Enum
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console
from rich.table import Table

from cpslam.common.cli import JsonOpt, OverwriteOpt, check_output, fail, out_option
from cpslam.common.datasets.cli import FormatOpt, FramesOpt
from cpslam.common.rundir import SCHEMA_VERSION
from cpslam.common.trajectory import Trajectory
from cpslam.tools.eval.ate import DEFAULT_MAX_DT, AteResult, JointAteResult, evaluate_ate
from cpslam.tools.eval.rpe import RpeResult, evaluate_rpe
from cpslam.tools.eval.segments import SegmentedAte, reference_jumps, segmented_ate
from cpslam.tools.eval.source import load_trajectory, locate_trajectory

logger = logging.getLogger(__name__)


class AlignMode(str, Enum):
    origin = "origin"
    se3 = "se3"
    sim3 = "sim3"
    none = "none"


def ate(
    gt: Annotated[
        list[Path],
        typer.Option(
            "--gt", help="Ground truth: TUM file, run folder or dataset folder (repeat with "
            "--est for several agents).", show_default=False
        ),
    ],
    est: Annotated[
        list[Path],
        typer.Option(
            "--est",
            help="Estimate: TUM file, run folder with one trajectory.tum (at the top or in "
            "agent_*/) or dataset folder (its ground-truth poses). The n-th --est goes with "
            "the n-th --gt.",
            show_default=False,
        ),
    ],
    align: Annotated[
        AlignMode | None,
        typer.Option(
            "--align",
            help="origin: first poses coincide (the paper's protocol); se3/sim3: "
            "least-squares rigid/similarity fit; none: same frame already. Default: origin "
            "for one pair, se3 for several (one alignment for all).",
            show_default=False,
        ),
    ] = None,
    max_dt: Annotated[
        float,
        typer.Option(
            "--max-dt", min=0.0, help="Largest time difference of a pose pair, in seconds."
        ),
    ] = DEFAULT_MAX_DT,
    fmt: FormatOpt = None,
    frames: FramesOpt = None,
    as_json: JsonOpt = False,
    out: Annotated[Path | None, out_option("Also write the numbers to this JSON file.")] = None,
    plot: Annotated[
        Path | None, typer.Option("--plot", help="Write a PNG: top view and error over time.")
    ] = None,
    overwrite: OverwriteOpt = False,
    rpe: Annotated[
        list[int] | None,
        typer.Option(
            "--rpe", min=1, help="Also the relative pose error over this many frames "
            "(repeat for several, e.g. --rpe 1 --rpe 10).", show_default=False,
        ),
    ] = None,
    pieces: Annotated[
        bool,
        typer.Option(
            "--pieces", help="Also the ATE over the pieces between one-frame jumps of the "
            "ground truth, each piece aligned on its own (docs/evaluation.md).",
        ),
    ] = False,
) -> None:
    """Absolute trajectory error (ATE) of an estimate against ground truth, in centimetres.

    Poses are paired by timestamp. --format and --frames apply to whichever of --gt and
    --est is a dataset folder (usually the ground truth); a selection keeps the sequence's
    own timestamps, so it lines up with an estimate of the same frames.

    Several --gt/--est pairs (one per agent, the estimates in one shared frame such as
    RUN/trajectories/agent_<id>_global.tum) are scored under ONE alignment fitted to all
    pairs together: the joint ATE of a multi-robot system, with each pair's share of it.

    Examples:

      cpslam eval ate --gt runs/data/room/agent_0 --est runs/room

      cpslam eval ate --gt ../shared/data/7scenes-kitchen-0-299 --frames 0:100 --est runs/kitchen

      cpslam eval ate --gt groundtruth.tum --est runs/apt/agent_1/trajectory.tum --align sim3

      cpslam eval ate --gt data/office --format tum --est runs/office --out ate.json --plot ate.png

      cpslam eval ate --gt runs/data/room/agent_0 --est runs/room --json > ate.json

      cpslam eval ate --gt ../shared/data/7scenes-kitchen-0-299 --est runs/kitchen --rpe 1 --rpe 10

      cpslam eval ate --gt ../shared/data/7scenes-kitchen-0-299 --est runs/kitchen --pieces

      cpslam eval ate --gt data/apt/agent_0 --est runs/apt/trajectories/agent_0_global.tum
      --gt data/apt/agent_1 --est runs/apt/trajectories/agent_1_global.tum
    """
    for path in (out, plot):
        if path is not None:
            check_output(path, overwrite)
    if len(gt) != len(est):
        fail(f"--gt and --est come in pairs: got {len(gt)} --gt and {len(est)} --est")
    if len(gt) > 1:
        if rpe or pieces:
            fail("--rpe and --pieces score one trajectory; give one --gt/--est pair")
        _joint(gt, est, align or AlignMode.se3, max_dt, fmt, frames, as_json, out, plot)
        return
    gt, est, align = gt[0], est[0], align or AlignMode.origin
    try:
        gt_kind, gt_file = locate_trajectory(gt)
        est_kind, est_file = locate_trajectory(est)
        if (fmt is not None or frames is not None) and "dataset" not in (gt_kind, est_kind):
            raise ValueError(
                f"--format/--frames apply to dataset folders; {gt_file} and {est_file} are "
                "TUM trajectory files"
            )
        gt_traj = _load(gt, gt_kind, fmt, frames)
        est_traj = _load(est, est_kind, fmt, frames)
        result = evaluate_ate(
            gt_traj.stamps,
            gt_traj.poses,
            est_traj.stamps,
            est_traj.poses,
            align=align.value,
            max_dt=max_dt,
            gt_name=str(gt_file),
            est_name=str(est_file),
        )
        rpes = [evaluate_rpe(gt_traj.stamps, gt_traj.poses, est_traj.stamps, est_traj.poses,
                             delta=delta, max_dt=max_dt) for delta in sorted(set(rpe or []))]
        split = segmented_ate(gt_traj.stamps, gt_traj.poses, est_traj.stamps, est_traj.poses,
                              reference_jumps(gt_traj.poses), align=align.value,
                              max_dt=max_dt) if pieces else None
    except (OSError, ValueError) as exc:
        fail(str(exc))

    record = {"schema_version": SCHEMA_VERSION, "gt": str(gt_file), "est": str(est_file),
              **result.to_dict()}
    if rpes:
        record["rpe"] = [r.to_dict() for r in rpes]
    if split is not None:
        record["pieces"] = split.to_dict()
    if as_json:
        typer.echo(json.dumps(record, indent=2))
    else:
        _print_table(result, gt_file, est_file, rpes, split)
    try:
        if out is not None:
            write_record(out, record, quiet=as_json)
        if plot is not None:
            from cpslam.tools.eval.plot import plot_ate

            plot_ate(result, plot, title=f"{est_file} vs {gt_file}")
            if not as_json:
                typer.echo(f"wrote {plot}")
    except OSError as exc:
        fail(str(exc))


def _joint(gts: list[Path], ests: list[Path], align: AlignMode, max_dt: float,
           fmt: str | None, frames: str | None, as_json: bool, out: Path | None,
           plot: Path | None) -> None:
    """Several pairs under one alignment: per-pair rows and the joint row."""
    from cpslam.tools.eval.ate import joint_ate

    try:
        located = [(locate_trajectory(g), locate_trajectory(e)) for g, e in zip(
            gts, ests, strict=True)]
        if (fmt is not None or frames is not None) and all(
                "dataset" not in (g[0], e[0]) for g, e in located):
            raise ValueError("--format/--frames apply to dataset folders; every --gt and "
                             "--est is a TUM trajectory file")
        pairs = [(_load(g, gk, fmt, frames), _load(e, ek, fmt, frames))
                 for g, e, ((gk, _), (ek, _)) in zip(gts, ests, located, strict=True)]
        names = [(str(gf), str(ef)) for (_, gf), (_, ef) in located]
        result = joint_ate(pairs, align=align.value, max_dt=max_dt, names=names)
    except (OSError, ValueError) as exc:
        fail(str(exc))
    record = {"schema_version": SCHEMA_VERSION, "align": align.value,
              "joint": result.overall.to_dict(),
              "pairs": [{"gt": g, "est": e, **p.to_dict()}
                        for (g, e), p in zip(names, result.parts, strict=True)]}
    if as_json:
        typer.echo(json.dumps(record, indent=2))
    else:
        _print_joint(result, names)
    try:
        if out is not None:
            write_record(out, record, quiet=as_json)
        if plot is not None:
            from cpslam.tools.eval.plot import plot_ate

            plot_ate(result.parts, plot, labels=[e for _, e in names],
                     title=f"{len(names)} trajectories, one {align.value} alignment, joint "
                           f"RMSE {100 * result.overall.rmse:.1f} cm")
            if not as_json:
                typer.echo(f"wrote {plot}")
    except OSError as exc:
        fail(str(exc))


def _print_joint(result: JointAteResult, names: list[tuple[str, str]]) -> None:
    table = Table(title=f"Absolute trajectory error, {len(names)} pairs under one "
                  f"{result.overall.align} alignment", title_justify="left")
    for col in ("estimate", "ground truth", "pairs", "RMSE cm", "mean cm", "max cm",
                "rot RMSE deg"):
        table.add_column(col, justify="left" if col in ("estimate", "ground truth") else "right")
    for (g, e), r in zip(names, result.parts, strict=True):
        table.add_row(e, g, str(r.n_pairs), f"{100 * r.rmse:.2f}", f"{100 * r.mean:.2f}",
                      f"{100 * r.max:.2f}", f"{r.rot_rmse_deg:.2f}")
    r = result.overall
    table.add_section()
    table.add_row("joint", "", str(r.n_pairs), f"{100 * r.rmse:.2f}", f"{100 * r.mean:.2f}",
                  f"{100 * r.max:.2f}", f"{r.rot_rmse_deg:.2f}")
    Console().print(table)
    if r.align == "sim3":
        Console().print(f"scale {r.scale:.4f}")


def write_record(path: Path, record: dict, quiet: bool = False) -> None:
    """Write an evaluation record as JSON (`--out`); say so unless stdout carries `--json`."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(record, indent=2) + "\n")
    if not quiet:
        typer.echo(f"wrote {path}")


def _load(path: Path, kind: str, fmt: str | None, frames: str | None) -> Trajectory:
    # Only a dataset folder takes the format and selection; load_trajectory refuses them for
    # a TUM file, which is right when it is the only input but not next to a dataset.
    if kind == "dataset":
        return load_trajectory(path, fmt, frames)
    return load_trajectory(path)


def _print_table(result: AteResult, gt_file: Path, est_file: Path,
                 rpes: list[RpeResult], split: SegmentedAte | None = None) -> None:
    table = Table(title="Absolute trajectory error", show_header=False, title_justify="left")
    table.add_column("quantity", style="bold")
    table.add_column("value")
    table.add_row("ground truth", str(gt_file))
    table.add_row("estimate", str(est_file))
    table.add_row(
        "matched pairs",
        f"{result.n_pairs} of {result.n_est} (gt {result.n_gt}, max dt {result.max_dt:g} s)",
    )
    table.add_row("alignment", result.align)
    if result.align == "sim3":
        table.add_row("scale", f"{result.scale:.4f}")
    table.add_row("RMSE", f"{100.0 * result.rmse:.2f} cm")
    table.add_row("mean", f"{100.0 * result.mean:.2f} cm")
    table.add_row("median", f"{100.0 * result.median:.2f} cm")
    table.add_row("max", f"{100.0 * result.max:.2f} cm")
    table.add_row("rotation RMSE", f"{result.rot_rmse_deg:.2f} deg")
    for r in rpes:
        table.add_row(f"RPE over {r.delta} frame{'s' if r.delta > 1 else ''}",
                      f"{1000.0 * r.trans_mean:.2f} mm, {r.rot_mean_deg:.3f} deg mean "
                      f"({r.pairs} pairs)")
    if split is not None:
        jumps = ", ".join(f"{j}->{j + 1}" for j in split.jumps) or "none"
        table.add_row("RMSE over pieces", f"{100.0 * split.rmse:.2f} cm ({len(split.pieces)} "
                      f"pieces; ground truth jumps at frames {jumps})")
    Console().print(table)

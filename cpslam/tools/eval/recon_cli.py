"""``cpslam eval recon``: score a reconstructed mesh against a ground-truth mesh."""

from __future__ import annotations

import json
import logging
from enum import Enum
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import numpy as np
import typer
from rich.console import Console
from rich.table import Table

from cpslam.common.cli import JsonOpt, OverwriteOpt, check_output, fail, out_option
from cpslam.common.rundir import SCHEMA_VERSION

if TYPE_CHECKING:
    from cpslam.common.datasets import RGBDSequence
    from cpslam.tools.eval.recon import Frustum, ReconResult

logger = logging.getLogger(__name__)

# Mirrors cpslam.tools.eval.recon (not imported here: it pulls in open3d, and the CLI
# should list its commands without that cost).
_DEFAULT_SAMPLES = 200_000
_DEFAULT_THRESHOLD = 0.05


class Method(str, Enum):
    points = "points"
    surface = "surface"


def recon(
    gt: Annotated[
        Path, typer.Option("--gt", help="Ground-truth mesh (.ply, .obj, ...).", show_default=False)
    ],
    est: Annotated[
        Path,
        typer.Option("--est", help="Reconstructed mesh, e.g. RUN/mesh.ply.", show_default=False),
    ],
    samples: Annotated[
        int, typer.Option("--samples", min=1, help="Points sampled on each mesh.")
    ] = _DEFAULT_SAMPLES,
    sample_seed: Annotated[int, typer.Option(
        "--sample-seed", help="Seed of the surface sampling.")] = 0,
    threshold: Annotated[
        float,
        typer.Option("--threshold", min=0.0, help="Completion-ratio radius, metres."),
    ] = _DEFAULT_THRESHOLD,
    method: Annotated[
        Method,
        typer.Option(
            "--method",
            help="points: distance to the other mesh's samples (the papers' protocol); "
            "surface: distance to the other mesh's triangles (no sampling floor).",
        ),
    ] = Method.points,
    cull_to: Annotated[
        Path | None,
        typer.Option(
            "--cull-to",
            help="Dataset folder: score only samples its cameras saw (ground-truth poses).",
        ),
    ] = None,
    frames: Annotated[
        str | None,
        typer.Option("--frames", help="With --cull-to: frames START:STOP[:STEP] to use."),
    ] = None,
    occlusion: Annotated[
        bool,
        typer.Option(
            "--occlusion",
            help="With --cull-to: also drop samples hidden behind the observed depth "
            "(reads the depth images).",
        ),
    ] = False,
    depth_max: Annotated[
        float,
        typer.Option("--depth-max", min=0.0, help="With --cull-to: farthest seen depth, metres."),
    ] = 6.0,
    as_json: JsonOpt = False,
    out: Annotated[Path | None, out_option("Also write the numbers to this JSON file.")] = None,
    overwrite: OverwriteOpt = False,
) -> None:
    """Mesh accuracy, completion (cm) and completion ratio (%) against ground truth.

    Examples:

      cpslam eval recon --gt data/synth/mesh.ply --est runs/x/mesh.ply

      cpslam eval recon --gt data/synth/mesh.ply --est runs/x/mesh.ply --cull-to data/synth/agent_0

      cpslam eval recon --gt gt.ply --est runs/x/mesh.ply --method surface --out recon.json

      cpslam eval recon --gt gt.ply --est runs/x/mesh.ply --sample-seed 1 --json
    """
    from cpslam.tools.eval.cli import write_record
    from cpslam.tools.eval.recon import evaluate_recon

    if out is not None:
        check_output(out, overwrite)
    from cpslam.tools.mesh import read_mesh

    try:
        gt_mesh = read_mesh(gt)
        est_mesh = read_mesh(est)
        frustum = None
        if cull_to is not None:
            frustum = _frustum(cull_to, frames, occlusion, depth_max)
        result = evaluate_recon(
            est_mesh,
            gt_mesh,
            samples=samples,
            seed=sample_seed,
            threshold=threshold,
            method=method.value,
            frustum=frustum,
        )
    except (OSError, ValueError) as exc:
        fail(str(exc))

    record = {"schema_version": SCHEMA_VERSION, "gt": str(gt), "est": str(est),
              "cull_to": cull_to and str(cull_to), **result.to_dict()}
    if as_json:
        typer.echo(json.dumps(record, indent=2))
    else:
        _print_table(result, gt, est, cull_to)
    if out is not None:
        try:
            write_record(out, record, quiet=as_json)
        except OSError as exc:
            fail(f"{out}: {exc}")


def _frustum(path: Path, frames: str | None, occlusion: bool, depth_max: float) -> Frustum:
    """The cameras of a dataset folder at their ground-truth poses."""
    from cpslam.common.datasets import open_sequence
    from cpslam.tools.eval.recon import Frustum

    seq = open_sequence(path, frames=frames)
    poses = seq.gt_poses()
    if poses is None or not np.isfinite(poses).all(axis=(1, 2)).any():
        raise ValueError(f"{path}: no ground-truth poses to cull with")
    depths = _Depths(seq) if occlusion else None
    return Frustum(poses, seq.intrinsics, depth_max=depth_max, depths=depths)


class _Depths:
    """The depth images of a sequence, read when indexed (a long sequence does not fit in
    memory at once)."""

    def __init__(self, seq: RGBDSequence) -> None:
        self.seq = seq

    def __len__(self) -> int:
        return len(self.seq)

    def __getitem__(self, i: int) -> np.ndarray:
        return self.seq[i].depth


def _print_table(result: ReconResult, gt: Path, est: Path, cull_to: Path | None) -> None:
    table = Table(title="Reconstruction", show_header=False, title_justify="left")
    table.add_column("quantity", style="bold")
    table.add_column("value")
    table.add_row("ground truth", str(gt))
    table.add_row("reconstruction", str(est))
    table.add_row(
        "samples",
        f"{result.samples} per mesh (seed {result.seed}), method {result.method}",
    )
    if cull_to is not None:
        table.add_row("culled to", f"{cull_to}: scored {result.n_est} est, {result.n_gt} gt")
    floors = result.method == "points"
    acc_floor = f"  (sampling floor {100.0 * result.accuracy_floor:.2f} cm)" if floors else ""
    comp_floor = f"  (sampling floor {100.0 * result.completion_floor:.2f} cm)" if floors else ""
    table.add_row("accuracy", f"{100.0 * result.accuracy:.2f} cm{acc_floor}")
    table.add_row("completion", f"{100.0 * result.completion:.2f} cm{comp_floor}")
    table.add_row(
        "completion ratio",
        f"{100.0 * result.completion_ratio:.1f} % (< {100.0 * result.threshold:g} cm)",
    )
    table.add_row(
        "precision / F-score", f"{100 * result.precision:.1f} % / {100 * result.f_score:.1f} %"
    )
    Console().print(table)

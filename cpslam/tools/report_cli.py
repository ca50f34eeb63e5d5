"""`cpslam report RUN`: the end-of-run report of any run folder, and `finish_run`, the one
path every command that ends a run takes to build and print it (`cpslam demo`, `cpslam run`,
`cpslam-agent --standalone`, `cpslam-server`)."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Annotated, Any

import typer

from cpslam.common.cli import JsonOpt, fail, interruptible

logger = logging.getLogger(__name__)

__all__ = ["finish_run", "report"]


def finish_run(run: Path, sequences: dict[str, Path] | None = None, mesh: bool = True,
               title: str | None = None, process: str = "report", show_progress: bool = False,
               console: Any = None, outputs: bool = True,
               render_views: int | None = None) -> dict[str, Any]:
    """Build the report of a finished run (RUN/report.json, plots, mesh) and print it; the
    list of outputs too unless `outputs` is False. Returns the report."""
    from rich.console import Console

    from cpslam.tools.report import RENDER_VIEWS, build_report
    from cpslam.tools.report_table import print_outputs, print_report

    console = console or Console()
    # Ctrl-C during a report leaves the run as it is; `cpslam report RUN` makes it again.
    report = interruptible(
        lambda: build_report(run, sequences, mesh=mesh, show_progress=show_progress,
                             process=process, render_views=RENDER_VIEWS
                             if render_views is None else render_views),
        f"the report of {run} (cpslam report {run} makes it again)")
    print_report(report, console, title)
    if outputs:
        print_outputs(report, console)
    return report


def report(
    run: Annotated[Path, typer.Argument(help="Finished run folder: cpslam run, cpslam demo, "
                                        "the daemons' --out or cpslam-agent --standalone.")],
    gt: Annotated[list[Path] | None, typer.Option(
        "--gt", help="Ground truth of an agent: ID=PATH, or PATH for the next agent in order "
        "(a dataset folder or a TUM file; repeat per agent). Default: the sequences the run "
        "recorded.", show_default=False)] = None,
    mesh: Annotated[bool, typer.Option("--mesh/--no-mesh", help="TSDF mesh of the final map "
                                       "(RUN/mesh.ply).")] = True,
    render_views: Annotated[int, typer.Option(
        "--render-views", min=0, help="Frames per agent for the render metrics (PSNR, SSIM, "
        "depth L1 at ground-truth poses, as cpslam eval render; 0: none).")] = 5,
    if_gt: Annotated[bool, typer.Option(
        "--if-ground-truth", help="Only when every agent's recorded sequence has ground "
        "truth; otherwise say so and exit 0 (what cpslam-server runs after finalising).")
                     ] = False,
    as_json: JsonOpt = False,
    no_progress: Annotated[bool, typer.Option("--no-progress", help="No progress bar.")
                           ] = False,
) -> None:
    """Tables, plots, mesh and report.json of a finished run.

    The table: per agent and for all, ATE (local and global, cm), loops, merge times, map
    size, bytes sent and received; then traffic per agent and key expression, peak memory of
    every process, render metrics (PSNR, SSIM, depth L1 of the final map at ground-truth
    poses, as cpslam eval render) and, for a synthetic scene, the mesh's accuracy and
    completion. Writes
    RUN/report.json (replaced), RUN/plots/*.png (with ground truth) and RUN/mesh.ply.
    Ground truth: the sequences recorded in RUN/agent_<id>/metrics.json (or demo.json);
    --gt replaces those of the agents it names.

    Examples:

      cpslam report runs/demo

      cpslam report runs/apt --gt runs/data/apt/agent_0 --gt runs/data/apt/agent_1

      cpslam report runs/lab --gt robot-2=data/lab/robot2 --no-mesh

      cpslam report runs/room --json > report.json
    """
    import json

    from rich.console import Console

    from cpslam.tools.runfolder import (
        agent_ids,
        ground_truth,
        parse_gt_options,
        recorded_sequences,
    )

    if not run.is_dir():
        fail(f"{run}: no such run folder")
    if if_gt and not gt and ground_truth(run) is None:
        typer.echo(f"{run}: not every agent has a recorded sequence with ground truth; no "
                   "report (cpslam report RUN --gt ... makes one)", err=True)
        return
    try:
        # --gt replaces the recorded sequence of the agents it names, no others.
        sequences = {**recorded_sequences(run), **parse_gt_options([str(g) for g in gt or []],
                                                                agent_ids(run))}
        console = Console(stderr=True) if as_json else Console()
        result = finish_run(run, sequences, mesh=mesh, show_progress=not no_progress,
                            console=console, outputs=not as_json, render_views=render_views)
    except (FileNotFoundError, ValueError) as err:
        fail(str(err))
    if as_json:
        typer.echo(json.dumps(result, indent=2, default=str))

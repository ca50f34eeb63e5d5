"""`cpslam-agent`: run one agent on one RGB-D sequence."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Annotated

import typer

from cpslam.common.config.cli import ConfigOpt, DeviceOpt, PresetOpt, SeedOpt, SetOpt

logger = logging.getLogger("cpslam.agent")

app = typer.Typer(add_completion=False, context_settings={"help_option_names": ["-h", "--help"]})


@app.command()
def agent(
    seq: Annotated[Path, typer.Option("--seq", help="Sequence folder (any supported format).")],
    standalone: Annotated[
        bool, typer.Option("--standalone", help="Run without a server (odometry and mapping only).")
    ] = False,
    agent_id: Annotated[int, typer.Option("--agent-id", help="Agent id (0, 1, …).")] = 0,
    preset: PresetOpt = "cpu",
    config_file: ConfigOpt = None,
    sets: SetOpt = None,
    device: DeviceOpt = None,
    seed: SeedOpt = None,
    frames: Annotated[
        str | None, typer.Option("--frames", help="START:STOP[:STEP] of the sequence.")
    ] = None,
    fmt: Annotated[
        str | None,
        typer.Option("--format", help="replica, tum, 7scenes or scannet (default: detect)."),
    ] = None,
    out: Annotated[
        Path | None,
        typer.Option("--out", help="Run folder (default: run.out/run.name, timestamped)."),
    ] = None,
    resume: Annotated[
        Path | None, typer.Option("--resume", help="state.pt of an earlier run to continue from.")
    ] = None,
    no_progress: Annotated[bool, typer.Option("--no-progress", help="No progress bar.")] = False,
    verbose: Annotated[int, typer.Option("--verbose", "-v", count=True)] = 0,
) -> None:
    """Track the camera of one RGB-D sequence and build its neural point map.

    Writes RUN/config.yaml and RUN/agent_<id>/: trajectory.tum (every frame), map.ply,
    state.pt (reload with `cpslam render` or `--resume`) and metrics.json. Ctrl-C stops the run
    and saves what exists.

    Examples:

      cpslam-agent --seq runs/data/room/agent_0 --standalone --out runs/room

      cpslam-agent --seq ../shared/data/7scenes-kitchen-0-299 --standalone --frames 0:100

      cpslam-agent --seq data/office0 --standalone --preset paper --device cuda
    """
    from cpslam.common.config.cli import config_or_exit
    from cpslam.common.datasets import DatasetError
    from cpslam.common.device import resolve_device
    from cpslam.common.logs import setup_logging
    from cpslam.common.rundir import create_run_dir

    setup_logging(max(verbose, 1))
    if not standalone:
        typer.echo("error: only --standalone is available in this version: the networked agent "
                   "(connecting to cpslam-server) is not built yet", err=True)
        raise typer.Exit(2)
    cfg = config_or_exit(preset, config_file, sets, device, seed)
    try:
        torch_device = resolve_device(cfg.run.device)
    except ValueError as err:
        typer.echo(f"error: {err}", err=True)
        raise typer.Exit(2) from None
    if resume is not None and not resume.is_file():
        typer.echo(f"error: --resume {resume}: no such file", err=True)
        raise typer.Exit(2)

    from cpslam.agent.standalone import open_for_config, run_standalone

    try:
        sequence = open_for_config(cfg, seq, fmt, frames)
    except DatasetError as err:
        typer.echo(f"error: {err}", err=True)
        raise typer.Exit(2) from None
    if cfg.run.num_threads:
        import torch

        torch.set_num_threads(cfg.run.num_threads)
    run_dir = out if out is not None else create_run_dir(cfg.run.out, cfg.run.name)
    run_dir.mkdir(parents=True, exist_ok=True)
    logger.info("agent %d: %s (%s, %d frames) on %s → %s", agent_id, seq, sequence.format,
                len(sequence), torch_device, run_dir)
    result = run_standalone(cfg, sequence, run_dir, torch_device, agent_id=agent_id,
                            resume=resume, show_progress=not no_progress)
    typer.echo(f"{result.frames_done}/{result.frames_total} frames in {result.wall_time_s:.1f} s "
               f"→ {result.agent_dir}")
    if result.interrupted:
        raise typer.Exit(130)


def main() -> None:
    app()


if __name__ == "__main__":
    main()

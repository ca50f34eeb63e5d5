"""`cpslam dataset synth`: render a synthetic RGB-D collection (no downloads needed)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer


def synth(
    out: Annotated[Path, typer.Option("--out", "-o", help="Output folder.")],
    scene: Annotated[str, typer.Option(
        help="room (one furnished room) or apartment (four rooms joined by doorways).")
    ] = "room",
    frames: Annotated[int, typer.Option(help="Frames per agent.", min=2)] = 300,
    agents: Annotated[int, typer.Option(
        help="Number of sequences (1-8); they start apart and share views.", min=1)] = 1,
    loop: Annotated[bool, typer.Option(
        "--loop", help="Closed trajectories that return to their start pose.")] = False,
    width: Annotated[int, typer.Option(help="Image width (fx = fy = 0.8 width).", min=8)
                     ] = 320,
    height: Annotated[int, typer.Option(help="Image height.", min=8)] = 240,
    seed: Annotated[int, typer.Option(
        help="Seed for furniture, textures, wobble and noise; same seed, same bytes.")] = 0,
    noise: Annotated[bool, typer.Option(
        "--noise", help="Kinect-like depth noise, holes at edges, max range 6 m.")] = False,
    fps: Annotated[float, typer.Option(help="Frame rate written to camera.yaml.")] = 30.0,
    overwrite: Annotated[bool, typer.Option(
        "--overwrite", help="Replace an earlier collection in the output folder.")] = False,
) -> None:
    """Render a synthetic RGB-D collection in the Replica layout, with ground truth.

    Writes OUT/agent_<i>/ (results/frame*.png, results/depth*.png, traj.txt, camera.yaml)
    and OUT/mesh.ply, OUT/scene.json. Motion: at most 1 cm and 1 degree per frame.

    Examples:

      cpslam dataset synth --scene apartment --agents 2 --out data/apt2

      cpslam dataset synth --scene room --loop --frames 300 --out runs/data/room

      cpslam dataset synth --frames 60 --width 160 --height 120 --noise --out data/noisy
    """
    from cpslam.tools.synth.writer import generate

    try:
        result = generate(out, scene=scene, agents=agents, frames=frames, width=width,
                          height=height, seed=seed, noise=noise, loop=loop, fps=fps,
                          overwrite=overwrite, show_progress=True)
    except (ValueError, FileExistsError) as e:
        typer.echo(f"error: {e}", err=True)
        raise typer.Exit(code=2) from e
    typer.echo(f"scene {scene} (seed {seed}), {agents} agent(s) x {frames} frames "
               f"at {width}x{height}")
    for folder in result.agent_dirs:
        typer.echo(f"  sequence: {folder}")
    typer.echo(f"  mesh:     {result.mesh_path}")
    typer.echo(f"  summary:  {result.scene_json}")
    typer.echo(f"render time {1000 * result.seconds_per_frame:.1f} ms per frame, "
               f"total {result.total_seconds:.1f} s; min camera clearance "
               f"{result.min_clearance:.2f} m")

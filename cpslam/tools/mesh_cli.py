"""The mesh of a finished run (`cpslam mesh RUN`; the report makes the same one).

TSDF fusion (`cpslam.tools.mesh.tsdf_mesh`, open3d ``VoxelBlockGrid``) of depth and colour
rendered (`cpslam.tools.render.render_views`) from the run's final map
(`cpslam.tools.runfolder.final_model`: the server's fused map with the main group's decoders,
or one agent's own map) at up to `max_views` poses spread evenly over the trajectories of the
agents the map covers. The mesh is in the map's frame (the group's, or the agent's first
camera).
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import typer

from cpslam.common.cli import JsonOpt, OverwriteOpt, check_output, fail, out_option

logger = logging.getLogger(__name__)

__all__ = ["mesh", "run_mesh"]

DEFAULT_VIEWS = 40
DEFAULT_VOXEL = 0.03


def run_mesh(run: Path, out: Path | None = None, max_views: int = DEFAULT_VIEWS,
             voxel_size: float = DEFAULT_VOXEL, device: str = "cpu",
             show_progress: bool = False) -> dict[str, Any]:
    """Write the run's mesh (default RUN/mesh.ply); returns what was made (path, frame,
    views, vertices, triangles, voxel size, seconds)."""
    from cpslam.common.logs import progress
    from cpslam.tools.mesh import tsdf_mesh, write_mesh
    from cpslam.tools.render import render_views
    from cpslam.tools.runfolder import final_model, trajectories

    t0 = time.perf_counter()
    run = Path(run)
    final = final_model(run, device)
    tracks = trajectories(run, final.members)
    poses = np.concatenate([t["global"][1] for t in tracks.values() if t["global"]]
                           or [np.empty((0, 4, 4))])
    if len(poses) == 0:
        raise ValueError(f"{run}: no trajectory of {final.frame} to render from")
    pick = np.linspace(0, len(poses) - 1, min(max_views, len(poses))).round().astype(int)
    poses = poses[pick]
    intrinsics = final.model.intrinsics
    views = render_views(final.model, poses)
    frames = ((rgb, depth, T) for (rgb, depth), T in zip(
        progress(views, total=len(poses), desc="mesh: render", disable=not show_progress),
        poses, strict=True))
    result = tsdf_mesh(frames, intrinsics, voxel_size=voxel_size,
                       min_observations=min(2, len(poses)))
    path = write_mesh(out or run / "mesh.ply", result)
    return {"path": str(path), "frame": final.frame, "views": len(poses),
            "vertices": len(result.vertices), "triangles": len(result.triangles),
            "voxel_size_m": voxel_size, "seconds": time.perf_counter() - t0}


def mesh(
    run: Annotated[Path, typer.Argument(help="Finished run folder (any kind).")],
    out: Annotated[Path | None, out_option("Mesh file (default: RUN/mesh.ply).")] = None,
    overwrite: OverwriteOpt = False,
    views: Annotated[int, typer.Option("--views", min=1, help="Most poses rendered, spread "
                                       "evenly over the trajectories.")] = DEFAULT_VIEWS,
    voxel_size: Annotated[float, typer.Option("--voxel-size", min=0.001,
                                              help="TSDF voxel edge, metres.")] = DEFAULT_VOXEL,
    device: Annotated[str, typer.Option("--device", help="auto, cpu, cuda or cuda:N "
                                        "(rendering).")] = "cpu",
    as_json: JsonOpt = False,
    no_progress: Annotated[bool, typer.Option("--no-progress", help="No progress bar.")
                           ] = False,
) -> None:
    """TSDF mesh of a run's final map, rendered at its trajectories' poses.

    The server's fused map (main group) for a collaborative run, the agent's own map for
    cpslam-agent --standalone --no-loops. The mesh is in the map's frame; cpslam report
    makes the same mesh and scores it against a synthetic scene's ground truth.

    Examples:

      cpslam mesh runs/demo

      cpslam mesh runs/room --views 80 --voxel-size 0.02 --out runs/room/mesh_fine.ply

      cpslam mesh runs/kitchen --json
    """
    import json

    from cpslam.common.device import resolve_device
    from cpslam.common.rundir import SCHEMA_VERSION

    target = out or run / "mesh.ply"
    check_output(target, overwrite)
    try:
        info = run_mesh(run, target, views, voxel_size, resolve_device(device),
                        show_progress=not (no_progress or as_json))
    except (FileNotFoundError, ValueError, KeyError) as err:
        fail(str(err))
    if as_json:
        typer.echo(json.dumps({"schema_version": SCHEMA_VERSION, **info}, indent=2))
    else:
        typer.echo(f"mesh of {info['frame']}: {info['vertices']} vertices, "
                   f"{info['triangles']} triangles from {info['views']} views → {info['path']}")

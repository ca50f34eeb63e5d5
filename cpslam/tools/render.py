"""Render depth and colour images from a saved neural point map: `cpslam render`.

The output folder is itself a sequence in the Replica layout (`results/`, `traj.txt`,
`camera.yaml`), so `cpslam dataset info`, the mesh builder and the depth-L1 metric read it like
any other data set.

The map lives in the agent's world, its first camera. Poses from elsewhere (a data set's ground
truth) live in another world; `relative_to_start` re-expresses them relative to their pose at
the run's first frame, which is where the agent's world sits in theirs.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import numpy as np
import typer

from cpslam.common.cli import OverwriteOpt, check_output, fail, out_option

if TYPE_CHECKING:
    from cpslam.common.camera import Intrinsics
    from cpslam.common.config import CpslamConfig
    from cpslam.common.field import Decoders, NeuralPointMap

logger = logging.getLogger(__name__)

STATE_FILE = "state.pt"


@dataclass
class RunModel:
    """What is needed to render a saved run: its config, map, decoders and camera."""

    config: CpslamConfig
    point_map: NeuralPointMap
    decoders: Decoders
    intrinsics: Intrinsics


def load_run_model(run: Path, agent_id: str = "0", device: str = "cpu") -> RunModel:
    """Rebuild the map and decoders of `run/agent_<id>/state.pt` using `run/config.yaml`
    (a networked agent writes its config as `run/agent_<id>/config.yaml`: used when the run
    has none at its top). Agent ids are strings (``--agent-id robot-2`` writes
    ``agent_robot-2/``)."""
    import torch

    from cpslam.common.camera import Intrinsics
    from cpslam.common.config import load_config_file
    from cpslam.common.field_config import field_spec

    agent_dir = run / f"agent_{agent_id}"
    config_path = run / "config.yaml"
    if not config_path.is_file() and (agent_dir / "config.yaml").is_file():
        config_path = agent_dir / "config.yaml"
    state_path = agent_dir / STATE_FILE
    for path in (config_path, state_path):
        if not path.is_file():
            raise FileNotFoundError(f"{path}: not found (is {run} a cpslam run folder?)")
    cfg = load_config_file(config_path)
    state = torch.load(state_path, map_location=device, weights_only=True)
    for key in ("point_map", "decoders", "intrinsics"):
        if key not in state:
            raise ValueError(f"{state_path}: missing {key!r}; not a cpslam agent state file")
    # The map's agent key is local to the agent process (always 0); the state sets it anyway.
    spec = field_spec(cfg.field)
    point_map = spec.point_map(0, device)
    point_map.load_state_dict(state["point_map"])
    decoders = spec.decoders(cfg.run.seed).to(device)
    decoders.load_state_dict(state["decoders"])
    decoders.eval()
    return RunModel(cfg, point_map, decoders, Intrinsics.from_dict(state["intrinsics"]))


def relative_to_start(stamps: np.ndarray, poses: np.ndarray, run_start: float | None,
                      max_dt: float = 0.02) -> np.ndarray:
    """``poses`` [N, 4, 4] re-expressed relative to the one at the run's first frame:
    ``inv(T_w_start) @ T_w_cam``, the camera poses in the agent's world (its first camera).

    ``run_start`` is the stamp of the run's first frame (its trajectory.tum); None takes the
    first pose. Raises ValueError when no pose lies within ``max_dt`` seconds of it.
    """
    if run_start is None:
        i = 0
    else:
        i = int(np.argmin(np.abs(stamps - run_start)))
        if abs(stamps[i] - run_start) > max_dt:
            raise ValueError(f"no pose within {max_dt} s of the run's first frame (stamp "
                             f"{run_start:.6f}; nearest {stamps[i]:.6f}): --relative needs the "
                             f"poses of the sequence the run processed")
    return np.linalg.inv(poses[i])[None] @ poses


def render_views(
    model: RunModel, poses: np.ndarray, intrinsics: Intrinsics | None = None, chunk: int = 2048
) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """Yield (rgb uint8 [H,W,3], depth float32 [H,W]) for each `T_world_cam` in `poses`."""
    import torch

    from cpslam.common.field import render_image
    from cpslam.common.field_config import field_spec

    intr = intrinsics or model.intrinsics
    f = model.config.field
    # Bin centres, no jitter: renders are deterministic.
    sampler = field_spec(f).sampler(perturb=False)
    for T_world_cam in poses:
        T = torch.as_tensor(T_world_cam, dtype=torch.float64, device=model.point_map.device)
        out = render_image(model.point_map, model.decoders, intr, T, sampler,
                           k=f.k_neighbors, radius=f.radius, chunk=chunk,
                           backend=f.neighbour_backend)
        rgb = (out["color"].clamp(0, 1) * 255 + 0.5).to(torch.uint8).cpu().numpy()
        yield rgb, out["depth"].float().cpu().numpy()


def write_renders(
    out: Path, views: Iterator[tuple[np.ndarray, np.ndarray]], poses: np.ndarray,
    intrinsics: Intrinsics, fps: float = 30.0, show_progress: bool = True,
) -> int:
    """Write views in the Replica layout; returns the number of frames written."""
    import yaml

    from cpslam.common.logs import progress
    from cpslam.tools.synth.writer import DEPTH_SCALE, write_frame

    results = out / "results"
    results.mkdir(parents=True, exist_ok=True)
    count = 0
    for i, (rgb, depth) in enumerate(progress(views, total=len(poses), desc="render",
                                              disable=not show_progress)):
        write_frame(results, i, rgb, depth)
        count += 1
    np.savetxt(out / "traj.txt", poses[:count].reshape(count, 16), fmt="%.9f")
    camera = {**intrinsics.to_dict(), "depth_scale": DEPTH_SCALE, "fps": fps}
    (out / "camera.yaml").write_text(yaml.safe_dump(camera, sort_keys=False))
    return count


def render(
    run: Annotated[Path, typer.Argument(help="Run folder (holds config.yaml and agent_<id>/).")],
    poses: Annotated[
        Path | None,
        typer.Option("--poses", help="Poses T_world_cam to render: a TUM file, a run folder or a "
                     "data set folder (its ground truth). Default: the run's own "
                     "agent_<id>/trajectory.tum."),
    ] = None,
    relative: Annotated[
        bool,
        typer.Option("--relative", help="Express the poses relative to their pose at the run's "
                     "first frame (matched by timestamp): ground truth is in the data set's "
                     "world, the map in the agent's (its first camera)."),
    ] = False,
    agent: Annotated[
        str, typer.Option("--agent", help="Which agent's map: the id of agent_<id>/ (e.g. 0 "
                          "or robot-2).")
    ] = "0",
    out: Annotated[Path | None, out_option("Output folder (default: RUN/agent_<id>/renders).")
                   ] = None,
    overwrite: OverwriteOpt = False,
    every: Annotated[int, typer.Option("--every", min=1, help="Render every N-th pose.")] = 1,
    scale: Annotated[
        float, typer.Option("--scale", min=0.05, max=4.0, help="Image size factor.")
    ] = 1.0,
    device: Annotated[str, typer.Option("--device", help="auto, cpu, cuda or cuda:N.")] = "auto",
) -> None:
    """Render depth and colour images from a saved map.

    The output is a sequence folder in the Replica layout (results/frame*.png, depth*.png,
    traj.txt, camera.yaml).

    Examples:

      cpslam render runs/room --every 10

      cpslam render runs/room --poses runs/data/room/agent_0 --relative --out runs/room/gt

      cpslam render runs/office --agent robot-2 --every 10

      cpslam render runs/room --every 5 --overwrite
    """
    from cpslam.common.device import resolve_device
    from cpslam.protocol import ProtocolError, keys
    from cpslam.tools.eval.source import load_trajectory

    target = out or run / f"agent_{agent}" / "renders"
    try:
        keys.check_id(agent, "--agent")
        check_output(target, overwrite)
        torch_device = resolve_device(device)
        model = load_run_model(run, agent, torch_device)
        own = run / f"agent_{agent}" / "trajectory.tum"
        trajectory = load_trajectory(poses or own)
        T_world_cam = trajectory.poses
        if relative:
            start = load_trajectory(own).stamps[0] if own.is_file() else None
            T_world_cam = relative_to_start(trajectory.stamps, T_world_cam, start)
    except (FileNotFoundError, ValueError, ProtocolError) as err:
        fail(str(err))
    T_world_cam = T_world_cam[::every]
    intrinsics = model.intrinsics if scale == 1.0 else model.intrinsics.scaled(scale)
    n = write_renders(target, render_views(model, T_world_cam, intrinsics), T_world_cam,
                      intrinsics)
    typer.echo(f"rendered {n} views at {intrinsics.width}x{intrinsics.height} → {target}")

"""Write a finalised back end into the run folder.

Layout (under ``run_dir``):

- ``trajectories/agent_<id>_local.tum``: the agent's corrected trajectory in its own frame;
- ``trajectories/agent_<id>_global.tum``: the same in its group's frame (its own frame when
  it never merged; metrics.json says which);
- ``fused_map.ply`` / ``fused_map.pt``: the main group's refined map (points and neural
  state); with several groups also ``fused_map_<group>.ply`` / ``.pt`` for each;
- ``decoders_<group>.pt``: final decoder weights of each group that has some;
- ``pose_graph.g2o``: the final pose graph;
- ``metrics.json``: groups, loops, merges, rounds, pose-graph errors, timings, bytes.

Every file is written atomically (`cpslam.common.durable`) and ``metrics.json`` last: its
presence marks a complete run (a driver that adds outputs of its own writes it itself with
`write_metrics`, after them).
"""

from __future__ import annotations

import logging
from pathlib import Path

import torch

from cpslam.common.durable import torch_save_atomic
from cpslam.common.ply import write_ply
from cpslam.common.rundir import SCHEMA_VERSION, write_json
from cpslam.common.trajectory import write_tum
from cpslam.server.result import FinalResult

__all__ = ["export_run", "write_metrics"]

logger = logging.getLogger(__name__)


def export_run(result: FinalResult, run_dir: str | Path, mark_complete: bool = True
               ) -> dict[str, Path]:
    """Write every output of `result` under `run_dir`, ``metrics.json`` last (not at all
    when not `mark_complete`); returns name -> path written."""
    run = Path(run_dir)
    traj_dir = run / "trajectories"
    traj_dir.mkdir(parents=True, exist_ok=True)
    written: dict[str, Path] = {}
    for a in result.agents:
        for kind, poses in (("local", a.T_own_cam), ("global", a.T_group_cam)):
            path = traj_dir / f"agent_{a.agent_id}_{kind}.tum"
            write_tum(path, a.stamps, poses)
            written[path.stem] = path
    for gid, point_map in result.maps.items():
        names = [f"fused_map_{gid}"] if len(result.maps) > 1 else []
        if gid == result.main_group:
            names.append("fused_map")
        for name in names:
            xyz = point_map.xyz_world().cpu().numpy()
            written[name + ".ply"] = write_ply(run / f"{name}.ply", xyz,
                                               point_map.color.cpu().numpy())
            point_map.save(run / f"{name}.pt")
            written[name + ".pt"] = run / f"{name}.pt"
    for gid, state in result.decoders.items():
        path = run / f"decoders_{gid}.pt"
        torch_save_atomic({k: torch.as_tensor(v) for k, v in state.items()}, path)
        written[path.name] = path
    if result.pose_graph is not None:
        result.pose_graph.export_g2o(run / "pose_graph.g2o")
        written["pose_graph.g2o"] = run / "pose_graph.g2o"
    if mark_complete:
        written["metrics.json"] = write_metrics(result, run)
    logger.info("exported %d files to %s", len(written), run)
    return written


def write_metrics(result: FinalResult, run_dir: str | Path) -> Path:
    """Write ``metrics.json``, the run's completion mark (atomically)."""
    return write_json(Path(run_dir) / "metrics.json",
                      {"schema_version": SCHEMA_VERSION, **result.metrics})

"""Reading a finished run folder of any kind: which agents it holds, their trajectories, the
sequences they ran on (for ground truth) and the final map to render from.

Kinds of folder, all read the same way:

- collaborative (`cpslam run`, `cpslam-agent --standalone` with loops, the daemons' shared
  ``--out``, `cpslam demo`): the server's ``metrics.json``, ``trajectories/agent_<id>_{local,
  global}.tum``, ``fused_map.pt`` with ``decoders_<group>.pt``, and ``agent_<id>/``;
- one agent alone (`cpslam-agent --standalone --no-loops`): ``agent_<id>/trajectory.tum``,
  ``state.pt`` and ``metrics.json``; its trajectory is both its local and its global one.

Each agent's ``metrics.json`` records the sequence it ran on (``sequence.path``); a demo's
``demo.json`` lists them too. Those are where ground truth is looked up.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from cpslam.tools.render import RunModel

logger = logging.getLogger(__name__)

__all__ = ["FinalModel", "agent_ids", "final_model", "ground_truth", "main_group",
           "parse_gt_options", "read_json", "read_tum", "recorded_sequences", "trajectories"]


def read_json(path: Path) -> dict | None:
    return json.loads(path.read_text()) if path.is_file() else None


def read_tum(path: Path) -> tuple[np.ndarray, np.ndarray] | None:
    from cpslam.common.trajectory import read_tum as read

    return read(path) if path.is_file() else None


def _sort_ids(ids: set[str]) -> list[str]:
    return sorted(ids, key=lambda a: (not a.isdigit(), int(a) if a.isdigit() else 0, a))


def agent_ids(run: Path) -> list[str]:
    """The agents of a run: those with a global trajectory, else those with an agent folder
    holding a trajectory (one agent alone)."""
    ids = {p.name[len("agent_"):-len("_global.tum")]
           for p in (run / "trajectories").glob("agent_*_global.tum")}
    if not ids:
        ids = {p.parent.name[len("agent_"):] for p in run.glob("agent_*/trajectory.tum")}
    return _sort_ids(ids)


def trajectories(run: Path, ids: list[str]) -> dict[str, dict[str, Any]]:
    """Per agent ``{"local", "global", "odometry"}``: (stamps, T [N, 4, 4]) or None. Without
    the server's trajectories/ (one agent alone) its own trajectory.tum stands for both."""
    out = {}
    for a in ids:
        own = {k: read_tum(run / "trajectories" / f"agent_{a}_{k}.tum")
               for k in ("local", "global", "odometry")}
        if own["global"] is None:
            alone = read_tum(run / f"agent_{a}" / "trajectory.tum")
            own["local"] = own["global"] = alone
        out[a] = own
    return out


def recorded_sequences(run: Path) -> dict[str, Path]:
    """Agent id → the sequence folder the run recorded for it (``agent_<id>/metrics.json``,
    else the demo's ``demo.json``), where that folder still exists."""
    found: dict[str, Path] = {}
    demo = read_json(run / "demo.json") or {}
    for a, path in demo.get("sequences", {}).items():
        found[str(a)] = Path(path)
    for metrics_path in run.glob("agent_*/metrics.json"):
        try:
            seq = (read_json(metrics_path) or {}).get("sequence") or {}
        except json.JSONDecodeError:
            logger.warning("%s: not JSON; its sequence is not known", metrics_path)
            continue
        if seq.get("path"):
            found[metrics_path.parent.name[len("agent_"):]] = Path(seq["path"])
    missing = {a: p for a, p in found.items() if not p.exists()}
    for a, p in missing.items():
        logger.info("agent %s: recorded sequence %s no longer exists", a, p)
    return {a: p for a, p in found.items() if a not in missing}


def ground_truth(run: Path) -> dict[str, Path] | None:
    """The recorded sequences when every agent of the run has one with ground-truth poses,
    else None (a run on data without ground truth gets no report of its own)."""
    from cpslam.tools.eval import load_trajectory

    ids, found = agent_ids(run), recorded_sequences(run)
    if not ids or any(a not in found for a in ids):
        return None
    for a in ids:
        try:
            load_trajectory(found[a])
        except (FileNotFoundError, ValueError) as err:
            logger.info("agent %s: no ground truth (%s)", a, err)
            return None
    return {a: found[a] for a in ids}


def parse_gt_options(values: list[str], ids: list[str]) -> dict[str, Path]:
    """``--gt`` values: ``ID=PATH`` names the agent; a plain ``PATH`` takes the next agent in
    order. Raises ValueError on an unknown agent id or more paths than agents."""
    out: dict[str, Path] = {}
    plain = iter(ids)
    for value in values:
        aid, sep, path = value.partition("=")
        if sep and aid in ids:
            out[aid] = Path(path)
        elif sep and not Path(value).exists():
            raise ValueError(f"--gt {value}: agent {aid!r} is not in this run (agents: "
                             f"{', '.join(ids) or 'none'})")
        else:
            try:
                out[next(plain)] = Path(value)
            except StopIteration:
                raise ValueError(f"--gt {value}: more ground truths than the run's "
                                 f"{len(ids)} agent(s)") from None
    return out


def main_group(metrics: dict) -> str | None:
    """The group the server wrote as fused_map.* (``main_group`` in its metrics; for older
    run folders, the server's rule: most members, then most points)."""
    if "main_group" in metrics:
        return metrics["main_group"]
    points = {r.get("group"): r.get("points", 0) for r in metrics.get("refinement", [])}
    groups = metrics.get("groups", [])
    if not groups:
        return None
    best = max(groups, key=lambda g: (len(g.get("members", [])), points.get(g["group_id"], 0)))
    return best["group_id"]


@dataclass
class FinalModel:
    """The run's final map with its decoders and camera, the agents it covers and the frame
    its poses are in (``group <id>`` or ``agent <id>``)."""

    model: RunModel
    members: list[str]
    frame: str


def final_model(run: Path, device: str = "cpu") -> FinalModel:
    """The server's fused map of its main group, or (one agent alone) the agent's own map."""
    run = Path(run)
    if (run / "fused_map.pt").is_file():
        return _fused_model(run, device)
    from cpslam.tools.render import load_run_model

    ids = [a for a in agent_ids(run) if (run / f"agent_{a}" / "state.pt").is_file()]
    if not ids:
        raise FileNotFoundError(f"{run}: neither fused_map.pt nor agent_<id>/state.pt (is it "
                                "a finished cpslam run folder?)")
    return FinalModel(load_run_model(run, ids[0], device), [ids[0]], f"agent {ids[0]}")


def _fused_model(run: Path, device: str) -> FinalModel:
    import torch

    from cpslam.common.camera import Intrinsics
    from cpslam.common.config import load_config_file
    from cpslam.common.field import NeuralPointMap
    from cpslam.common.field_config import field_spec
    from cpslam.tools.render import STATE_FILE, RunModel

    metrics = read_json(run / "metrics.json") or {}
    gid = main_group(metrics)
    members = next((g["members"] for g in metrics.get("groups", []) if g["group_id"] == gid), [])
    decoder_path = run / f"decoders_{gid}.pt"
    for path in (run / "config.yaml", decoder_path):
        if not path.is_file():
            raise FileNotFoundError(f"{path}: not found")
    cfg = load_config_file(run / "config.yaml")
    point_map = NeuralPointMap.load(run / "fused_map.pt").to(device)
    decoders = field_spec(cfg.field).decoders(cfg.run.seed)
    decoders.load_state_dict(torch.load(decoder_path, map_location="cpu", weights_only=True))
    decoders.to(device).eval()
    state = next((run / f"agent_{m}" / STATE_FILE for m in members
                  if (run / f"agent_{m}" / STATE_FILE).is_file()), None)
    if state is None:
        raise FileNotFoundError(f"{run}: no agent_<id>/{STATE_FILE} of group {gid} (camera)")
    intrinsics = Intrinsics.from_dict(torch.load(state, map_location="cpu",
                                                 weights_only=True)["intrinsics"])
    return FinalModel(RunModel(cfg, point_map, decoders, intrinsics), list(members),
                      f"group {gid}")

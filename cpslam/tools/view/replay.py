"""Replay a finished run folder into Rerun: `cpslam view RUN`.

Reads what `cpslam run`, `cpslam-agent --standalone`, the daemons' server and `cpslam demo`
write (docs/outputs): ``trajectories/agent_<a>_global.tum``, ``agent_<a>/state.pt``
(keyframe poses and images), ``fused_map[_<group>].pt``, ``mesh.ply``, ``pose_graph.g2o``,
``metrics.json`` (loops, merges, federated rounds) and, for ground truth, the sequences given
with ``--gt`` or recorded in the demo's ``demo.json``. Whatever is missing is skipped (logged);
a folder without any trajectory is refused.

    counts = replay_run(Path("runs/apt"), Scene(open_recording("apt", save=Path("apt.rrd"))))
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import numpy as np

from cpslam.common.camera import Intrinsics
from cpslam.tools.view.sink import EDGE, Scene, agent_colour

logger = logging.getLogger(__name__)

__all__ = ["agent_ids", "demo_sequences", "replay_run"]


def replay_run(run: Path, scene: Scene, sequences: dict[str, Path] | None = None) -> dict:
    """Log everything the run folder holds; returns what was logged (counts per entity kind,
    per agent) for the caller's summary. `sequences` maps agent ids to ground truth (sequence
    folder or TUM file); by default the demo's record of them, if any."""
    from cpslam.common.trajectory import read_tum

    run = Path(run)
    ids = agent_ids(run)
    if not ids:
        raise FileNotFoundError(f"{run}: no trajectories/agent_<id>_global.tum nor "
                                "agent_<id>/trajectory.tum (is this a finished run folder?)")
    metrics = _read_json(run / "metrics.json") or {}
    index = _agent_index(ids, metrics)
    sequences = sequences if sequences is not None else demo_sequences(run)
    counts: dict[str, Any] = {"agents": {}}
    trajectories = {a: read_tum(_trajectory_path(run, a)) for a in ids}
    graph = _read_g2o(run / "pose_graph.g2o")
    kf_poses = {key: T for key, T in graph["kf_poses"].items()}
    for a in ids:
        stamps, poses = trajectories[a]
        scene.trajectory(a, index[a], poses[:, :3, 3])
        for t, T in zip(stamps, poses, strict=True):
            scene.at(stamp_s=t)
            scene.camera(a, T)
        kfs = _log_keyframes(scene, run / f"agent_{a}" / "state.pt", a, index[a], kf_poses)
        counts["agents"][a] = {"frames": len(stamps), "keyframes": kfs}
    gt = _log_ground_truth(scene, ids, index, trajectories, metrics, sequences or {})
    for a in ids:
        counts["agents"][a]["ground_truth"] = a in gt
    points = _log_points(scene, run, ids, index)
    for a in ids:
        counts["agents"][a]["points"] = points.get(a, 0)
    counts["mesh"] = _log_mesh(scene, run / "mesh.ply")
    counts["pose_graph_edges"] = _log_edges(scene, graph)
    counts["loops"] = _log_loops(scene, metrics.get("loops", {}).get("list", []), kf_poses)
    counts["events"] = _log_events(scene, metrics)
    return counts


def demo_sequences(run: Path) -> dict[str, Path]:
    """Agent id -> sequence folder, as `cpslam demo` recorded them in RUN/demo.json."""
    info = _read_json(Path(run) / "demo.json") or {}
    return {str(a): Path(p) for a, p in info.get("sequences", {}).items()}


def _log_keyframes(scene: Scene, state_path: Path, agent: str, index: int,
                   kf_poses: dict[tuple[str, int], np.ndarray]) -> int:
    """Frusta with thumbnails from the agent's saved state; poses from the final pose graph
    where it has them (the state's are the agent's last view). Without a state: the pose
    graph's keyframes, as bare poses."""
    import cv2

    own = {key: T for key, T in kf_poses.items() if key[0] == agent}
    if not state_path.is_file():
        for (_, kf), T in sorted(own.items()):
            scene.keyframe(agent, index, kf, T, None)
        return len(own)
    import torch

    state = torch.load(state_path, map_location="cpu", weights_only=True)
    intr = Intrinsics(**state["intrinsics"])
    keyframes = state["keyframes"]["keyframes"]
    for kf in keyframes:
        kf_id = int(kf["kf_id"])
        T = own.get((agent, kf_id), kf["T_world_cam"].double().numpy())
        rgb = None
        png = kf.get("rgb_png")
        if png is not None and len(png):
            bgr = cv2.imdecode(png.numpy(), cv2.IMREAD_COLOR)
            rgb = None if bgr is None else cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
        scene.keyframe(agent, index, kf_id, T, intr, rgb)
    return len(keyframes)


def _log_ground_truth(scene: Scene, ids: list[str], index: dict[str, int],
                      trajectories: dict, metrics: dict, sequences: dict[str, Path]) -> set[str]:
    """``world/agents/<a>/ground_truth`` in the estimate's frame: one se3 alignment per group
    (fitted to all its members together, as the joint ATE is), so a misaligned member shows."""
    from cpslam.tools.eval import joint_ate, load_trajectory

    have = [a for a in ids if a in sequences]
    groups: dict[str, list[str]] = {}
    for a in have:
        groups.setdefault(metrics.get("agents", {}).get(a, {}).get("group", a), []).append(a)
    done: set[str] = set()
    for members in groups.values():
        try:
            gts = {a: load_trajectory(sequences[a]) for a in members}
            joint = joint_ate([((gts[a].stamps, gts[a].poses), trajectories[a])
                               for a in members], align="se3")
        except (FileNotFoundError, ValueError) as err:
            logger.warning("no ground truth for agents %s: %s", ", ".join(members), err)
            continue
        T_est_gt = np.linalg.inv(joint.overall.T_gt_est)
        for a in members:
            xyz = gts[a].poses[:, :3, 3] @ T_est_gt[:3, :3].T + T_est_gt[:3, 3]
            scene.trajectory(a, index[a], xyz, kind="ground_truth")
            done.add(a)
    return done


def _log_points(scene: Scene, run: Path, ids: list[str], index: dict[str, int]) -> dict:
    """Each agent's points of the final fused map(s) in their colour, and ``world/map/
    by_agent`` (all points, coloured by agent). Several groups: ``fused_map_<g>.pt`` each."""
    from cpslam.common.field import NeuralPointMap

    files = sorted(run.glob("fused_map_*.pt")) or ([run / "fused_map.pt"]
                                                  if (run / "fused_map.pt").is_file() else [])
    maps = [(NeuralPointMap.load(path), None) for path in files] or _agent_maps(run, ids, index)
    if not maps:
        logger.warning("%s: no fused_map*.pt nor agent states, no points", run)
        return {}
    xyz_all, colour_all, agent_all = [], [], []
    for pmap, owner in maps:
        xyz_all.append(pmap.xyz_world().numpy())
        colour_all.append(pmap.color.numpy().astype(np.uint8))
        agents = pmap.agent_id.numpy()
        agent_all.append(agents if owner is None else np.full_like(agents, owner))
    xyz, colours, agents = (np.concatenate(x) for x in (xyz_all, colour_all, agent_all))
    counts = {}
    by_index = {i: a for a, i in index.items()}
    for i in np.unique(agents):
        name = by_index.get(int(i), f"index_{int(i)}")
        mask = agents == i
        scene.points(f"world/agents/{name}/points", xyz[mask], colours[mask])
        counts[name] = int(mask.sum())
    scene.points("world/map/by_agent", xyz, np.stack([agent_colour(i) for i in agents])
                 if len(agents) else None)
    return counts


def _agent_maps(run: Path, ids: list[str], index: dict[str, int]) -> list:
    """(map, agent index) of each agent's own state.pt (a run without a server), in the
    agent's own world."""
    import torch

    from cpslam.common.field import NeuralPointMap

    maps = []
    for a in ids:
        path = run / f"agent_{a}" / "state.pt"
        if path.is_file():
            state = torch.load(path, map_location="cpu", weights_only=True)["point_map"]
            pmap = NeuralPointMap(feature_dim=1, cell_size=1.0)
            pmap.load_state_dict(state, source=str(path))
            maps.append((pmap, index[a]))
    return maps


def _log_mesh(scene: Scene, path: Path) -> int:
    """``world/mesh`` from RUN/mesh.ply (written by the report); returns its triangle count."""
    if not path.is_file():
        return 0
    import open3d as o3d

    mesh = o3d.io.read_triangle_mesh(str(path))
    triangles = np.asarray(mesh.triangles)
    if not len(triangles):
        return 0
    colours = (np.clip(np.asarray(mesh.vertex_colors), 0, 1) * 255).astype(np.uint8) \
        if mesh.has_vertex_colors() else None
    scene.mesh(np.asarray(mesh.vertices), triangles, colours)
    return len(triangles)


def _log_edges(scene: Scene, graph: dict) -> int:
    """``world/pose_graph/edges``: every edge of the final pose graph."""
    edges = graph["edges"]
    if not edges:
        return 0
    xyz = graph["xyz"]
    a, b = np.array(edges).T
    scene.segments("world/pose_graph/edges", xyz[a], xyz[b], EDGE)
    return len(edges)


def _log_loops(scene: Scene, loops: list[dict], kf_poses: dict) -> dict[str, int]:
    """Verified loops whose two keyframes have a pose, accepted and rejected apart."""
    starts, ends, accepted, labels = [], [], [], []
    for lp in loops:
        a = kf_poses.get((str(lp.get("agent_a")), int(lp.get("kf_a", -1))))
        b = kf_poses.get((str(lp.get("agent_b")), int(lp.get("kf_b", -1))))
        if a is None or b is None:
            continue
        starts.append(a[:3, 3])
        ends.append(b[:3, 3])
        accepted.append(bool(lp.get("accepted")))
        why = "" if lp.get("accepted") else f" ({lp.get('reason', 'rejected')})"
        labels.append(f"{float(lp.get('score', 0)):.2f}{why}")
    scene.loops(np.array(starts).reshape(-1, 3), np.array(ends).reshape(-1, 3),
                np.array(accepted, dtype=bool), labels)
    return {"accepted": sum(accepted), "rejected": len(accepted) - sum(accepted),
            "without_pose": len(loops) - len(accepted)}


def _log_events(scene: Scene, metrics: dict) -> int:
    """Merges, federated rounds and loops on the `run_time` timeline (server seconds)."""
    events = []
    for m in metrics.get("merges", []):
        events.append((m.get("time", 0.0), "merges", "group {} merged: {}".format(
            m.get("group"), ", ".join(map(str, m.get("members", []))))))
    for r in metrics.get("rounds", {}).get("list", []):
        events.append((r.get("time", 0.0), "rounds", f"group {r.get('group')} federated "
                       f"round {r.get('round')} closed"))
    for lp in metrics.get("loops", {}).get("list", []):
        verdict = "accepted" if lp.get("accepted") else "rejected"
        events.append((lp.get("stamp", 0.0), "loops", f"loop {lp.get('agent_a')}:"
                       f"{lp.get('kf_a')} - {lp.get('agent_b')}:{lp.get('kf_b')} {verdict}, "
                       f"score {float(lp.get('score', 0)):.2f}"))
    for t, kind, text in sorted(events, key=lambda e: float(e[0] or 0.0)):
        scene.at(run_s=float(t or 0.0))
        scene.event(kind, text)
    return len(events)


def _read_g2o(path: Path) -> dict:
    """Vertex positions, edges and keyframe poses by (agent, kf) of a pose_graph.g2o."""
    from cpslam.common.geometry import pose_from_tq

    out: dict[str, Any] = {"xyz": np.zeros((0, 3)), "edges": [], "kf_poses": {}}
    if not path.is_file():
        return out
    poses: dict[int, np.ndarray] = {}
    names: dict[int, tuple[str, str, int]] = {}
    for line in path.read_text().splitlines():
        parts = line.split()
        if line.startswith("# NODE") and len(parts) == 6:
            names[int(parts[2])] = (parts[3], parts[4], int(parts[5]))
        elif parts and parts[0] == "VERTEX_SE3:QUAT":
            values = np.array(parts[2:9], dtype=np.float64)
            poses[int(parts[1])] = pose_from_tq(values[:3], values[3:])
        elif parts and parts[0] == "EDGE_SE3:QUAT":
            out["edges"].append((int(parts[1]), int(parts[2])))
    if poses:
        xyz = np.zeros((max(poses) + 1, 3))
        for i, T in poses.items():
            xyz[i] = T[:3, 3]
        out["xyz"] = xyz
    out["edges"] = [(a, b) for a, b in out["edges"] if a in poses and b in poses]
    out["kf_poses"] = {(agent, idx): poses[i] for i, (agent, kind, idx) in names.items()
                       if kind == "kf" and i in poses}
    return out


def agent_ids(run: Path) -> list[str]:
    """Ids of the agents with a trajectory, numbers first: the server's global ones in
    RUN/trajectories/, else the agents' own (``cpslam-agent --standalone --no-loops``)."""
    suffix = "_global.tum"
    names = [p.name[len("agent_"):-len(suffix)]
             for p in (Path(run) / "trajectories").glob(f"agent_*{suffix}")]
    if not names:
        names = [p.parent.name[len("agent_"):]
                 for p in Path(run).glob("agent_*/trajectory.tum")]
    return sorted(names, key=lambda a: (not a.isdigit(), int(a) if a.isdigit() else 0, a))


def _trajectory_path(run: Path, agent: str) -> Path:
    path = run / "trajectories" / f"agent_{agent}_global.tum"
    return path if path.is_file() else run / f"agent_{agent}" / "trajectory.tum"


def _agent_index(ids: list[str], metrics: dict) -> dict[str, int]:
    """The agents' numbers in the fused map (metrics.json; older folders: id order)."""
    info = metrics.get("agents", {})
    if all("index" in info.get(a, {}) for a in ids):
        return {a: int(info[a]["index"]) for a in ids}
    return {a: i for i, a in enumerate(ids)}


def _read_json(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text())
    except (FileNotFoundError, json.JSONDecodeError):
        return None

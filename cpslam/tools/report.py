"""The end-of-run report of a collaborative run folder: tables, peak memory, plots and mesh.

Works on any folder the server wrote (`cpslam demo`, `cpslam-server`, `cpslam run`): it reads
``metrics.json``, ``trajectories/agent_<id>_{local,global}.tum``, ``agent_<id>/metrics.json``,
``fused_map.pt`` with ``decoders_<group>.pt`` and ``config.yaml``; ground truth comes from the
agents' sequence folders (evaluation only).

    report = build_report(run, {"0": seq0, "1": seq1})
    print_report(report)

ATE (metres, position RMSE): *local* is each agent's corrected trajectory in its own frame,
origin-aligned (the paper's protocol); *global* is every agent's trajectory in its group
frame under ONE se3 alignment fitted to all agents together (per agent: its share of that
joint fit), so an agent whose frame was never aligned with the others shows a large value.

Mesh: TSDF fusion (`cpslam.tools.mesh.tsdf_mesh`, open3d ``VoxelBlockGrid``) of depth and
colour rendered (`cpslam.tools.render.render_views`) from the server's final fused map with
the main group's decoders, at the global poses of the group's agents.
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path
from typing import Any

import numpy as np

logger = logging.getLogger(__name__)

__all__ = ["build_report", "fused_mesh", "main_group", "print_report", "write_plots"]

PLOTS = ("trajectories_global.png", "trajectories_local.png")


def build_report(run: Path, sequences: dict[str, Path] | None = None, mesh: bool = True,
                 max_views: int = 40, show_progress: bool = False,
                 process: str = "report") -> dict[str, Any]:
    """Numbers, plots (RUN/plots/) and mesh (RUN/mesh.ply) of a finished run; writes
    RUN/report.json and returns its content.

    Besides the table: ``traffic`` (the server's messages, bytes and bytes/s per agent,
    direction and topic, and per group decoder key) and ``memory_mb`` (peak resident memory
    of the server, of each agent and of this process, named `process`)."""
    run = Path(run)
    metrics = _read_json(run / "metrics.json")
    if metrics is None:
        raise FileNotFoundError(f"{run}/metrics.json: not found (did the server finalise?)")
    ids = _agent_ids(run)
    report: dict[str, Any] = {"run": str(run), "agents": {}, "all": {}, "notes": []}
    memory: dict[str, float | None] = {"server": metrics.get("process", {}).get("peak_rss_mb")}
    est = {a: {k: _read_tum(run / "trajectories" / f"agent_{a}_{k}.tum")
               for k in ("local", "global")} for a in ids}
    loops = metrics.get("loops", {})
    merges = metrics.get("merges", [])
    per_agent_bus = metrics.get("bus", {}).get("per_agent", {})
    for a in ids:
        info = metrics.get("agents", {}).get(a, {})
        own = _read_json(run / f"agent_{a}" / "metrics.json") or {}
        involved = [lp for lp in loops.get("list", []) if a in (lp.get("agent_a"),
                                                                lp.get("agent_b"))]
        bus = per_agent_bus.get(a, {})
        memory[f"agent_{a}"] = own.get("peak_cpu_memory_mb")
        report["agents"][a] = {
            "frames": len(est[a]["global"][0]) if est[a]["global"] else 0,
            "group": info.get("group"), "merged": bool(info.get("merged")),
            "merged_at_s": next((m["time"] for m in merges if a in m.get("members", [])), None),
            "loops_verified": len(involved),
            "loops_accepted": sum(bool(lp.get("accepted")) for lp in involved),
            "points": own.get("points"),
            "sent_bytes": _sent_bytes(own, bus, info),
            "received_bytes": bus.get("to_agent_bytes"),
        }
    groups = metrics.get("groups", [])
    main = main_group(metrics)
    fused = {r.get("group"): r.get("points") for r in metrics.get("refinement", [])}
    report["all"] = {
        "groups": len(groups), "main_group": main,
        "loops_found": loops.get("found", 0), "loops_accepted": loops.get("accepted", 0),
        "loops_rejected": loops.get("rejected", 0),
        "merge_times_s": [m["time"] for m in merges],
        "fused_points": fused.get(main),
        "sent_bytes": _total(r["sent_bytes"] for r in report["agents"].values()),
        "received_bytes": _total(r["received_bytes"] for r in report["agents"].values()),
    }
    report["traffic"] = _traffic(metrics)
    results = _evaluate(report, est, sequences or {})
    if results:
        report["plots"] = [str(p) for p in write_plots(run / "plots", *results)]
    if mesh:
        try:
            report["mesh"] = fused_mesh(run, max_views=max_views, show_progress=show_progress)
        except (FileNotFoundError, ValueError, KeyError) as err:
            report["mesh"] = {"skipped": str(err)}
            report["notes"].append(f"mesh skipped: {err}")
    from cpslam.common.rundir import peak_rss_mb, write_json

    memory[process] = peak_rss_mb()  # after the mesh: it is what this process costs most
    report["memory_mb"] = memory
    write_json(run / "report.json", report)
    return report


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


def write_plots(folder: Path, joint: Any, local: dict[str, Any]) -> list[Path]:
    """Top views against ground truth and error over time, one colour per agent: the global
    trajectories under their joint alignment, and each local one origin-aligned."""
    from cpslam.tools.eval.plot import plot_ate

    ids = list(local)
    return [
        plot_ate(joint.parts, folder / PLOTS[0], labels=[f"agent {a}" for a in ids],
                 title=f"global trajectories (one se3 alignment for all), joint RMSE "
                       f"{100 * joint.overall.rmse:.1f} cm"),
        plot_ate([local[a] for a in ids], folder / PLOTS[1], labels=[f"agent {a}" for a in ids],
                 title="local trajectories (each agent's own frame, origin-aligned)"),
    ]


def fused_mesh(run: Path, max_views: int = 40, voxel_size: float = 0.03,
               show_progress: bool = False) -> dict[str, Any]:
    """TSDF mesh of the fused map rendered at its agents' global poses → RUN/mesh.ply."""
    import torch

    from cpslam.common.camera import Intrinsics
    from cpslam.common.config import load_config_file
    from cpslam.common.field import NeuralPointMap
    from cpslam.common.field_config import field_spec
    from cpslam.common.logs import progress
    from cpslam.tools.mesh import tsdf_mesh, write_mesh
    from cpslam.tools.render import STATE_FILE, RunModel, render_views

    t0 = time.perf_counter()
    metrics = _read_json(run / "metrics.json") or {}
    gid = main_group(metrics)
    members = next((g["members"] for g in metrics.get("groups", []) if g["group_id"] == gid), [])
    decoder_path = run / f"decoders_{gid}.pt"
    for path in (run / "config.yaml", run / "fused_map.pt", decoder_path):
        if not path.is_file():
            raise FileNotFoundError(f"{path}: not found")
    cfg = load_config_file(run / "config.yaml")
    point_map = NeuralPointMap.load(run / "fused_map.pt")
    decoders = field_spec(cfg.field).decoders(cfg.run.seed)
    decoders.load_state_dict(torch.load(decoder_path, map_location="cpu", weights_only=True))
    decoders.eval()
    state = next((run / f"agent_{m}" / STATE_FILE for m in members
                  if (run / f"agent_{m}" / STATE_FILE).is_file()), None)
    if state is None:
        raise FileNotFoundError(f"{run}: no agent_<id>/{STATE_FILE} of group {gid} (camera)")
    intrinsics = Intrinsics.from_dict(torch.load(state, map_location="cpu",
                                                 weights_only=True)["intrinsics"])
    tracks = [_read_tum(run / "trajectories" / f"agent_{m}_global.tum") for m in members]
    poses = np.concatenate([t[1] for t in tracks if t is not None] or [np.empty((0, 4, 4))])
    if len(poses) == 0:
        raise ValueError(f"{run}: no global trajectory of group {gid} to render from")
    poses = poses[np.linspace(0, len(poses) - 1, min(max_views, len(poses))).round().astype(int)]
    model = RunModel(cfg, point_map, decoders, intrinsics)
    views = render_views(model, poses)
    frames = ((rgb, depth, T) for (rgb, depth), T in zip(
        progress(views, total=len(poses), desc="mesh: render", disable=not show_progress),
        poses, strict=True))
    mesh = tsdf_mesh(frames, intrinsics, voxel_size=voxel_size,
                     min_observations=min(2, len(poses)))
    path = write_mesh(run / "mesh.ply", mesh)
    return {"path": str(path), "group": gid, "views": len(poses),
            "vertices": len(mesh.vertices), "triangles": len(mesh.triangles),
            "voxel_size_m": voxel_size, "seconds": time.perf_counter() - t0}


def print_report(report: dict[str, Any], console: Any = None, title: str | None = None) -> None:
    """The table (one row per agent and one for all) and notes."""
    from rich import box
    from rich.console import Console
    from rich.table import Table

    console = console or Console()
    table = Table(box=box.SIMPLE_HEAD, pad_edge=False, padding=(0, 1, 0, 0),
                  title=title or f"cpslam → {report['run']}",
                  caption="ATE in cm (local: own frame, origin-aligned; global: one se3 "
                          "alignment for all agents); loops accepted/verified (all: /found); "
                          "merge: s since server start; sent/recv: MB by / to the agent")
    for col in ("agent", "frames", "group", "ATE loc", "ATE glob", "loops", "merge",
                "points", "sent", "recv"):
        table.add_column(col, justify="left" if col in ("agent", "group") else "right",
                         no_wrap=True)
    for a, r in report["agents"].items():
        table.add_row(a, str(r["frames"]), str(r["group"]), _cm(r.get("local_ate_m")),
                      _cm(r.get("global_ate_m")), f"{r['loops_accepted']}/{r['loops_verified']}",
                      _num(r["merged_at_s"], "{:.1f}"), _num(r["points"], "{:d}"),
                      _mb(r["sent_bytes"]), _mb(r["received_bytes"]))
    t = report["all"]
    table.add_section()
    table.add_row("all", str(sum(r["frames"] for r in report["agents"].values())),
                  "", "", _cm(t.get("joint_ate_m")),
                  f"{t['loops_accepted']}/{t['loops_found']}",
                  ", ".join(f"{s:.1f}" for s in t["merge_times_s"]) or "none",
                  _num(t["fused_points"], "{:d}"), _mb(t["sent_bytes"]),
                  _mb(t["received_bytes"]))
    console.print(table)
    console.print(f"{t['groups']} group(s) at the end; fused map of group {t['main_group']}: "
                  f"{_num(t['fused_points'], '{:d}')} points")
    if report.get("traffic", {}).get("agents"):
        console.print(_traffic_table(report["traffic"]))
    memory = report.get("memory_mb", {})
    if memory:
        console.print("peak memory (MB): " + ", ".join(
            f"{name.replace('_', ' ')} {_num(mb, '{:.0f}')}" for name, mb in memory.items()))
    for note in report.get("notes", []):
        console.print(f"note: {note}")


def _traffic(metrics: dict) -> dict[str, Any]:
    """Per agent and direction: {topic: {messages, bytes, bytes_per_s}}; per group the
    decoders published; the server's uptime the rates are over."""
    bus = metrics.get("bus", {})
    agents = {a: {d: dict(entry.get(d, {})) for d in ("from_agent", "to_agent")}
              for a, entry in bus.get("per_agent", {}).items()}
    return {"agents": agents, "groups": bus.get("per_group", {}),
            "seconds": metrics.get("process", {}).get("uptime_s")}


def _traffic_table(traffic: dict[str, Any]) -> Any:
    from rich import box
    from rich.table import Table

    table = Table(box=box.SIMPLE_HEAD, pad_edge=False, padding=(0, 1, 0, 0),
                  title="traffic per agent and key expression (server's counters)",
                  caption="to server: agent/<id>/<topic> (image: keyframe image replies); "
                          "from server: server/agent/<id>/<topic>, image requests, every "
                          "group's decoder; kB/s over the server's uptime")
    for col in ("agent", "direction", "topic", "messages", "MB", "kB/s"):
        table.add_column(col, justify="left" if col in ("agent", "direction", "topic")
                         else "right", no_wrap=True)
    for a, entry in traffic["agents"].items():
        for direction, label in (("from_agent", "to server"), ("to_agent", "from server")):
            for topic, cell in sorted(entry.get(direction, {}).items()):
                rate = cell.get("bytes_per_s")
                table.add_row(a, label, topic, str(cell.get("messages", 0)),
                              _mb(cell.get("bytes")), _num(rate and rate / 1e3, "{:.2f}"))
    if traffic.get("groups"):
        table.add_section()
        for g, cell in traffic["groups"].items():
            rate = cell.get("bytes_per_s")
            table.add_row(f"group {g}", "published", "decoder", str(cell.get("messages", 0)),
                          _mb(cell.get("bytes")), _num(rate and rate / 1e3, "{:.2f}"))
    return table


def _evaluate(report: dict, est: dict, sequences: dict[str, Path]) -> tuple | None:
    """Fill the ATE fields; returns (joint result, local results) for the plots, or None
    when an agent has no ground truth or no trajectory."""
    from cpslam.tools.eval import evaluate_ate, joint_ate, load_trajectory

    ids = list(report["agents"])
    if not ids or any(a not in sequences or not est[a]["global"] for a in ids):
        report["notes"].append("no ATE: an agent lacks ground truth or a global trajectory")
        return None
    try:
        gts = {a: load_trajectory(sequences[a]) for a in ids}
        gt = {a: (g.stamps, g.poses) for a, g in gts.items()}
        joint = joint_ate([(gt[a], est[a]["global"]) for a in ids], align="se3")
        local = {a: evaluate_ate(*gt[a], *(est[a]["local"] or est[a]["global"]),
                                 align="origin") for a in ids}
    except (FileNotFoundError, ValueError) as err:
        report["notes"].append(f"no ATE: {err}")
        return None
    for a, part in zip(ids, joint.parts, strict=True):
        report["agents"][a]["global_ate_m"] = float(part.rmse)
        report["agents"][a]["local_ate_m"] = float(local[a].rmse)
    report["all"]["joint_ate_m"] = float(joint.overall.rmse)
    return joint, local


def _sent_bytes(own: dict, bus: dict, info: dict) -> int | None:
    """What the agent sent: its own bus counters, else what the server received from it."""
    sent = own.get("bus", {}).get("sent")
    if sent:
        return int(sum(row.get("bytes", 0) for row in sent.values()))
    value = bus.get("from_agent_bytes", info.get("bytes"))
    return None if value is None else int(value)


def _total(values: Any) -> int | None:
    known = [v for v in values if v is not None]
    return sum(known) if known else None


def _agent_ids(run: Path) -> list[str]:
    ids = {p.name[len("agent_"):-len("_global.tum")]
           for p in (run / "trajectories").glob("agent_*_global.tum")}
    return sorted(ids, key=lambda a: (not a.isdigit(), int(a) if a.isdigit() else 0, a))


def _read_tum(path: Path) -> tuple[np.ndarray, np.ndarray] | None:
    from cpslam.common.trajectory import read_tum

    return read_tum(path) if path.is_file() else None


def _read_json(path: Path) -> dict | None:
    return json.loads(path.read_text()) if path.is_file() else None


def _cm(value: float | None) -> str:
    return "-" if value is None else f"{100 * value:.1f}"


def _mb(value: int | None) -> str:
    return "-" if value is None else f"{value / 1e6:.2f}"


def _num(value: Any, fmt: str, none: str = "-") -> str:
    return none if value is None else fmt.format(value)

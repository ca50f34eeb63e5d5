"""The end-of-run report of a run folder: numbers, plots, mesh and reconstruction accuracy.

Works on any run folder (`cpslam.tools.runfolder`): `cpslam demo`, `cpslam run`, the
daemons' shared ``--out``, `cpslam-agent --standalone` with or without loops. It reads the
server's ``metrics.json`` (when there is a server), the trajectories, ``agent_<id>/metrics.json``
and the final map; ground truth comes from the sequences the run recorded for its agents
(`recorded_sequences`) or from the caller (evaluation only).

    report = build_report(run)             # writes RUN/report.json, RUN/plots/, RUN/mesh.ply
    print_report(report)                   # cpslam.tools.report_table

ATE (metres, position RMSE): *local* is each agent's corrected trajectory in its own frame,
origin-aligned (the paper's protocol); *global* is every agent's trajectory in its group
frame under ONE se3 alignment fitted to all agents together (per agent: its share of that
joint fit), so an agent whose frame was never aligned with the others shows a large value.
*odometry* (`cpslam run` folders): the same joint figure for the trajectories without any
pose-graph correction.

Mesh: `cpslam.tools.mesh_cli.run_mesh`. Render metrics: `cpslam.tools.eval.render_cli`.
Reconstruction (synthetic scenes, whose folder holds the ground-truth ``mesh.ply`` next to
``scene.json``): the mesh moved into the ground-truth world by the se3 alignment of the main
group's trajectories, scored by `cpslam.tools.eval.recon.evaluate_recon` on the part the
agents' cameras saw.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from cpslam.tools.runfolder import (
    agent_ids,
    main_group,
    read_json,
    recorded_sequences,
    trajectories,
)

logger = logging.getLogger(__name__)

__all__ = ["PLOTS", "build_report", "main_group", "write_plots"]

PLOTS = ("trajectories_global.png", "trajectories_local.png")
RENDER_VIEWS = 5
"""Frames per agent of the report's render metrics (`cpslam eval render` defaults to 10)."""
RECON_SAMPLES = 50_000
"""Surface samples per mesh of the report's reconstruction figure (`cpslam eval recon`
defaults to 200 000; the report keeps its cost to seconds)."""


def build_report(run: Path, sequences: dict[str, Path] | None = None, mesh: bool = True,
                 max_views: int = 40, show_progress: bool = False,
                 process: str = "report", render_views: int = RENDER_VIEWS) -> dict[str, Any]:
    """Numbers, plots (RUN/plots/) and mesh (RUN/mesh.ply) of a finished run; writes
    RUN/report.json and returns its content.

    `sequences` maps agent ids to ground truth (dataset folders or TUM files); None takes
    the sequences the run recorded. Besides the table: ``traffic`` (the server's messages,
    bytes and bytes/s per agent, direction and topic, and per group decoder key),
    ``memory_mb`` (peak resident memory of the server, of each agent and of this process,
    named `process`), with ground truth ``render`` (`cpslam eval render` at `render_views`
    frames per agent; 0: none) and, for synthetic scenes, ``recon``."""
    from cpslam.common.rundir import SCHEMA_VERSION

    run = Path(run)
    metrics = read_json(run / "metrics.json")
    ids = agent_ids(run)
    if metrics is None and (run / "server_state.pt").is_file():
        raise FileNotFoundError(f"{run}/metrics.json: not found; the server's state is there, "
                                "so it has not finalised (cpslam finalise)")
    if metrics is None and not ids:
        raise FileNotFoundError(f"{run}/metrics.json: not found and no agent_<id>/"
                                "trajectory.tum (did the server finalise? is it a run folder?)")
    if sequences is None:
        sequences = recorded_sequences(run)
    report: dict[str, Any] = {
        "schema_version": SCHEMA_VERSION, "run": str(run),
        "kind": "agent" if metrics is None else "collaborative",
        "ground_truth": {a: str(p) for a, p in sequences.items() if a in ids},
        "agents": {}, "all": {}, "notes": []}
    metrics = metrics or {}
    memory: dict[str, float | None] = {"server": metrics.get("process", {}).get("peak_rss_mb")}
    if report["kind"] == "agent":
        del memory["server"]
    est = trajectories(run, ids)
    loops = metrics.get("loops", {})
    merges = metrics.get("merges", [])
    per_agent_bus = metrics.get("bus", {}).get("per_agent", {})
    for a in ids:
        info = metrics.get("agents", {}).get(a, {})
        own = read_json(run / f"agent_{a}" / "metrics.json") or {}
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
    if report["kind"] == "agent" and ids:
        fused[None] = report["agents"][ids[0]]["points"]
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
    results = _evaluate(report, est, sequences)
    if results:
        report["plots"] = [str(p) for p in write_plots(run / "plots", *results[:2])]
    if mesh:
        from cpslam.tools.mesh_cli import run_mesh

        try:
            report["mesh"] = run_mesh(run, max_views=max_views, show_progress=show_progress)
        except (FileNotFoundError, ValueError, KeyError) as err:
            report["mesh"] = {"skipped": str(err)}
            report["notes"].append(f"mesh skipped: {err}")
    if "path" in report.get("mesh", {}) and results:
        _recon(report, results[2], sequences)
    if render_views and results:
        from cpslam.tools.eval.render_cli import evaluate_renders

        try:
            report["render"] = evaluate_renders(run, sequences, render_views,
                                                show_progress=show_progress)
        except (FileNotFoundError, ValueError) as err:
            report["notes"].append(f"no render metrics: {err}")
    from cpslam.common.rundir import peak_rss_mb, write_json

    memory[process] = peak_rss_mb()  # after the mesh: it is what this process costs most
    report["memory_mb"] = memory
    write_json(run / "report.json", report)
    return report


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


def _traffic(metrics: dict) -> dict[str, Any]:
    """Per agent and direction: {topic: {messages, bytes, bytes_per_s}}; per group the
    decoders published; the server's uptime the rates are over."""
    bus = metrics.get("bus", {})
    agents = {a: {d: dict(entry.get(d, {})) for d in ("from_agent", "to_agent")}
              for a, entry in bus.get("per_agent", {}).items()}
    return {"agents": agents, "groups": bus.get("per_group", {}),
            "seconds": metrics.get("process", {}).get("uptime_s")}


def _evaluate(report: dict, est: dict, sequences: dict[str, Path]) -> tuple | None:
    """Fill the ATE fields; returns (joint result, local results, ground truths) for the
    plots and the reconstruction, or None when an agent has no ground truth or no
    trajectory."""
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
    if all(est[a]["odometry"] for a in ids):
        try:
            odo = joint_ate([(gt[a], est[a]["odometry"]) for a in ids], align="se3")
        except ValueError as err:
            report["notes"].append(f"no ATE without the pose graph: {err}")
        else:
            report["all"]["odometry_joint_ate_m"] = float(odo.overall.rmse)
            for a, part in zip(ids, odo.parts, strict=True):
                report["agents"][a]["odometry_ate_m"] = float(part.rmse)
    return joint, local, (gt, est)


def _recon(report: dict, tracks: tuple[dict, dict], sequences: dict[str, Path]) -> None:
    """Accuracy and completion of the mesh against a synthetic scene's ground-truth mesh
    (its folder holds scene.json and mesh.ply); nothing for other data sets."""
    from cpslam.tools.eval import joint_ate
    from cpslam.tools.eval.recon import Frustum, evaluate_recon
    from cpslam.tools.mesh import read_mesh
    from cpslam.tools.runfolder import final_model

    gt, est = tracks
    scenes = {Path(p).parent for p in sequences.values()}
    scene = next(iter(scenes))
    if len(scenes) != 1 or not (scene / "scene.json").is_file() or not (
            scene / "mesh.ply").is_file():
        return  # not one synthetic scene: no ground-truth mesh
    try:
        final = final_model(Path(report["run"]))
        members = [m for m in final.members if m in gt and est[m]["global"]]
        fit = joint_ate([(gt[m], est[m]["global"]) for m in members], align="se3").overall
        T_gt_est = fit.T_gt_est
        mesh = read_mesh(report["mesh"]["path"]).transform(T_gt_est)
        poses = np.concatenate([T_gt_est[None] @ est[m]["global"][1] for m in members])
        result = evaluate_recon(mesh, read_mesh(scene / "mesh.ply"), samples=RECON_SAMPLES,
                                frustum=Frustum(poses, final.model.intrinsics))
    except (FileNotFoundError, ValueError) as err:
        report["notes"].append(f"no reconstruction figure: {err}")
        return
    report["recon"] = {"gt_mesh": str(scene / "mesh.ply"), "frame": final.frame,
                       **result.to_dict()}


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

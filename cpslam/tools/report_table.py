"""Printing a run report (`cpslam.tools.report.build_report`): the table, the traffic per
agent and key expression, peak memory, reconstruction, notes and the list of outputs."""

from __future__ import annotations

from pathlib import Path
from typing import Any

__all__ = ["print_outputs", "print_report"]


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
        table.add_row(a, str(r["frames"]), str(r["group"] or "-"), _cm(r.get("local_ate_m")),
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
    if report.get("kind") == "agent":
        console.print(f"one agent, no server; its map: {_num(t['fused_points'], '{:d}')} points")
    else:
        console.print(f"{t['groups']} group(s) at the end; fused map of group "
                      f"{t['main_group']}: {_num(t['fused_points'], '{:d}')} points")
    if report.get("traffic", {}).get("agents"):
        console.print(_traffic_table(report["traffic"]))
    memory = report.get("memory_mb", {})
    if memory:
        console.print("peak memory (MB): " + ", ".join(
            f"{name.replace('_', ' ')} {_num(mb, '{:.0f}')}" for name, mb in memory.items()))
    if "odometry_joint_ate_m" in t:
        console.print(f"without the pose graph (odometry only): joint ATE "
                      f"{_cm(t['odometry_joint_ate_m'])} cm; per agent " + ", ".join(
                          f"{a} {_cm(r.get('odometry_ate_m'))}"
                          for a, r in report["agents"].items()))
    recon = report.get("recon")
    if recon:
        console.print(f"reconstruction ({recon['frame']} mesh vs {recon['gt_mesh']}, seen part, "
                      f"{recon['samples']} samples): accuracy {recon['accuracy_cm']:.2f} cm, "
                      f"completion {recon['completion_cm']:.2f} cm, completion ratio "
                      f"{recon['completion_ratio_pct']:.1f} % (< {recon['threshold_cm']:.0f} cm)")
    render = report.get("render")
    if render:
        frames = sum(len(r["frames"]) for r in render["agents"].values())
        console.print(f"renders of the final map at ground-truth poses ({frames} frames, "
                      f"{render['width']}x{render['height']}): PSNR {render['psnr_db']:.2f} dB, "
                      f"SSIM {render['ssim']:.3f}, depth L1 {_cm(render['depth_l1_m'])} cm; "
                      "LPIPS omitted (its weights would have to be downloaded)")
    for note in report.get("notes", []):
        console.print(f"note: {note}")


def print_outputs(report: dict[str, Any], console: Any = None) -> None:
    """Where the run's files are."""
    from rich.console import Console

    console = console or Console()
    run = Path(report["run"])
    mesh_file = "mesh.ply" if "path" in report.get("mesh", {}) else "(skipped)"
    plots = ", ".join(Path(p).name for p in report.get("plots", [])) or "(no ground truth)"
    if report.get("kind") == "agent":
        trajectories = "agent_<id>/trajectory.tum"
        maps = f"agent_<id>/map.ply, {mesh_file}"
        metrics = "agent_<id>/metrics.json, report.json (this table)"
    else:
        trajectories = "trajectories/agent_<id>_global.tum (and _local)"
        maps = f"fused_map.ply, {mesh_file}"
        metrics = ("metrics.json (server), report.json (this table), "
                   "agent_<id>/metrics.json\n  pose graph           pose_graph.g2o")
    logs = sorted(p.name for p in (run / "logs").glob("*.log"))
    console.print(f"outputs in {run}/\n"
                  f"  trajectories         {trajectories}\n"
                  f"  map, mesh            {maps}\n"
                  f"  metrics              {metrics}\n"
                  f"  plots                plots/: {plots}"
                  + (f"\n  logs                 logs/: {', '.join(logs)}" if logs else ""),
                  soft_wrap=True)


def _traffic_table(traffic: dict[str, Any]) -> Any:
    from rich import box
    from rich.table import Table

    table = Table(box=box.SIMPLE_HEAD, pad_edge=False, padding=(0, 1, 0, 0),
                  title="traffic per agent and key expression (server's counters)",
                  caption="to server: agent/<id>/<topic> (image: keyframe image replies); "
                          "from server: server/agent/<id>/<topic>, image requests, every "
                          "group's decoder; kB/s over the server's uptime, kB/sensor-s per "
                          "second of the agent's frames")
    for col in ("agent", "direction", "topic", "messages", "MB", "kB/s", "kB/sensor-s"):
        table.add_column(col, justify="left" if col in ("agent", "direction", "topic")
                         else "right", no_wrap=True)
    for a, entry in traffic["agents"].items():
        for direction, label in (("from_agent", "to server"), ("to_agent", "from server")):
            for topic, cell in sorted(entry.get(direction, {}).items()):
                rate, sensor = cell.get("bytes_per_s"), cell.get("bytes_per_sensor_s")
                table.add_row(a, label, topic, str(cell.get("messages", 0)),
                              _mb(cell.get("bytes")), _num(rate and rate / 1e3, "{:.2f}"),
                              _num(sensor and sensor / 1e3, "{:.2f}"))
    if traffic.get("groups"):
        table.add_section()
        for g, cell in traffic["groups"].items():
            rate = cell.get("bytes_per_s")
            table.add_row(f"group {g}", "published", "decoder", str(cell.get("messages", 0)),
                          _mb(cell.get("bytes")), _num(rate and rate / 1e3, "{:.2f}"), "-")
    return table


def _cm(value: float | None) -> str:
    return "-" if value is None else f"{100 * value:.1f}"


def _mb(value: int | None) -> str:
    return "-" if value is None else f"{value / 1e6:.2f}"


def _num(value: Any, fmt: str, none: str = "-") -> str:
    return none if value is None else fmt.format(value)

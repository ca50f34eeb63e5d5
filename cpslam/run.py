"""`cpslam run`: N agents and the server in one process over the in-memory bus.

The debugging and integration harness: same nodes as the daemons, one `InMemoryNetwork`.
Everything is driven from one thread in lock-step: for each frame t, every agent steps one
frame (in order), the bus is flushed, the server handles what arrived in (agent, seq) order
and steps, the bus is flushed again, and every agent applies what came back. Each agent's
mapping runs on a thread of its own unless `run.schedule` is `lockstep`; with lockstep a CPU
run is reproducible. The back end's clock is virtual (frame t at t times the frame period), so
time-based choices (round time-outs, sharing) do not depend on the machine's speed.

Outputs under RUN: ``config.yaml``; per agent ``agent_<id>/`` (as a standalone run, with
``trajectory.tum`` the final pose-graph-corrected trajectory in the frame of the agent's map,
its group's, ``trajectory_odometry.tum`` the same frames without any loop correction, and the
agent's loops in ``metrics.json``); ``trajectories/agent_<id>_local.tum`` and ``_global.tum``
(and ``_odometry.tum``: the group-frame trajectory without any pose-graph correction, for
comparison), ``fused_map.*``, ``pose_graph.g2o``, ``metrics.json`` (server) and, when the
sequences have ground truth, ``evaluation.json`` (computed after the run; nothing reads
ground truth while it runs). ``cpslam-agent --standalone`` is this run with one sequence.

A set `stop` event ends the frames early (Ctrl-C, SIGTERM); everything is still flushed,
optimised and written, and the result says it was interrupted.

Relative poses of loops are the coarse geometric estimates, refined by tracking the loop
keyframe against the other sub-map when ``loop.refine`` is on (`cpslam.server.loops.PoseRefiner`,
wired by `Backend.from_config`; on by default and in ``paper``, off in ``cpu`` and ``tiny``).
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import numpy as np
import typer

from cpslam.common.cli import (
    ExitCode,
    OverwriteOpt,
    check_output,
    fail,
    out_option,
    stop_on_signals,
)
from cpslam.common.config.cli import ConfigOpt, DeviceOpt, PresetOpt, SeedOpt, SetOpt
from cpslam.common.datasets.cli import (
    FormatOpt,
    FramesOpt,
    TopicDepthOpt,
    TopicInfoOpt,
    TopicPoseOpt,
    TopicRgbOpt,
    topics_arg,
)
from cpslam.protocol import keys

if TYPE_CHECKING:
    from cpslam.common.bus import Bus
    from cpslam.common.config import CpslamConfig
    from cpslam.common.datasets import RGBDSequence
    from cpslam.server.result import FinalResult

__all__ = ["CollabRun", "LockstepBarrier", "evaluate_run", "report_run", "run", "run_collab"]

logger = logging.getLogger(__name__)


@dataclass
class CollabRun:
    """What `run_collab` did: the server's final result, the nodes' numbers, evaluation."""

    run_dir: Path
    agent_ids: list[str]
    final: FinalResult
    frames: dict[str, int]
    wall_s: float
    odometry: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    """Per agent (stamps, T_group_cam) without pose-graph corrections."""
    evaluation: dict[str, Any] = field(default_factory=dict)
    interrupted: bool = False
    """The `stop` event ended the frames before the sequences' end."""
    nodes: dict[str, Any] = field(default_factory=dict)
    """The agents' `AgentNode`s (closed; their odometry and frame results stay readable)."""


class LockstepBarrier:
    """Waits until the bus has delivered everything published before `wait` was called.

    The in-memory network delivers on one dispatcher thread in publication order, so once a
    marker published now comes back, every earlier publication sits in its subscribers'
    queues.
    """

    def __init__(self, bus: Bus, session: str) -> None:
        self.bus = bus
        self.key = keys.run_barrier(session)
        self.sub = bus.subscribe(self.key, queue_size=16)
        self.count = 0

    def wait(self, timeout_s: float = 60.0) -> None:
        self.count += 1
        marker = str(self.count).encode()
        self.bus.publish(self.key, marker)
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            sample = self.sub.get(timeout=max(deadline - time.monotonic(), 1e-3))
            if sample is not None and sample.payload == marker:
                return
        raise TimeoutError(f"in-memory bus did not flush within {timeout_s} s")


def run_collab(cfg: CpslamConfig, sequences: list[RGBDSequence], run_dir: Path,
               device: str = "cpu", agent_ids: list[str] | None = None,
               show_progress: bool = True, describe: Any = None,
               stop: threading.Event | None = None) -> CollabRun:
    """Run one agent per sequence and the server in lock-step; write everything to run_dir.
    A set `stop` ends the frames early; what was done is still optimised and written. With
    `run.rerun` on, each agent logs itself to Rerun (`cpslam.tools.view.agent_log`)."""
    import torch

    from cpslam.agent.node import AgentNode
    from cpslam.common.bus import InMemoryBus, InMemoryNetwork
    from cpslam.common.config import save_config
    from cpslam.common.logs import make_progress
    from cpslam.common.trajectory import write_tum
    from cpslam.server.node import ServerNode

    ids = agent_ids or [str(i) for i in range(len(sequences))]
    if len(ids) != len(sequences) or len(set(ids)) != len(ids):
        raise ValueError(f"run_collab: {len(sequences)} sequences need as many distinct agent "
                         f"ids, got {ids}")
    run_dir.mkdir(parents=True, exist_ok=True)
    save_config(cfg, run_dir / "config.yaml")
    torch.manual_seed(cfg.run.seed)
    period = _frame_period(sequences[0])
    clock = [0.0]
    network = InMemoryNetwork()
    buses = [InMemoryBus(network) for _ in range(len(sequences) + 1)]
    t0 = time.perf_counter()
    interrupted = False
    try:
        server = ServerNode(cfg, buses[0], run_dir, now=lambda: clock[0]).start()
        agents = [AgentNode(cfg, seq, bus, aid, run_dir, device, describe=describe).start()
                  for seq, bus, aid in zip(sequences, buses[1:], ids, strict=True)]
        barrier = LockstepBarrier(buses[0], server.session)
        streams = [node.frames() for node in agents]
        total = max(len(s) for s in sequences)
        recorders = _recorders(cfg, ids, run_dir)

        def exchange() -> None:
            barrier.wait()
            server.poll()
            barrier.wait()
            for node in agents:
                node.poll()

        try:
            with make_progress(disable=not show_progress) as bar:
                task = bar.add_task("agents " + ",".join(ids), total=total, info="")
                for t in range(total):
                    if stop is not None and stop.is_set():
                        interrupted = True
                        logger.warning("stopped after %d of %d frames: writing what was done", t,
                                       total)
                        break
                    for node, stream, seq in zip(agents, streams, sequences, strict=True):
                        if t < len(seq):
                            frame = next(stream)
                            result = node.step(frame)
                            if node.agent_id in recorders:
                                recorders[node.agent_id](frame, result, node.odometry)
                    exchange()
                    clock[0] = (t + 1) * period
                    status = server.backend.status()
                    bar.update(task, advance=1, info=f"groups {len(status['groups'])}  loops "
                               f"{status['loops']['accepted']}/{status['loops']['found']}")
        finally:  # a run that raises still leaves readable recordings
            for recorder in recorders.values():
                recorder.close()
        for node in agents:
            node.flush()
        exchange()
        for node in agents:
            if node.link.outbox:
                logger.warning("agent %s: %d messages unacknowledged at the end", node.agent_id,
                               len(node.link.outbox))
        for node in agents:
            node.write_outputs({"interrupted": True} if interrupted else None)
        # metrics.json marks a complete run: written last, after this driver's own outputs.
        final = server.finalise(mark_complete=False)
        odometry = _odometry_trajectories(server)
        for aid, (stamps, poses) in odometry.items():
            write_tum(run_dir / "trajectories" / f"agent_{aid}_odometry.tum", stamps, poses)
        _write_agent_trajectories(run_dir, final, odometry)
        frames = {node.agent_id: len(node.results) for node in agents}
        for node in agents:
            node.close()
        server.close()
    finally:
        for bus in buses:
            bus.close()
    out = CollabRun(run_dir, ids, final, frames, time.perf_counter() - t0, odometry,
                    interrupted=interrupted, nodes={n.agent_id: n for n in agents})
    out.evaluation = evaluate_run(out, sequences)
    if out.evaluation:
        from cpslam.common.rundir import SCHEMA_VERSION, write_json

        write_json(run_dir / "evaluation.json", {"schema_version": SCHEMA_VERSION,
                                                 **out.evaluation})
    from cpslam.server.export import write_metrics

    write_metrics(final, run_dir)
    return out


def evaluate_run(result: CollabRun, sequences: list[RGBDSequence]) -> dict[str, Any]:
    """ATE (m) of the global trajectories against ground truth: one se3 alignment for all
    agents (joint), per agent with the paper's origin alignment, and the same without the
    pose graph. Empty when a sequence has no ground truth."""
    from cpslam.tools.eval import joint_ate

    gts = {}
    for aid, seq in zip(result.agent_ids, sequences, strict=True):
        if not seq.has_gt:
            return {}
        gts[aid] = (np.asarray(seq.timestamps, np.float64), seq.gt_poses())
    estimates = {a.agent_id: (a.stamps, a.T_group_cam) for a in result.final.agents}
    present = [aid for aid in result.agent_ids if aid in estimates]
    if not present:
        return {}
    out: dict[str, Any] = {}
    for name, trajs in (("global", estimates), ("odometry", result.odometry)):
        have = [aid for aid in present if aid in trajs and len(trajs[aid][0]) >= 3]
        if not have:
            continue
        joint = joint_ate([(gts[a], trajs[a]) for a in have], align="se3")
        out[f"{name}_joint_se3_rmse_m"] = float(joint.overall.rmse)
        out[f"{name}_origin_rmse_m"] = {
            a: float(joint_ate([(gts[a], trajs[a])], align="origin").overall.rmse)
            for a in have}
    out["merged"] = {a.agent_id: a.merged for a in result.final.agents}
    merges = result.final.metrics.get("merges", [])
    out["merge_time_s"] = [m["time"] for m in merges]
    return out


def _recorders(cfg: CpslamConfig, ids: list[str], run_dir: Path) -> dict[str, Any]:
    """Each agent's Rerun recorder when `run.rerun` is on (imports rerun only then)."""
    if cfg.run.rerun is None:
        return {}
    from cpslam.tools.view.agent_log import AgentRecorder

    return {aid: AgentRecorder.from_config(cfg.run, aid, run_dir / f"agent_{aid}")
            for aid in ids}


def _frame_period(seq: RGBDSequence) -> float:
    stamps = np.asarray(seq.timestamps, np.float64)
    if len(stamps) > 1:
        step = float(np.median(np.diff(stamps)))
        if step > 0:
            return step
    return 1.0 / 30.0


def _write_agent_trajectories(run_dir: Path, final: FinalResult,
                              odometry: dict[str, tuple[np.ndarray, np.ndarray]]) -> None:
    """Each agent folder's trajectory.tum becomes the final pose-graph-corrected trajectory in
    its group's frame (the frame the agent's map ends in), trajectory_odometry.tum the same
    frames without loop corrections, and its metrics.json gets the loops it took part in."""
    import json

    from cpslam.common.rundir import write_json
    from cpslam.common.trajectory import write_tum

    records = final.metrics.get("loops", {}).get("list", [])
    for a in final.agents:
        agent_dir = run_dir / f"agent_{a.agent_id}"
        if len(a.stamps):
            write_tum(agent_dir / "trajectory.tum", a.stamps, a.T_group_cam)
        if a.agent_id in odometry and len(odometry[a.agent_id][0]):
            write_tum(agent_dir / "trajectory_odometry.tum", *odometry[a.agent_id])
        mine = [r for r in records if a.agent_id in (r["agent_a"], r["agent_b"])]
        metrics_path = agent_dir / "metrics.json"
        if metrics_path.is_file():
            metrics = json.loads(metrics_path.read_text())
            accepted = [r for r in mine if r["accepted"]]
            # Verified pairs this agent is part of (the run's metrics.json also counts the
            # candidates still pending at the end in "found").
            metrics["loops"] = {
                "verified": len(mine), "accepted": len(accepted),
                "rejected": len(mine) - len(accepted),
                "accepted_within_agent": sum(r["agent_a"] == r["agent_b"] for r in accepted)}
            write_json(metrics_path, metrics)


def _odometry_trajectories(server: Any) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Each agent's frames chained from its odometry alone, placed in its group's frame by
    the merge alignment: the trajectory the system would have without pose graphs."""
    from cpslam.common.geometry import compose
    from cpslam.server.tracks import trajectory_poses

    backend = server.backend
    out = {}
    for group in backend.groups.groups.values():
        for m in group.members:
            rec = backend.registry.agents[m]
            if not rec.keyframes:
                continue
            T_ga = group.T_group_agent[m]
            kf_poses = {k: compose(T_ga, T) for k, T in rec.odometry().items()}
            out[m] = trajectory_poses(rec, kf_poses)
    return out


def run(
    seq: Annotated[list[Path], typer.Option("--seq", help="Sequence folder or bag of one "
                                            "agent (repeat for more agents).")],
    preset: PresetOpt = "cpu",
    config_file: ConfigOpt = None,
    sets: SetOpt = None,
    device: DeviceOpt = None,
    seed: SeedOpt = None,
    frames: FramesOpt = None,
    fmt: FormatOpt = None,
    topic_rgb: TopicRgbOpt = None,
    topic_depth: TopicDepthOpt = None,
    topic_info: TopicInfoOpt = None,
    topic_pose: TopicPoseOpt = None,
    out: Annotated[Path | None, out_option(
        "Run folder (default: run.out/run.name, timestamped).")] = None,
    overwrite: OverwriteOpt = False,
    no_progress: Annotated[bool, typer.Option("--no-progress", help="No progress bar.")] = False,
    mesh: Annotated[bool, typer.Option("--mesh/--no-mesh", help="The report's TSDF mesh of "
                                       "the fused map (RUN/mesh.ply).")] = True,
) -> None:
    """Run N agents and the server in one process over the in-memory bus.

    One agent per --seq, ids 0, 1, …; agents that see the same place merge into one group
    (one frame, shared decoders). With one --seq: single-agent SLAM with loop closure.
    --frames and --topic-* apply to every sequence.

    Writes RUN/config.yaml, RUN/agent_<id>/ (as cpslam-agent --standalone),
    RUN/trajectories/agent_<id>_local.tum (own frame) and _global.tum (group frame),
    fused_map.ply, pose_graph.g2o, metrics.json and, with ground truth, evaluation.json;
    then the report of cpslam report (table, report.json, plots/, mesh.ply).
    RUN/agent_<id>/trajectory.tum is the final pose-graph-corrected trajectory (group frame),
    trajectory_odometry.tum the same frames without loop corrections. Ctrl-C (or SIGTERM)
    stops after the current frame and writes what was done (exit 130); again exits at once.

    Examples:

      cpslam run --seq data/apt/agent_0 --seq data/apt/agent_1 --out runs/apt

      cpslam run --seq data/room-loop/agent_0 --preset cpu --out runs/loop

      cpslam run --seq data/room-loop/agent_0 --frames 0:150 --seed 1 --out runs/loop -v --overwrite

      cpslam run --seq robot1.mcap --seq robot2.mcap --topic-depth /camera/depth/image_raw
    """
    from cpslam.common.config.cli import config_or_exit
    from cpslam.common.datasets import DatasetError
    from cpslam.common.device import configure_torch, resolve_device
    from cpslam.common.rundir import create_run_dir

    cfg = config_or_exit(preset, config_file, sets, device, seed)
    try:
        torch_device = resolve_device(cfg.run.device)
        from cpslam.protocol import ProtocolError, keys

        keys.check_id(cfg.transport.session, "transport.session")
    except (ValueError, ProtocolError) as err:
        fail(str(err))
    from cpslam.agent.standalone import open_for_config

    try:
        topics = topics_arg(topic_rgb, topic_depth, topic_info, topic_pose)
        sequences = [open_for_config(cfg, path, fmt, frames, topics) for path in seq]
    except DatasetError as err:
        fail(str(err))
    configure_torch(cfg.run.num_threads, cfg.run.deterministic)
    run_dir = out if out is not None else create_run_dir(cfg.run.out, cfg.run.name)
    check_output(run_dir, overwrite)
    with stop_on_signals() as stop:
        result = run_collab(cfg, sequences, run_dir, torch_device,
                            show_progress=not no_progress, stop=stop)
    report_run(result, mesh=mesh, show_progress=not no_progress)
    if result.interrupted:
        raise typer.Exit(ExitCode.INTERRUPTED)


def report_run(result: CollabRun, command: str = "cpslam run", mesh: bool = True,
               show_progress: bool = False) -> None:
    """`cpslam report` of the run just finished (`cpslam.tools.report_cli.finish_run`)."""
    from cpslam.tools.report_cli import finish_run

    finish_run(result.run_dir, mesh=mesh, show_progress=show_progress,
               title=f"{command} → {result.run_dir}  ({result.wall_s:.0f} s)")

"""`cpslam-agent`: run one agent on one RGB-D sequence.

It lives at the top of the package, beside `cpslam run`, because a standalone run with loop
closure drives the server's back end in the same process (`cpslam.run.run_collab`); the agent
package itself never imports the server."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Annotated

import typer

from cpslam.common.cli import App, ExitCode, OverwriteOpt, check_output, fail, out_option
from cpslam.common.config.cli import (
    ConfigOpt,
    ConnectOpt,
    DeviceOpt,
    PresetOpt,
    SeedOpt,
    SessionOpt,
    SetOpt,
)
from cpslam.common.datasets.cli import (
    FormatOpt,
    FramesOpt,
    TopicDepthOpt,
    TopicInfoOpt,
    TopicPoseOpt,
    TopicRgbOpt,
    topics_arg,
)

logger = logging.getLogger("cpslam.agent")

app = App()


@app.command()
def agent(
    ctx: typer.Context,
    seq: Annotated[Path, typer.Option("--seq", help="Sequence folder (any supported format) or "
                                                      "a ROS 1/2 bag or MCAP file.")],
    standalone: Annotated[
        bool, typer.Option("--standalone", help="Run without a separate server: odometry, "
                           "mapping and loop closure by an in-process back end (as `cpslam "
                           "run` with one --seq).")
    ] = False,
    no_loops: Annotated[
        bool, typer.Option("--no-loops", help="With --standalone: odometry and mapping only, "
                           "no back end (no loop closure); needed for --resume.")
    ] = False,
    agent_id: Annotated[
        str, typer.Option("--agent-id", help="Agent id: 1-64 letters, digits, '_' or '-'.")
    ] = "0",
    connect: ConnectOpt = None,
    session: SessionOpt = None,
    wait_timeout: Annotated[
        float, typer.Option("--wait-timeout", min=0.0,
                            help="Seconds to wait for the server before giving up (exit 3: "
                            "no server).")
    ] = 300.0,
    ack_timeout: Annotated[
        float, typer.Option("--ack-timeout", min=0.0, help="Seconds to wait at the end for the "
                            "server to acknowledge everything (else exit 4).")
    ] = 120.0,
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
        "Run folder, may be shared with the server and other agents (default: "
        "run.out/run.name, timestamped); RUN/agent_<id>/ follows the overwrite rule.")] = None,
    overwrite: OverwriteOpt = False,
    resume: Annotated[
        Path | None, typer.Option("--resume", help="state.pt of an earlier run to continue from "
                                  "(networked: the same incarnation, with link.pt beside it; "
                                  "or --standalone --no-loops).")
    ] = None,
    no_progress: Annotated[bool, typer.Option("--no-progress", help="No progress bar.")] = False,
) -> None:
    """Track the camera of one RGB-D sequence, build its neural point map, and (unless
    --standalone) stream it to a cpslam-server that merges it with other agents' maps.

    Writes RUN/agent_<id>/: trajectory.tum (every frame, in the agent's working frame),
    map.ply, state.pt (reload with `cpslam render` or `--resume`) and metrics.json (with bytes
    sent per key expression when networked). The effective configuration goes to
    RUN/config.yaml with --standalone, and to RUN/agent_<id>/config.yaml (next to agent.log)
    when networked, where agents and the server may share RUN; an existing RUN/agent_<id>/ is
    replaced only with --overwrite. Networked: waits for the server, resends what was not
    acknowledged after a server restart, exits 0 once everything is acknowledged (3: no
    server, 4: unacknowledged, 5: refused because the agent id already streams as another
    incarnation). Every start is a new incarnation unless --resume RUN/agent_<id>/state.pt
    continues the earlier one (its link.pt beside it: seq counter, outbox, group frame).

    --standalone closes the agent's own loops with the server's back end in this process
    (the run `cpslam run --seq SEQ` makes): trajectory.tum is then the loop-corrected
    trajectory (the final pose graph's), trajectory_odometry.tum the same frames without loop
    corrections, metrics.json counts the loops, and RUN/ also gets the back end's outputs
    (metrics.json with loops found and accepted, trajectories/, fused_map.ply, pose_graph.g2o,
    evaluation.json when the sequence has ground truth) and the report of cpslam report
    without its mesh (report.json; cpslam mesh RUN makes the mesh). --standalone --no-loops
    runs the odometry alone: trajectory.tum is the odometry, and --resume continues such a
    run; cpslam report RUN reports it.

    Ctrl-C or SIGTERM stops the run and saves what exists (exit 130); with loop closure the
    run stops after the current frame and still runs the last pose graph (a second signal
    exits at once).
    Torch uses every core this process may use (run.num_threads: auto); beside other busy
    processes on the same cores, give it fewer (--set run.num_threads=1).

    Examples:

      cpslam-agent --seq runs/data/apartment/agent_0 --agent-id 0 --connect tcp/127.0.0.1:7447

      cpslam-agent --seq /data/office --agent-id robot-2 --connect tcp/10.0.0.5:7447 --session lab

      cpslam-agent --seq runs/data/room/agent_0 --standalone --out runs/room

      cpslam-agent --seq runs/data/room/agent_0 --standalone --no-loops --out runs/odo

      cpslam-agent --seq data/room --standalone --no-loops --resume runs/odo/agent_0/state.pt

      cpslam-agent --seq ../shared/data/7scenes-kitchen-0-299 --standalone --frames 0:100

      cpslam-agent --seq robot.bag --topic-rgb /camera/color/image_raw --standalone

      cpslam-agent --seq runs/data/room/agent_0 --standalone --set run.num_threads=1

      cpslam-agent --seq data/office0 --standalone --preset paper --device cuda
    """
    from cpslam.common.cli import verbosity
    from cpslam.common.config.cli import config_or_exit, transport_sets
    from cpslam.common.datasets import DatasetError
    from cpslam.common.device import configure_torch, resolve_device
    from cpslam.common.logs import setup_logging
    from cpslam.common.rundir import create_run_dir
    from cpslam.protocol import ProtocolError, keys

    setup_logging(verbosity(ctx), daemon=not standalone, info=True)
    try:
        keys.check_id(agent_id, "--agent-id")
    except ProtocolError as err:
        fail(str(err))
    if standalone and (connect or session):
        fail("--connect/--session make no sense with --standalone")
    cfg = config_or_exit(preset, config_file, [*(sets or []), *transport_sets(
        session, None, connect)], device, seed)
    if not standalone and cfg.transport.tls_cert is not None:
        _check_certificate(cfg.transport.tls_cert, agent_id)
    try:
        torch_device = resolve_device(cfg.run.device)
    except ValueError as err:
        fail(str(err))
    if no_loops and not standalone:
        fail("--no-loops works with --standalone only (networked, the server closes loops)")
    if resume is not None and standalone and not no_loops:
        fail("--resume works networked or with --standalone --no-loops (it continues the "
             "odometry; the in-process loop-closing back end keeps no state to resume)")
    if resume is not None and not resume.is_file():
        fail(f"--resume {resume}: no such file")
    if resume is not None and not standalone and not resume.with_name("link.pt").is_file():
        fail(f"--resume {resume}: no link.pt beside it; a networked agent resumes from the "
             "agent_<id>/ folder of an earlier networked run (state.pt and link.pt)")

    from cpslam.agent.standalone import open_for_config, run_standalone

    try:
        topics = topics_arg(topic_rgb, topic_depth, topic_info, topic_pose)
        sequence = open_for_config(cfg, seq, fmt, frames, topics)
    except DatasetError as err:
        fail(str(err))
    threads = configure_torch(cfg.run.num_threads, cfg.run.deterministic)
    run_dir = out if out is not None else create_run_dir(cfg.run.out, cfg.run.name)
    check_output(run_dir / f"agent_{agent_id}", overwrite)
    loops = standalone and not no_loops
    if loops:  # the back end's outputs of an earlier run in RUN
        for name in ("metrics.json", "trajectories"):
            check_output(run_dir / name, overwrite)
    run_dir.mkdir(parents=True, exist_ok=True)
    logger.info("agent %s: %s (%s, %d frames) on %s (%d CPU threads) → %s", agent_id, seq,
                sequence.format, len(sequence), torch_device, threads, run_dir)
    if not standalone:
        raise typer.Exit(_networked(cfg, sequence, agent_id, run_dir, torch_device, wait_timeout,
                                    ack_timeout, not no_progress, resume))
    if loops:
        raise typer.Exit(_with_loops(cfg, sequence, agent_id, run_dir, torch_device,
                                     not no_progress))
    from cpslam.common.cli import stop_on_signals

    recorder = _recorder(cfg, agent_id, run_dir)
    try:
        with stop_on_signals() as stop:
            result = run_standalone(cfg, sequence, run_dir, torch_device, agent_id=agent_id,
                                    resume=resume, show_progress=not no_progress, stop=stop,
                                    on_frame=recorder)
    finally:
        if recorder is not None:
            recorder.close()
    typer.echo(f"{result.frames_done}/{result.frames_total} frames in {result.wall_time_s:.1f} s "
               f"→ {result.agent_dir}")
    if result.interrupted:
        raise typer.Exit(ExitCode.INTERRUPTED)


def _with_loops(cfg, sequence, agent_id: str, run_dir: Path, device: str,
                show_progress: bool) -> int:
    """The standalone run with loop closure: `cpslam run`'s lock-step run of this one agent
    and the back end, with SIGINT/SIGTERM ending the frames early."""
    from cpslam.common.cli import stop_on_signals
    from cpslam.run import report_run, run_collab

    with stop_on_signals() as stop:
        result = run_collab(cfg, [sequence], run_dir, device, agent_ids=[agent_id],
                            show_progress=show_progress, stop=stop)
    # No mesh: it renders the map 40 times, long next to a short agent run; `cpslam mesh RUN`
    # or `cpslam report RUN` makes it.
    report_run(result, "cpslam-agent --standalone", mesh=False, show_progress=show_progress)
    typer.echo(f"{result.frames.get(agent_id, 0)}/{len(sequence)} frames in "
               f"{result.wall_s:.1f} s → {run_dir / f'agent_{agent_id}'}")
    return ExitCode.INTERRUPTED if result.interrupted else ExitCode.OK


def _networked(cfg, sequence, agent_id: str, run_dir: Path, device: str, wait_timeout: float,
               ack_timeout: float, show_progress: bool, resume: Path | None = None) -> int:
    """Run against a server with SIGINT/SIGTERM stopping the stream cleanly."""
    from cpslam.agent.daemon import run_networked
    from cpslam.common.cli import stop_on_signals
    from cpslam.common.config import save_config
    from cpslam.common.logs import log_to_file

    log_to_file(run_dir / f"agent_{agent_id}" / "agent.log")
    save_config(cfg, run_dir / f"agent_{agent_id}" / "config.yaml")
    recorder = _recorder(cfg, agent_id, run_dir)
    try:
        with stop_on_signals() as stop:
            return run_networked(cfg, sequence, agent_id, run_dir, device, wait_timeout,
                                 ack_timeout, show_progress, stop, on_frame=recorder,
                                 resume=resume)
    finally:
        if recorder is not None:
            recorder.close()


def _recorder(cfg, agent_id: str, run_dir: Path):
    """The agent's Rerun recorder when `run.rerun` is on (rerun is imported only then); a
    missing viz extra is a usage error, before any work."""
    if cfg.run.rerun is None:
        return None
    from cpslam.tools.view import RerunMissingError
    from cpslam.tools.view.agent_log import AgentRecorder

    try:
        return AgentRecorder.from_config(cfg.run, agent_id, run_dir / f"agent_{agent_id}")
    except RerunMissingError as err:
        fail(f"run.rerun={cfg.run.rerun}: {err}")


def _check_certificate(cert: Path, agent_id: str) -> None:
    """With mutual TLS the server's access control knows an agent by its certificate's common
    name: a different --agent-id would be refused message by message, so refuse it here."""
    from cpslam.common.bus.zenoh_security import certificate_name

    try:
        name = certificate_name(cert)
    except ValueError as err:
        fail(str(err))
    if name != agent_id:
        fail(f"--agent-id {agent_id!r} differs from the name {name!r} of transport.tls_cert "
             f"{cert}: the server's access control would refuse this agent's messages")


def main() -> None:
    app()


if __name__ == "__main__":
    main()

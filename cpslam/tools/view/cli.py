"""`cpslam view`: replay a run folder, or watch a running session, in Rerun."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Annotated

import typer

from cpslam.common.cli import ExitCode, OverwriteOpt, check_output, fail
from cpslam.common.config.cli import ConnectOpt, SessionOpt
from cpslam.tools.view import RerunMissingError

logger = logging.getLogger(__name__)

__all__ = ["save_replay", "view"]


def view(
    run: Annotated[Path | None, typer.Argument(
        help="Finished run folder to replay (omit with --connect).")] = None,
    connect: ConnectOpt = None,
    session: SessionOpt = None,
    save: Annotated[Path | None, typer.Option(
        "--save", help="Record to this .rrd file instead of opening a viewer.")] = None,
    web: Annotated[bool, typer.Option(
        "--web", help="Serve Rerun's web viewer from this process (headless machines); "
        "runs until Ctrl-C.")] = False,
    web_port: Annotated[int, typer.Option("--web-port", help="Port of the web viewer.")] = 9090,
    gt: Annotated[list[Path] | None, typer.Option(
        "--gt", help="Ground truth of an agent: AGENT=PATH, or PATH for the agents in id "
        "order (sequence folder or TUM file; repeatable). Default: the demo's record.")] = None,
    thumbnails: Annotated[bool, typer.Option(
        "--thumbnails/--no-thumbnails", help="Live: fetch each new keyframe's colour image "
        "from its agent.")] = True,
    duration: Annotated[float | None, typer.Option(
        "--duration", min=0.1, help="Live: stop after this many seconds (else Ctrl-C).")] = None,
    timeout: Annotated[float, typer.Option(
        "--timeout", min=0.1, help="Live: seconds to wait for the server.")] = 60.0,
    overwrite: OverwriteOpt = False,
) -> None:
    """Replay a run folder, or watch a running session, in Rerun (needs rerun-sdk, the viz extra).

    A replay shows each agent's trajectory (against ground truth where known), keyframes as
    camera frusta with thumbnails, the fused map (and coloured by agent), the mesh, the pose
    graph and the accepted and rejected loops. --connect follows a live session through the
    wire protocol only (it publishes nothing). Entity paths: docs/viewer.md.

    Examples:

      cpslam view runs/apt

      cpslam view runs/apt --save runs/apt/view.rrd

      cpslam view runs/x --gt data/apt/agent_0 --gt data/apt/agent_1 --web

      cpslam view --connect tcp/10.0.0.5:7447 --session lab --save live.rrd
    """
    if (run is None) == (not connect):
        fail("give a run folder to replay, or --connect ENDPOINT to watch a session "
             "(not both)")
    if save is not None and web:
        fail("--save and --web exclude each other")
    if save is not None:
        check_output(save, overwrite)
    try:
        if run is not None:
            from cpslam.tools.view.replay import agent_ids

            if not run.is_dir() or not agent_ids(run):
                fail(f"{run}: not a finished run folder (no trajectories/agent_<id>_global.tum "
                     "nor agent_<id>/trajectory.tum)")
            counts = save_replay(run, save, web=web, web_port=web_port,
                                 sequences=_ground_truth(run, gt or []))
            typer.echo(_summary(counts))
            if web:
                _wait_for_ctrl_c()
        else:
            _live(connect, session, save, web, web_port, thumbnails, duration, timeout)
    except RerunMissingError as err:
        fail(str(err), ExitCode.ERROR)
    if save is not None:
        typer.echo(f"saved {save} ({save.stat().st_size / 1e6:.1f} MB); open it with: "
                   f"rerun {save}")


def save_replay(run: Path, save: Path | None, web: bool = False, web_port: int = 9090,
                sequences: dict[str, Path] | None = None) -> dict:
    """Replay `run` into a viewer or, with `save`, an .rrd file (what `cpslam demo` leaves);
    returns the replay's counts."""
    from cpslam.tools.view.replay import replay_run
    from cpslam.tools.view.sink import Scene, open_recording

    scene = Scene(open_recording(run.resolve().name, save=save, web=web, web_port=web_port))
    try:
        return replay_run(run, scene, sequences)
    finally:
        scene.close()


def _live(connect: list[str] | None, session: str | None, save: Path | None, web: bool,
          web_port: int, thumbnails: bool, duration: float | None, timeout: float) -> None:
    import threading

    from cpslam.common.cli import stop_on_signals
    from cpslam.server.client import _client
    from cpslam.tools.view.live import Observer
    from cpslam.tools.view.sink import Scene, open_recording

    cfg, bus = _client(connect, session, timeout)
    s = cfg.transport.session
    scene = Scene(open_recording(f"live-{s}", save=save, web=web, web_port=web_port))
    with bus, stop_on_signals() as stop:
        observer = Observer(bus, s, scene, thumbnails=thumbnails)
        observer.start()
        timer = threading.Timer(duration, stop.set) if duration else None
        if timer is not None:
            timer.daemon = True
            timer.start()
        typer.echo(f"watching session {s!r} (Ctrl-C stops)", err=True)
        try:
            observer.run(stop)
        finally:
            observer.close()
            scene.close()
    typer.echo(f"observed {observer.messages} messages from {len(observer.agents)} agents")


def _ground_truth(run: Path, items: list[Path]) -> dict[str, Path] | None:
    """--gt items as agent id -> path (bare paths in the run's agent order); None: default."""
    if not items:
        return None
    from cpslam.tools.view.replay import agent_ids

    ids = agent_ids(run)
    out, bare = {}, []
    for item in items:
        agent, sep, path = str(item).partition("=")
        if sep and agent in ids:
            out[agent] = Path(path)
        else:
            bare.append(item)
    if len(bare) > len(ids):
        fail(f"--gt: {len(bare)} paths for the {len(ids)} agents of {run}")
    out.update(zip(ids, bare, strict=False))
    for agent, path in out.items():
        if not path.exists():
            fail(f"--gt {agent}={path}: not found")
    return out


def _summary(counts: dict) -> str:
    lines = []
    for a, c in counts["agents"].items():
        gt = ", ground truth" if c.get("ground_truth") else ""
        lines.append(f"agent {a}: {c['frames']} frames, {c['keyframes']} keyframes, "
                     f"{c['points']} points{gt}")
    loops = counts["loops"]
    lines.append(f"pose graph edges {counts['pose_graph_edges']}, loops accepted "
                 f"{loops['accepted']} rejected {loops['rejected']}, mesh triangles "
                 f"{counts['mesh']}, events {counts['events']}")
    return "\n".join(lines)


def _wait_for_ctrl_c() -> None:
    from cpslam.common.cli import stop_on_signals

    typer.echo("serving the web viewer; Ctrl-C ends it", err=True)
    with stop_on_signals() as stop:
        while not stop.wait(1.0):
            pass

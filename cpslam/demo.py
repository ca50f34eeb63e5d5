"""`cpslam demo`: a server and N agents as separate processes over loopback TCP, then a report.

1. The synthetic scene (`cpslam.tools.synth.generate`, N agents walking a 300-frame path) is
   generated once and cached under ``DATA/<scene>-<N>x<walk>-<W>x<H>-s<seed>/`` (``--data-dir``,
   default ``runs/data``; the seed is ``--scene-seed``); a folder with its ``scene.json`` is
   complete and reused.
2. ``python -m cpslam.server.cli`` listens on ``tcp/127.0.0.1:PORT`` (a free port unless
   ``--port``); once its liveliness token is seen, one ``python -m cpslam.agent_cli`` per agent
   streams ``--num-frames`` evenly spaced frames of its walk. Each child runs in its own process
   group with stdout and stderr in ``RUN/logs/<name>.log``.
3. Progress: the server's status query (frames, keyframes, groups, loops) once a second.
4. When every agent exited 0, a ``Control(finalise)`` message asks the server for the final
   pose graph, refinement and outputs; it exits 0.
5. `cpslam.tools.report_cli.finish_run` (what `cpslam report` runs): tables (results; traffic
   per agent and key), peak memory of every process, render and reconstruction figures,
   plots, mesh; the list of outputs.

A child that dies (an agent with a non-zero code, the server at all before it was asked to
finish) stops the others and is named with its log file. Ctrl-C sends SIGINT once to every
child (agents save what they have, the server finalises) and waits for them; a second Ctrl-C
kills them (`cpslam.supervisor`).
"""

from __future__ import annotations

import logging
import os
import shutil
import signal
import socket
import sys
import time
from pathlib import Path
from typing import Annotated, Any

import typer

from cpslam.common.cli import ExitCode, OverwriteOpt, fail, out_option
from cpslam.common.config.cli import DeviceOpt, PresetOpt, SeedOpt, SetOpt
from cpslam.supervisor import ChildFailed, Supervisor

__all__ = ["demo", "frame_slice", "free_port", "prepare_run_dir", "scene_data"]

logger = logging.getLogger(__name__)

SESSION = "demo"
WALK_FRAMES = 300
MARKER = "demo.json"
KEYFRAME_EVERY = 10
"""Keyframe interval of the demo (unless --set or the preset asks for fewer frames): the
demo's frames are every 3rd of the walk, and the presets' 50 would leave 2 keyframes per
agent, too few for the agents to find each other."""


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port on `host` that was free a moment ago."""
    with socket.socket() as sock:
        sock.bind((host, 0))
        return int(sock.getsockname()[1])


def frame_slice(walk: int, frames: int) -> str:
    """``START:STOP:STEP`` picking `frames` evenly spaced frames of a `walk`-frame sequence."""
    step = max(1, walk // max(frames, 1))
    return f"0:{min(step * frames, walk)}:{step}"


def scene_data(data_dir: Path, scene: str, agents: int, walk: int, width: int, height: int,
               seed: int, show_progress: bool = True, loop: bool = False,
               noise: bool = False) -> list[Path]:
    """The agents' sequence folders of a synthetic scene, generated on first use (`loop`:
    closed trajectories, as ``cpslam dataset synth --loop``; `noise`: Kinect-like depth noise,
    as ``--noise``)."""
    from cpslam.tools.synth import generate

    out = Path(data_dir) / (f"{scene}-{agents}x{walk}-{width}x{height}-s{seed}"
                            + ("-loop" if loop else "") + ("-noise" if noise else ""))
    dirs = [out / f"agent_{i}" for i in range(agents)]
    if (out / "scene.json").is_file() and all(d.is_dir() for d in dirs):
        logger.info("scene cached in %s", out)
        return dirs
    return generate(out, scene=scene, agents=agents, frames=walk, width=width, height=height,
                    seed=seed, loop=loop, noise=noise, overwrite=True,
                    show_progress=show_progress).agent_dirs


def prepare_run_dir(run: Path, overwrite: bool = False) -> None:
    """An empty run folder; an earlier demo's folder (it holds demo.json) is replaced with
    `overwrite`, anything else is never removed."""
    if run.exists():
        if run.is_dir() and not any(run.iterdir()):
            return
        if not (run / MARKER).is_file():
            raise FileExistsError(f"{run}: exists and is not an earlier demo's folder; choose "
                                  "another --out or remove it")
        if not overwrite:
            raise FileExistsError(f"{run} already exists; pass --overwrite to replace it")
        shutil.rmtree(run)
    run.mkdir(parents=True)


def demo(
    agents: Annotated[int, typer.Option("--agents", min=1, max=8, help="Number of agents.")] = 2,
    preset: PresetOpt = "cpu",
    out: Annotated[Path, out_option("Run folder (an earlier demo's is replaced with "
                                    "--overwrite).")] = Path("runs/demo"),
    overwrite: OverwriteOpt = False,
    num_frames: Annotated[int, typer.Option("--num-frames", min=2, help="Frames per agent, "
                                            "evenly spaced over its 300-frame walk.")] = 100,
    scene: Annotated[str, typer.Option("--scene", help="apartment or room.")] = "apartment",
    width: Annotated[int, typer.Option("--width", min=8, help="Image width of the scene.")] = 320,
    height: Annotated[int, typer.Option("--height", min=8, help="Image height.")] = 240,
    scene_seed: Annotated[int, typer.Option("--scene-seed", help="Seed of the synthetic "
                                            "scene.")] = 0,
    seed: SeedOpt = None,
    data_dir: Annotated[Path, typer.Option("--data-dir", help="Cache of generated scenes.")
                        ] = Path("runs/data"),
    port: Annotated[int, typer.Option("--port", min=0, max=65535,
                                      help="Server port on 127.0.0.1 (0: a free one).")] = 0,
    sets: SetOpt = None,
    device: DeviceOpt = None,
    mesh: Annotated[bool, typer.Option("--mesh/--no-mesh", help="TSDF mesh of the fused map."
                                       )] = True,
    timeout: Annotated[float, typer.Option("--timeout", min=0, help="Give up after this many "
                                           "seconds (0: never).")] = 0.0,
    no_progress: Annotated[bool, typer.Option("--no-progress", help="No progress bars.")
                           ] = False,
) -> None:
    """Server and agents as separate processes on this machine, on a synthetic apartment.

    Generates (once, cached in --data-dir) the scene, starts cpslam-server on a free
    127.0.0.1 port and one cpslam-agent per agent, shows their progress, finalises the
    server and prints a table (per-agent and global ATE, loops, merge time, map size, bytes
    sent per agent), the traffic per agent and key expression (MB, kB/s) and the peak memory
    of each process. Outputs in --out: trajectories/, fused_map.ply, mesh.ply,
    pose_graph.g2o, metrics.json, report.json, plots/*.png, logs/ and, with rerun-sdk
    installed, demo.rrd (the 3-D view: `rerun RUN/demo.rrd`).

    Examples:

      cpslam demo

      cpslam demo --agents 3 --num-frames 60 --out runs/demo3

      cpslam demo --preset tiny --num-frames 30 --width 160 --height 120 --no-mesh

      cpslam demo --scene room --scene-seed 3 --seed 1 --overwrite
    """
    if scene not in ("apartment", "room"):
        fail(f"--scene must be apartment or room, got {scene!r}")
    from cpslam.common.config.cli import config_or_exit

    sets = list(sets or [])
    cfg = config_or_exit(preset, None, sets, device, seed)  # checks --set before any work
    if cfg.keyframes.every > KEYFRAME_EVERY and not any(
            s.replace(" ", "").startswith("keyframes.every=") for s in sets):
        sets.insert(0, f"keyframes.every={KEYFRAME_EVERY}")
    from cpslam.common.device import configure_torch, resolve_num_threads

    if cfg.run.num_threads == "auto":
        # The server and the agents share this machine's cores: one torch thread pool per
        # process over all of them would oversubscribe the cores several times.
        sets.append(f"run.num_threads={resolve_num_threads('auto', share=agents + 1)}")
    # The report renders in this process after the children exit.
    configure_torch(cfg.run.num_threads, cfg.run.deterministic)
    t0 = time.monotonic()
    try:
        prepare_run_dir(out, overwrite)
    except FileExistsError as err:
        fail(str(err))
    walk = max(WALK_FRAMES, num_frames)
    seqs = scene_data(data_dir, scene, agents, walk, width, height, scene_seed, not no_progress)
    port = port or free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    common = ["--session", SESSION, "--preset", preset, "--out", str(out),
              *(x for s in sets for x in ("--set", s)),
              *(["--device", device] if device else []),
              *(["--seed", str(seed)] if seed is not None else [])]
    info: dict[str, Any] = {"agents": agents, "preset": preset, "sets": sets,
                            "frames": num_frames, "frame_slice": frame_slice(walk, num_frames),
                            "scene": scene,
                            "endpoint": endpoint, "session": SESSION,
                            "sequences": {str(i): str(p) for i, p in enumerate(seqs)},
                            "data_s": time.monotonic() - t0}
    _write_marker(out, info)
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    env.setdefault("OMP_NUM_THREADS", "1")
    deadline = t0 + timeout if timeout else None
    code = ExitCode.OK
    # SIGTERM (a CI cancelling us, `kill`) stops the children like Ctrl-C does.
    try:
        previous = signal.signal(signal.SIGTERM, _interrupt)
    except ValueError:  # not the main thread: leave SIGTERM alone
        previous = None
    with Supervisor(out / "logs", env) as sup:
        try:
            _run(sup, endpoint, common, seqs, info, deadline, not no_progress)
        except ChildFailed as err:
            typer.echo(f"error: {err}", err=True)
            code = ExitCode.ERROR
        except TimeoutError as err:
            typer.echo(f"error: {err}; logs in {out / 'logs'}", err=True)
            code = ExitCode.ERROR
        except KeyboardInterrupt:
            typer.echo("interrupted: stopping the agents and the server (the server writes "
                       "what it has; Ctrl-C again to kill)", err=True)
            code = ExitCode.INTERRUPTED
    if previous is not None:
        signal.signal(signal.SIGTERM, previous)
    info["wall_s"] = time.monotonic() - t0
    from cpslam.common.rundir import peak_rss_mb

    info["memory_mb"] = {"demo": peak_rss_mb()}  # the report adds the server and agents
    _write_marker(out, info)
    if code:
        raise typer.Exit(code)
    _report(out, info, mesh, not no_progress)


def _run(sup: Supervisor, endpoint: str, common: list[str], seqs: list[Path],
         info: dict, deadline: float | None, show: bool) -> None:
    """Start the server and the agents, follow them, finalise the server."""
    from cpslam.agent.daemon import ServerPresence
    from cpslam.common.bus import BusError, bus_from_config
    from cpslam.common.config import load_config
    from cpslam.protocol import Control, encode, keys

    py = [sys.executable, "-m"]
    t = time.monotonic()
    # The demo reports itself (with its own title and memory), not through the server.
    sup.start("server", [*py, "cpslam.server.cli", "--listen", endpoint, "--no-report", *common],
              may_exit=False)
    client_cfg = load_config(overrides=[f"transport.connect={endpoint}",
                                        f"transport.session={SESSION}",
                                        "transport.open_timeout_s=1"], env={})

    def connect() -> Any:
        try:
            return bus_from_config(client_cfg.transport, "agent")
        except BusError:
            return None

    bus = _wait(connect, "the server to listen", sup, deadline)
    with bus:
        presence = ServerPresence(bus, SESSION)
        _wait(lambda: presence.wait(1.0) or None, "the server to come up", sup, deadline)
        for i, seq in enumerate(seqs):
            sup.start(f"agent_{i}", [*py, "cpslam.agent_cli", "--seq", str(seq), "--agent-id",
                                     str(i), "--connect", endpoint, "--no-progress",
                                     "--frames", info["frame_slice"], *common])
        names = [f"agent_{i}" for i in range(len(seqs))]
        _follow(sup, bus, names, info["frames"], deadline, show)
        info["agents_s"] = time.monotonic() - t
        t = time.monotonic()
        sup.children["server"].may_exit = True  # from now on it may finish
        bus.publish(keys.server_control(SESSION), encode(Control(action="finalise",
                                                                 reason="demo done")))
        _wait(lambda: None if sup.running("server") else True, "the server to finalise", sup,
              deadline, label="server: finalising", show=show)
        presence.close()
    sup.check()
    info["finalise_s"] = time.monotonic() - t


def _wait(poll: Any, what: str, sup: Supervisor, deadline: float | None,
          label: str | None = None, show: bool = False) -> Any:
    """Call `poll` until it returns something; fail if a child dies or time runs out."""
    from cpslam.common.logs import make_progress

    with make_progress(disable=not (show and label)) as bar:
        bar.add_task(label or what, total=None, info="")
        while True:
            value = poll()
            if value is not None:
                return value
            sup.check()
            if deadline is not None and time.monotonic() > deadline:
                raise TimeoutError(f"--timeout reached while waiting for {what}")
            time.sleep(0.5)


def _follow(sup: Supervisor, bus: Any, names: list[str], frames: int,
            deadline: float | None, show: bool) -> None:
    """Progress bars from the server's status until every agent has exited."""
    from cpslam.common.logs import make_progress

    with make_progress(disable=not show) as bar:
        tasks = {n: bar.add_task(n.replace("_", " "), total=frames, info="starting")
                 for n in names}
        server = bar.add_task("server", total=None, info="")
        while True:
            sup.check()
            summary = _status(bus)
            for n in names:
                a = summary.get("agents", {}).get(n.split("_", 1)[1])
                if not sup.running(n):
                    bar.update(tasks[n], completed=frames, info="done")
                elif a is not None:
                    bar.update(tasks[n], completed=min(a.get("frames", 0), frames),
                               info=f"keyframes {a.get('keyframes', 0)}  sent "
                                    f"{a.get('bytes', 0) / 1e6:.1f} MB")
            if summary:
                loops = summary.get("loops", {})
                bar.update(server, info=f"groups {len(summary.get('groups', {}))}  loops "
                           f"{loops.get('accepted', 0)}/{loops.get('found', 0)}  merges "
                           f"{summary.get('merges', 0)}  rounds "
                           f"{summary.get('rounds', {}).get('closed', 0)}")
            if not any(sup.running(n) for n in names):
                return
            if deadline is not None and time.monotonic() > deadline:
                raise TimeoutError("--timeout reached while the agents were running")
            time.sleep(1.0)


def _status(bus: Any) -> dict:
    """The server's status summary, or {} when it does not answer within a second."""
    from cpslam.server.client import query_status

    return query_status(bus, SESSION, timeout_s=1.0) or {}


def _report(out: Path, info: dict, mesh: bool, show: bool) -> None:
    from cpslam.tools.report_cli import finish_run

    t = time.monotonic()
    seqs = {a: Path(p) for a, p in info["sequences"].items()}
    report = finish_run(out, seqs, mesh=mesh, show_progress=show, process="demo",
                        title=f"cpslam demo: {info['agents']} agents, preset {info['preset']}, "
                              f"{info['frames']} frames each, run {info['wall_s']:.0f} s")
    info["report_s"] = time.monotonic() - t
    info["wall_s"] += info["report_s"]
    info["memory_mb"] = report["memory_mb"]
    _write_marker(out, info)
    from rich.console import Console

    _save_view(out, seqs, Console())


def _save_view(out: Path, seqs: dict[str, Path], console: Any) -> None:
    """RUN/demo.rrd, the replay `cpslam view RUN --save` makes, when rerun-sdk is installed."""
    from cpslam.tools.view import RerunMissingError
    from cpslam.tools.view.cli import save_replay

    path = out / "demo.rrd"
    try:
        save_replay(out, path, sequences=seqs)
    except RerunMissingError as err:
        console.print(f"3-D view: skipped ({err})", soft_wrap=True)
        return
    console.print(f"3-D view ({path.stat().st_size / 1e6:.1f} MB): rerun {path}",
                  soft_wrap=True)


def _interrupt(_signum: int, _frame: object) -> None:
    raise KeyboardInterrupt


def _write_marker(out: Path, info: dict) -> None:
    from cpslam.common.rundir import SCHEMA_VERSION, write_json

    write_json(out / MARKER, {"schema_version": SCHEMA_VERSION, **info})  # atomically

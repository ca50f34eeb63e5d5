"""`cpslam-server`: the collaboration back end as a daemon on a Zenoh endpoint.

The server hosts the Zenoh endpoint itself (no separate router), tracks agents by liveliness,
runs the back end and answers status queries. Everything it accepts is persisted (fsynced,
by a writer thread) under the run folder before it is acknowledged (``server_state.pt``, the
previous generation in ``server_state.pt.prev``), so a server restarted with the same
``--out`` goes on where it stopped and agents resend only what was never acknowledged; a full
disk holds the acks and is retried, it does not stop the server.
SIGINT, SIGTERM or a finalise request (`cpslam finalise`) run the final pose graph and
refinement, write the outputs and exit 0; a second signal exits at once (code 130, without
finalising), except the same signal again within `REPEAT_WINDOW_S` of the first: wrappers
that signal the whole process group (`timeout`, some supervisors) deliver it twice.
"""

from __future__ import annotations

import logging
import signal
import threading
from pathlib import Path
from typing import Annotated

import typer

from cpslam.common.cli import App, ExitCode, fail, out_option, signal_handler
from cpslam.common.config.cli import (
    ConfigOpt,
    ConnectOpt,
    DeviceOpt,
    PresetOpt,
    SeedOpt,
    SessionOpt,
    SetOpt,
)

logger = logging.getLogger("cpslam.server")

app = App()

STATE_FILE = "server_state.pt"
REPEAT_WINDOW_S = 1.0
"""The same signal again within this many seconds of the first is the same request
delivered twice (to the process and to its process group), not a second request."""


@app.command()
def server(
    ctx: typer.Context,
    listen: Annotated[
        list[str] | None,
        typer.Option("--listen", help="Endpoint to listen on (repeatable; default "
                     "tcp/0.0.0.0:7447, or transport.listen)."),
    ] = None,
    connect: ConnectOpt = None,
    session: SessionOpt = None,
    preset: PresetOpt = "cpu",
    config_file: ConfigOpt = None,
    sets: SetOpt = None,
    device: DeviceOpt = None,
    seed: SeedOpt = None,
    out: Annotated[Path | None, out_option(
        "Run folder (default: run.out/run.name, timestamped). An existing folder with a "
        "server_state.pt is resumed.")] = None,
    persist_every: Annotated[
        float, typer.Option("--persist-every", min=0.0,
                            help="Seconds between state writes (acks wait for the write).")
    ] = 1.0,
    persist_log_every: Annotated[
        float, typer.Option("--persist-log-every", min=0.0,
                            help="While state writes fail (full disk), one error line per this "
                            "many seconds; acks stay held and the write is retried.")
    ] = 60.0,
    report: Annotated[
        bool, typer.Option("--report/--no-report",
                           help="After finalising, run cpslam report on the run folder when "
                           "every agent's recorded sequence there has ground truth.")
    ] = True,
) -> None:
    """Run the collaboration server: loops, group merges, federated decoders, pose graph.

    Agents connect with `cpslam-agent --connect tcp/HOST:PORT`. Outputs (on SIGINT, SIGTERM or
    `cpslam finalise`): RUN/trajectories/, fused_map.ply, pose_graph.g2o, metrics.json,
    server.log; when the agents share RUN and their sequences have ground truth, the report
    of cpslam report (report.json, plots/, mesh.ply; --no-report: not). A second signal
    during finalisation exits at once with code 130 without finalising (the state file is
    kept); the same signal repeated within 1 s is ignored, as wrappers such as `timeout`
    that signal the whole process group deliver it twice. Torch
    uses every core this process may use (run.num_threads: auto); with agents on the same
    machine, give each process its share (--set run.num_threads=1 on two cores).

    Examples:

      cpslam-server --out runs/lab

      cpslam-server --listen tcp/0.0.0.0:7447 --session lab --preset cpu --out runs/lab

      cpslam-server --listen tcp/0.0.0.0:7447 --connect tcp/router.local:7447

      cpslam-server --out runs/lab -q
    """
    from cpslam.common.bus import BusError, bus_from_config
    from cpslam.common.cli import verbosity
    from cpslam.common.config import save_config
    from cpslam.common.config.cli import config_or_exit, transport_sets
    from cpslam.common.device import configure_torch
    from cpslam.common.logs import log_to_file, setup_logging
    from cpslam.common.rundir import create_run_dir

    setup_logging(verbosity(ctx), daemon=True)
    cfg = config_or_exit(preset, config_file, [*(sets or []), *transport_sets(
        session, listen, connect)], device, seed)
    if cfg.transport.backend != "zenoh":
        fail("cpslam-server needs transport.backend zenoh (the in-memory bus is for "
             "`cpslam run`)")
    run_dir = out if out is not None else create_run_dir(cfg.run.out, cfg.run.name)
    run_dir.mkdir(parents=True, exist_ok=True)
    log_to_file(run_dir / "server.log")
    save_config(cfg, run_dir / "config.yaml")
    threads = configure_torch(cfg.run.num_threads, cfg.run.deterministic)
    logger.info("torch CPU threads: %d", threads)

    from cpslam.server.node import ServerNode

    stop = threading.Event()
    _on_signals(stop)
    try:
        bus = bus_from_config(cfg.transport, "server", limits=cfg.limits)
    except (BusError, ValueError) as err:
        fail(f"cannot open the server endpoint: {err}", ExitCode.ERROR)
    with bus:
        try:
            # Loops are verified on a worker thread: acks and updates flow while loops queue up.
            node = ServerNode(cfg, bus, run_dir, state_path=run_dir / STATE_FILE,
                              persist_every_s=persist_every,
                              persist_log_every_s=persist_log_every,
                              verify_in_background=True).start()
        except RuntimeError as err:
            fail(str(err), ExitCode.ERROR)
        logger.info("server listening on %s (session %s, preset %s) -> %s",
                    ", ".join(bus.listen) or "-", cfg.transport.session, preset, run_dir)
        try:
            result = node.run(stop=stop)
        finally:
            node.close()
    if result is None:
        logger.info("shut down without finalising; state kept in %s", run_dir / STATE_FILE)
        return
    logger.info("finalised: agents %s -> %s", ", ".join(a.agent_id for a in result.agents),
                run_dir)
    if report:
        _report(run_dir)


def _report(run_dir: Path) -> None:
    """`cpslam report RUN --if-ground-truth` in a process of its own: the report (plots,
    mesh) belongs to the offline tools, which the daemon does not import, and its memory
    is not the server's. A failed report is logged; the run itself succeeded."""
    import subprocess
    import sys

    cmd = [sys.executable, "-m", "cpslam", "report", str(run_dir), "--if-ground-truth",
           "--no-progress"]
    logger.info("report: %s", " ".join(cmd))
    code = subprocess.call(cmd)
    if code != 0:
        logger.warning("report of %s failed with exit code %d (run `cpslam report %s` to "
                       "retry)", run_dir, code, run_dir)


def _on_signals(stop: threading.Event) -> None:
    """First SIGINT/SIGTERM: finish cleanly (final pose graph, outputs); second: exit now."""
    handler = signal_handler(stop, window_s=REPEAT_WINDOW_S, action="finalising")
    signal.signal(signal.SIGINT, handler)
    signal.signal(signal.SIGTERM, handler)


def main() -> None:
    app()


if __name__ == "__main__":
    main()

"""Talking to a running server: `cpslam status` and `cpslam finalise`.

Both open a short-lived Zenoh client session to the server's endpoint, like an agent, but
declare no liveliness token: they are not agents.
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from cpslam.common.cli import ExitCode, JsonOpt, fail
from cpslam.common.config.cli import ConfigOpt, ConnectOpt, SessionOpt

if TYPE_CHECKING:
    from cpslam.common.bus import Bus

logger = logging.getLogger(__name__)

TimeoutOpt = Annotated[
    float, typer.Option("--timeout", min=0.1, help="Seconds to wait for the server.")
]


def status(
    connect: ConnectOpt = None,
    session: SessionOpt = None,
    as_json: JsonOpt = False,
    timeout: TimeoutOpt = 10.0,
    config_file: ConfigOpt = None,
) -> None:
    """Print a running server's agents, groups, loops and federated rounds.

    Exits 3 when no server answers within --timeout (docs/cli.md, exit codes).

    Examples:

      cpslam status --connect tcp/127.0.0.1:7447

      cpslam status --connect tcp/10.0.0.5:7447 --session lab --json

      cpslam status --config secure/operator.yaml
    """
    cfg, bus = _client(connect, session, timeout, config_file)
    with bus:
        summary = query_status(bus, cfg.transport.session, timeout)
    if summary is None:
        fail(f"no cpslam-server answered on session {cfg.transport.session!r} within "
             f"{timeout:.0f} s", ExitCode.NO_SERVER)
    if as_json:
        from cpslam.common.rundir import SCHEMA_VERSION

        typer.echo(json.dumps({"schema_version": SCHEMA_VERSION, **summary}, indent=2,
                              sort_keys=True))
    else:
        typer.echo(format_status(summary))


def query_status(bus: Bus, session: str, timeout_s: float = 1.0) -> dict | None:
    """The server's status summary over `bus`, or None when no valid answer came in time
    (a malformed reply is logged and skipped)."""
    from cpslam import protocol
    from cpslam.protocol import ProtocolError, Status, keys

    for reply in bus.query(keys.server_status(session), timeout_s=timeout_s):
        if not reply.ok:
            continue
        try:
            return protocol.decode(reply.payload, expected=Status).summary
        except ProtocolError as err:
            logger.warning("malformed status reply: %s", err)
    return None


def finalise(
    connect: ConnectOpt = None,
    session: SessionOpt = None,
    shutdown: Annotated[bool, typer.Option(
        "--shutdown", help="Stop without the final optimisation and outputs (state is kept).")
    ] = False,
    wait: Annotated[bool, typer.Option(
        "--wait/--no-wait", help="Wait until the server has finished and left.")] = True,
    timeout: TimeoutOpt = 600.0,
    config_file: ConfigOpt = None,
) -> None:
    """Ask a running server to finish: final pose graph, refinement, outputs, exit.

    Exits 3 when no server is found, 1 when it is still running after --timeout.

    Examples:

      cpslam finalise --connect tcp/127.0.0.1:7447

      cpslam finalise --connect tcp/10.0.0.5:7447 --session lab --no-wait

      cpslam finalise --config secure/operator.yaml --connect tls/10.0.0.5:7447
    """
    import threading

    from cpslam import protocol
    from cpslam.protocol import Control, keys

    cfg, bus = _client(connect, session, min(timeout, 30.0), config_file)
    s = cfg.transport.session
    present, gone = threading.Event(), threading.Event()
    with bus:
        watch = bus.watch_liveliness(keys.alive_servers(s), on_join=lambda _k: present.set(),
                                     on_leave=lambda _k: gone.set())
        if not present.wait(min(timeout, 10.0)):
            watch.close()
            fail(f"no cpslam-server on session {s!r}", ExitCode.NO_SERVER)
        action = "shutdown" if shutdown else "finalise"
        bus.publish(keys.server_control(s), protocol.encode(
            Control(action=action, reason="cpslam finalise")))
        typer.echo(f"asked the server to {action}")
        t0 = time.monotonic()
        if wait and not gone.wait(timeout):
            watch.close()
            fail(f"the server was still running after {timeout:.0f} s", ExitCode.ERROR)
        watch.close()
    if wait:
        typer.echo(f"server finished in {time.monotonic() - t0:.1f} s")


def format_status(summary: dict) -> str:
    """The status summary as a few human-readable lines."""
    lines = []
    agents = summary.get("agents", {})
    lines.append(f"agents ({len(agents)}):")
    for aid, a in sorted(agents.items()):
        lines.append(f"  {aid:<12} {'alive' if a.get('alive') else 'gone ':<6} keyframes "
                     f"{a.get('keyframes', 0):>5}  frames {a.get('frames', 0):>6}  points "
                     f"{a.get('points', 0):>8}  received {a.get('bytes', 0) / 1e6:8.2f} MB")
    groups = summary.get("groups", {})
    lines.append(f"groups ({len(groups)}):")
    for gid, g in sorted(groups.items()):
        lines.append(f"  {gid:<12} members {', '.join(g.get('members', []))}  round "
                     f"{g.get('round', 0)}")
    loops = summary.get("loops", {})
    lines.append(f"loops: found {loops.get('found', 0)}, accepted {loops.get('accepted', 0)}, "
                 f"rejected {loops.get('rejected', 0)}, pending {loops.get('pending', 0)}, "
                 f"retrying {loops.get('retrying', 0)}")
    rounds = summary.get("rounds", {})
    lines.append(f"federated rounds: closed {rounds.get('closed', 0)}, open "
                 f"{len(rounds.get('open', []))}; merges {summary.get('merges', 0)}")
    return "\n".join(lines)


def _client(connect: list[str] | None, session: str | None, timeout: float,
            config_file: Path | None = None):
    """The config (defaults + --config + environment + flags) and an open client bus; exits 3
    when no server is reachable, 2 on a bad setting (e.g. a missing certificate)."""
    from cpslam.common.bus import open_client
    from cpslam.common.config.cli import config_or_exit, transport_sets

    cfg = config_or_exit("cpu", config_file, [*transport_sets(session, None, connect),
                                              f"transport.open_timeout_s={max(timeout, 0.5)}"])
    try:
        bus = open_client(cfg.transport, timeout, "client")
    except ValueError as err:
        fail(f"transport: {err}")
    if bus is None:
        where = ", ".join(cfg.transport.connect) or "tcp/127.0.0.1:7447"
        fail(f"cannot reach a server at {where}", ExitCode.NO_SERVER)
    return cfg, bus

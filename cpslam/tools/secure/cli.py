"""`cpslam secure init`."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from cpslam.common.cli import OverwriteOpt, check_output, fail, out_option


def init(
    out: Annotated[Path, out_option("Folder for the certificates, keys, ACL and overlays.")],
    agents: Annotated[int, typer.Option(
        help="Agents, with ids agent-0 … agent-<N-1> (ignored when --agent-id is given).",
        min=1)] = 2,
    agent_id: Annotated[list[str] | None, typer.Option(
        "--agent-id", help="An agent id (repeatable), instead of --agents.")] = None,
    operator: Annotated[str, typer.Option(
        help="Name of the operator certificate (status, finalise, shutdown).")] = "operator",
    server_name: Annotated[list[str] | None, typer.Option(
        "--server-name", help="DNS name or IP address agents use to reach the server "
        "(repeatable; the first goes into the overlays' endpoints). Default: localhost, "
        "127.0.0.1.")] = None,
    port: Annotated[int, typer.Option(help="The server's TLS port.", min=1, max=65535)
                    ] = 7447,
    session: Annotated[str, typer.Option(
        help="Session the ACL covers and the overlays set; '*' = any session.")] = "*",
    days: Annotated[int, typer.Option(help="Validity of the certificates (days).", min=1)
                    ] = 365,
    install_dir: Annotated[Path | None, typer.Option(
        "--install-dir", help="Folder the files will live in on the machines; the overlays "
        "name files there (default: --out).")] = None,
    overwrite: OverwriteOpt = False,
) -> None:
    """Make a CA, a server certificate, one certificate per agent and one for the operator,
    the server's Zenoh access control and a config overlay per role.

    Each agent's certificate (common name = its agent id) may only publish its own messages,
    serve its own images and hold its own presence token; only the operator's may query the
    status and finalise. Start each process with its overlay (--config OUT/<role>.yaml) and,
    for agents, --agent-id equal to the certificate's name. Keep ca-key.pem off the machines.
    Layout and two-machine recipe: docs/deployment.md.

    Examples:

      cpslam secure init --agents 2 --out secure

      cpslam secure init --agent-id robot-1 --agent-id robot-2 --server-name 10.0.0.5
      --install-dir /etc/cpslam --out secure

      cpslam-server --config secure/server.yaml --out runs/lab

      cpslam-agent --config secure/agent-0.yaml --agent-id agent-0 --seq data/office
    """
    from cpslam.tools.secure.bundle import write_bundle

    check_output(out, overwrite)
    ids = list(agent_id) if agent_id else [f"agent-{i}" for i in range(agents)]
    names = tuple(server_name) if server_name else ("localhost", "127.0.0.1")
    try:
        bundle = write_bundle(out, ids, operator=operator, server_names=names, port=port,
                              session=session, days=days, install_dir=install_dir)
    except ValueError as exc:
        fail(str(exc))
    for role, path in bundle.overlays.items():
        typer.echo(f"{role}: --config {path}")

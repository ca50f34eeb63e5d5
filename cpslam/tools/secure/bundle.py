"""Write a deployment's security files: CA, certificates, access control, config overlays.

Layout of the output folder (``<id>`` for every agent id and the operator's name)::

    ca.pem            CA certificate: every machine needs it
    ca-key.pem        CA key: only to issue more certificates; keep it off the machines
    server.pem        server certificate (names: --server-name) and server-key.pem
    <id>.pem          client certificate, common name <id>, and <id>-key.pem
    acl.json5         Zenoh access_control for the server (cpslam.tools.secure.acl)
    server.yaml       cpslam config overlay of the server: tls listener, mTLS, the ACL
    <id>.yaml         cpslam config overlay of an agent or the operator: tls connect, mTLS

The overlays name the files under `install_dir`, the folder they will live in on the machines.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from cpslam.protocol import keys
from cpslam.tools.secure import certs
from cpslam.tools.secure.acl import ANY_SESSION, access_control

__all__ = ["Bundle", "write_bundle"]

SERVER_CN = "cpslam-server"
"""Common name of the server certificate (clients check its names, not this)."""


@dataclass(frozen=True)
class Bundle:
    """What `write_bundle` wrote: the overlays by role name and every file."""

    overlays: dict[str, Path]
    files: list[Path]


def write_bundle(
    out: Path,
    agent_ids: list[str],
    operator: str = "operator",
    server_names: tuple[str, ...] = ("localhost", "127.0.0.1"),
    port: int = 7447,
    session: str = ANY_SESSION,
    days: int = 365,
    install_dir: Path | None = None,
) -> Bundle:
    """Make the CA, the certificates, the ACL and one config overlay per role in `out`.

    Args:
        agent_ids: one client certificate each; its common name is the agent id.
        operator: common name of the certificate allowed to query status and finalise.
        server_names: DNS names / IP addresses in the server certificate; the first is the
            host in the agents' and the operator's connect endpoint.
        port: the server's TLS port.
        session: the session the ACL covers; `ANY_SESSION` = every session.
        days: validity of every certificate.
        install_dir: where the files will be on the machines (default: `out`, absolute).
    """
    if not agent_ids:
        raise ValueError("at least one agent id is needed")
    if not server_names:
        raise ValueError("the server certificate needs at least one name")
    if not 1 <= port <= 65535:
        raise ValueError(f"port must be in [1, 65535], got {port}")
    if days < 1:
        raise ValueError(f"days must be at least 1, got {days}")
    # Also checks the names (ids, distinct) before anything is written.
    acl = access_control(session, agent_ids, [operator])
    if SERVER_CN in (*agent_ids, operator):
        raise ValueError(f"{SERVER_CN!r} is the server's certificate name")
    out.mkdir(parents=True, exist_ok=True)
    where = (install_dir if install_dir is not None else out).absolute()
    files: list[Path] = []
    ca = certs.new_authority("cpslam CA", days)
    files += _write_pair(out, "ca", ca.cert, ca.key)
    server = certs.issue(ca, SERVER_CN, list(server_names), server=True, days=days)
    files += _write_pair(out, "server", server.cert, server.key)
    for name in (*agent_ids, operator):
        issued = certs.issue(ca, name, [name], server=False, days=days)
        files += _write_pair(out, name, issued.cert, issued.key)
    acl_path = out / "acl.json5"
    acl_path.write_text("// Zenoh access_control of the cpslam server (cpslam secure init)\n"
                        + json.dumps(acl, indent=2) + "\n", encoding="utf-8")
    files.append(acl_path)
    host = server_names[0]
    host = f"[{host}]" if ":" in host else host
    overlays = {"server": _overlay(out, where, "server", {
        "listen": [f"tls/0.0.0.0:{port}"], "access_control": str(where / "acl.json5")},
        session)}
    for name in (*agent_ids, operator):
        overlays[name] = _overlay(out, where, name, {"connect": [f"tls/{host}:{port}"]},
                                  session)
    files.extend(overlays.values())
    return Bundle(overlays, files)


def _write_pair(out: Path, name: str, cert: Any, key: Any) -> list[Path]:
    cert_path, key_path = out / f"{name}.pem", out / f"{name}-key.pem"
    certs.write_cert(cert, cert_path)
    certs.write_key(key, key_path)
    return [cert_path, key_path]


def _overlay(out: Path, where: Path, name: str, extra: dict[str, Any], session: str) -> Path:
    transport: dict[str, Any] = {
        **extra,
        "tls_root_ca": str(where / "ca.pem"),
        "tls_cert": str(where / f"{name}.pem"),
        "tls_key": str(where / f"{name}-key.pem"),
        "tls_mtls": True,
    }
    if session != ANY_SESSION:
        transport["session"] = keys.check_id(session, "session")
    path = out / f"{name}.yaml"
    path.write_text(f"# cpslam transport overlay for {name} (cpslam secure init): --config "
                    f"{path.name}\n" + yaml.safe_dump({"transport": transport}, sort_keys=False),
                    encoding="utf-8")
    return path

"""Multi-host: the server and each agent in their own Linux network namespace.

Each agent namespace is joined to the server's by its own veth pair and subnet, so the traffic
crosses real (virtual) interfaces with their own addresses, as between machines. Needs root
(CAP_NET_ADMIN) and iproute2; skipped with the reason otherwise.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

import pytest
from daemons import Daemon, agent_args, server_args, tum_rows

pytestmark = [pytest.mark.loopback, pytest.mark.slow]
pytest.importorskip("open3d")

PORT = 7447
AGENTS = ("0", "1")


def _ip(*args: str) -> None:
    subprocess.run(["ip", *args], check=True, capture_output=True, text=True)


@pytest.fixture
def namespaces():
    """{"server": ns, "0": ns, "1": ns} and the server's address as seen by each agent."""
    if shutil.which("ip") is None:
        pytest.skip("iproute2 (`ip`) is not installed")
    tag = f"cps{os.getpid() % 100000}"
    names = {"server": f"{tag}s", **{a: f"{tag}a{a}" for a in AGENTS}}
    made: list[str] = []
    try:
        for ns in names.values():
            _ip("netns", "add", ns)
            made.append(ns)
            _ip("-n", ns, "link", "set", "lo", "up")
    except subprocess.CalledProcessError as err:
        for ns in made:
            subprocess.run(["ip", "netns", "del", ns], capture_output=True)
        pytest.skip(f"cannot create network namespaces here ({err.stderr.strip()}); "
                    "needs root / CAP_NET_ADMIN")
    addresses = {}
    try:
        for i, a in enumerate(AGENTS, start=1):
            srv_if, ag_if = f"{tag}v{a}s", f"{tag}v{a}a"
            _ip("link", "add", srv_if, "type", "veth", "peer", "name", ag_if)
            _ip("link", "set", srv_if, "netns", names["server"])
            _ip("link", "set", ag_if, "netns", names[a])
            _ip("-n", names["server"], "addr", "add", f"10.77.{i}.1/24", "dev", srv_if)
            _ip("-n", names[a], "addr", "add", f"10.77.{i}.2/24", "dev", ag_if)
            _ip("-n", names["server"], "link", "set", srv_if, "up")
            _ip("-n", names[a], "link", "set", ag_if, "up")
            addresses[a] = (f"10.77.{i}.1", srv_if)
        yield names, addresses
    finally:
        for ns in made:  # deleting a namespace removes its veth ends
            subprocess.run(["ip", "netns", "del", ns], capture_output=True)


def _rx_bytes(ns: str, dev: str) -> int:
    out = subprocess.run(["ip", "netns", "exec", ns, "cat",
                          f"/sys/class/net/{dev}/statistics/rx_bytes"],
                         check=True, capture_output=True, text=True)
    return int(out.stdout)


def test_server_and_agents_in_separate_network_namespaces(tmp_path: Path, namespaces) -> None:
    from cpslam.common.synth import generate

    names, addresses = namespaces
    data = generate(tmp_path / "apt", scene="apartment", agents=2, frames=40, width=160,
                    height=120, seed=3)
    out, s = tmp_path / "run", "netns"
    in_ns = lambda ns: ["ip", "netns", "exec", ns]  # noqa: E731
    server = Daemon("server", server_args(f"tcp/0.0.0.0:{PORT}", s, out), tmp_path,
                    prefix=in_ns(names["server"]))
    agents = [Daemon(f"agent{a}", agent_args(data.agent_dirs[int(a)], a,
                                             f"tcp/{addresses[a][0]}:{PORT}", s, out),
                     tmp_path, prefix=in_ns(names[a])) for a in AGENTS]
    try:
        for agent in agents:
            assert agent.wait(600) == 0, agent.tail() + "\n" + server.tail()
        # The agents cannot reach each other, only the server: nothing is routed between
        # their subnets.
        server.signal()  # SIGTERM: finalise and exit 0
        assert server.wait(180) == 0, server.tail()
    finally:
        for d in (server, *agents):
            d.kill()
    for a in AGENTS:
        assert tum_rows(out / "trajectories" / f"agent_{a}_global.tum") == 40
        sent = json.loads((out / f"agent_{a}" / "metrics.json").read_text())["bus"]
        payload = sum(v["bytes"] for v in sent["sent"].values())
        # Everything the agent published went through the server's end of its veth.
        assert _rx_bytes(names["server"], addresses[a][1]) >= payload > 0
    assert "finalised" in server.text()

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
import sys
import time
from pathlib import Path

import pytest
from daemons import ENV, Daemon, agent_args, server_args, tum_rows, wait_until

from cpslam.tools import netns

pytestmark = [pytest.mark.loopback, pytest.mark.slow]
pytest.importorskip("open3d")

PORT = 7447
AGENTS = ("0", "1")


@pytest.fixture
def net():
    """The server's and both agents' namespaces (a `cpslam.tools.netns.Network`), removed at
    teardown."""
    if shutil.which("ip") is None:
        pytest.skip("iproute2 (`ip`) is not installed")
    try:
        network = netns.create(f"cps{os.getpid() % 100000}", AGENTS)
    except netns.NetnsError as err:
        pytest.skip(f"cannot set up network namespaces here ({err}); needs root / "
                    "CAP_NET_ADMIN and veth support")
    try:
        yield network
    finally:
        network.remove()


def test_a_failing_set_up_step_undoes_what_was_made(monkeypatch) -> None:
    calls: list[tuple[str, ...]] = []

    def fake_ip(*args: str, check: bool = True) -> None:
        calls.append(args)
        if args[:2] == ("-n", "ts") and "addr" in args:  # the first address fails
            raise netns.NetnsError("`ip addr add` failed: Operation not permitted")

    monkeypatch.setattr(netns, "_ip", fake_ip)
    with pytest.raises(netns.NetnsError, match="Operation not permitted"):
        netns.create("t", AGENTS)
    assert ("link", "add", "tv0s", "type", "veth", "peer", "name", "tv0a") in calls
    # What was made is removed, newest first.
    assert calls[-4:] == [("link", "del", "tv0s"), ("netns", "del", "ta1"),
                          ("netns", "del", "ta0"), ("netns", "del", "ts")]


def _rx_bytes(net: netns.Network, dev: str) -> int:
    """Bytes received by interface `dev` of the server's namespace."""
    out = subprocess.run([*net.prefix("server"), "cat",
                          f"/sys/class/net/{dev}/statistics/rx_bytes"],
                         check=True, capture_output=True, text=True)
    return int(out.stdout)


def _start(tmp_path: Path, net: netns.Network, frames: int, seed: int, session: str):
    """Render a two-agent apartment, then start the server and both agents, each in its own
    namespace: (server, agents, run folder)."""
    from cpslam.tools.synth import generate

    data = generate(tmp_path / "apt", scene="apartment", agents=2, frames=frames, width=160,
                    height=120, seed=seed)
    out = tmp_path / "run"
    server = Daemon("server", server_args(f"tcp/0.0.0.0:{PORT}", session, out, "--no-report"),
                    tmp_path, prefix=net.prefix("server"))
    agents = [Daemon(f"agent{a}", agent_args(data.agent_dirs[int(a)], a,
                                             f"tcp/{net.links[a].server_ip}:{PORT}", session,
                                             out),
                     tmp_path, prefix=net.prefix(a)) for a in AGENTS]
    return server, agents, out


def test_server_and_agents_in_separate_network_namespaces(tmp_path: Path, net) -> None:
    server, agents, out = _start(tmp_path, net, frames=40, seed=3, session="netns")
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
        assert _rx_bytes(net, net.links[a].server_if) >= payload > 0
    assert "finalised" in server.text()


def _server_status(net: netns.Network, session: str) -> dict:
    """`cpslam status --json` asked from inside the server's namespace ({} if no answer)."""
    done = subprocess.run([*net.prefix("server"), sys.executable, "-m", "cpslam", "status",
                           "--connect", f"tcp/127.0.0.1:{PORT}", "--session", session, "--json",
                           "--timeout", "10"], capture_output=True, text=True, env=ENV,
                          timeout=60)
    return json.loads(done.stdout) if done.returncode == 0 else {}


PARTITION_S = 10.0


def test_partition_heals_with_nothing_lost(tmp_path: Path, net) -> None:
    """Agent 0's link to the server goes down for 10 s mid-stream (its veth end set down, so
    packets vanish as on a cut cable); when it heals, everything reaches the server: every
    frame pose is in the final trajectories and nothing is left unacknowledged."""
    frames, s = 60, "partition"
    server, agents, out = _start(tmp_path, net, frames=frames, seed=4, session=s)
    try:
        wait_until("agent 0's first keyframes at the server", lambda: _server_status(net, s)
                   .get("agents", {}).get("0", {}).get("keyframes", 0) >= 1,
                   600, server, *agents)
        net.partition("0")
        time.sleep(PARTITION_S)
        net.heal("0")
        for agent in agents:
            assert agent.wait(600) == 0, agent.tail() + "\n" + server.tail()
        server.signal()  # SIGTERM: finalise and exit 0
        assert server.wait(180) == 0, server.tail()
    finally:
        for d in (server, *agents):
            d.kill()
    for a in AGENTS:
        assert tum_rows(out / "trajectories" / f"agent_{a}_global.tum") == frames, a
        metrics = json.loads((out / f"agent_{a}" / "metrics.json").read_text())
        assert metrics["unacknowledged"] == 0, a
    # The partition outlasts the Zenoh lease (transport.lease_s, 3 s): the session was torn
    # down and rebuilt, and what was in flight was resent, not carried over by TCP.
    agent0 = json.loads((out / "agent_0" / "metrics.json").read_text())
    assert agent0["server_rejoins"] >= 1
    assert "server is back; resent" in agents[0].text()

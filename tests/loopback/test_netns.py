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

pytestmark = [pytest.mark.loopback, pytest.mark.slow]
pytest.importorskip("open3d")

PORT = 7447
AGENTS = ("0", "1")


class SetupFailed(Exception):
    """A set-up step failed; the message says which and why."""


def _ip(*args: str) -> None:
    try:
        subprocess.run(["ip", *args], check=True, capture_output=True, text=True, timeout=30)
    except subprocess.CalledProcessError as err:
        why = (err.stderr or err.stdout or "").strip() or f"exit code {err.returncode}"
        raise SetupFailed(f"`ip {' '.join(args)}` failed: {why}") from None
    except (OSError, subprocess.TimeoutExpired) as err:
        raise SetupFailed(f"`ip {' '.join(args)}` could not run: {err}") from None


def build_namespaces(tag: str, undo: list[list[str]]) -> tuple[dict, dict]:
    """Create the server's and each agent's namespace, joined by veth pairs with their own
    subnets. Every step that creates something appends the `ip` arguments that remove it to
    `undo` (run newest first by the caller, whatever happened); a failing step raises
    `SetupFailed`."""
    names = {"server": f"{tag}s", **{a: f"{tag}a{a}" for a in AGENTS}}
    for ns in names.values():
        _ip("netns", "add", ns)
        undo.append(["netns", "del", ns])  # deleting a namespace removes the veth ends in it
        _ip("-n", ns, "link", "set", "lo", "up")
    _ip("netns", "exec", names["server"], "true")  # exec needs more rights than add
    addresses = {}
    for i, a in enumerate(AGENTS, start=1):
        srv_if, ag_if = f"{tag}v{a}s", f"{tag}v{a}a"
        _ip("link", "add", srv_if, "type", "veth", "peer", "name", ag_if)
        # Until both ends are moved the pair lives in this namespace: remove it by name.
        undo.append(["link", "del", srv_if])
        _ip("link", "set", srv_if, "netns", names["server"])
        _ip("link", "set", ag_if, "netns", names[a])
        _ip("-n", names["server"], "addr", "add", f"10.77.{i}.1/24", "dev", srv_if)
        _ip("-n", names[a], "addr", "add", f"10.77.{i}.2/24", "dev", ag_if)
        _ip("-n", names["server"], "link", "set", srv_if, "up")
        _ip("-n", names[a], "link", "set", ag_if, "up")
        addresses[a] = (f"10.77.{i}.1", srv_if)
    return names, addresses


def remove(undo: list[list[str]]) -> None:
    """Run the undo steps, newest first; what is already gone is no error."""
    for args in reversed(undo):
        subprocess.run(["ip", *args], capture_output=True, timeout=30)
    undo.clear()


@pytest.fixture
def namespaces():
    """{"server": ns, "0": ns, "1": ns} and the server's address as seen by each agent."""
    if shutil.which("ip") is None:
        pytest.skip("iproute2 (`ip`) is not installed")
    undo: list[list[str]] = []
    try:
        names, addresses = build_namespaces(f"cps{os.getpid() % 100000}", undo)
    except SetupFailed as err:
        remove(undo)
        pytest.skip(f"cannot set up network namespaces here ({err}); needs root / "
                    "CAP_NET_ADMIN and veth support")
    try:
        yield names, addresses
    finally:
        remove(undo)


def test_a_failing_set_up_step_undoes_what_was_made(monkeypatch) -> None:
    calls: list[tuple[str, ...]] = []

    def fake_ip(*args: str) -> None:
        calls.append(args)
        if args[:2] == ("-n", "ts") and "addr" in args:  # the first address fails
            raise SetupFailed("`ip addr add` failed: Operation not permitted")

    monkeypatch.setattr(sys.modules[__name__], "_ip", fake_ip)
    undo: list[list[str]] = []
    with pytest.raises(SetupFailed, match="Operation not permitted"):
        build_namespaces("t", undo)
    assert undo == [["netns", "del", "ts"], ["netns", "del", "ta0"], ["netns", "del", "ta1"],
                    ["link", "del", "tv0s"]]
    assert ("link", "add", "tv0s", "type", "veth", "peer", "name", "tv0a") in calls


def _rx_bytes(ns: str, dev: str) -> int:
    out = subprocess.run(["ip", "netns", "exec", ns, "cat",
                          f"/sys/class/net/{dev}/statistics/rx_bytes"],
                         check=True, capture_output=True, text=True)
    return int(out.stdout)


def _start(tmp_path: Path, namespaces, frames: int, seed: int, session: str):
    """Render a two-agent apartment, then start the server and both agents, each in its own
    namespace: (server, agents, run folder)."""
    from cpslam.tools.synth import generate

    names, addresses = namespaces
    data = generate(tmp_path / "apt", scene="apartment", agents=2, frames=frames, width=160,
                    height=120, seed=seed)
    out = tmp_path / "run"
    in_ns = lambda ns: ["ip", "netns", "exec", ns]  # noqa: E731
    server = Daemon("server", server_args(f"tcp/0.0.0.0:{PORT}", session, out, "--no-report"),
                    tmp_path, prefix=in_ns(names["server"]))
    agents = [Daemon(f"agent{a}", agent_args(data.agent_dirs[int(a)], a,
                                             f"tcp/{addresses[a][0]}:{PORT}", session, out),
                     tmp_path, prefix=in_ns(names[a])) for a in AGENTS]
    return server, agents, out


def test_server_and_agents_in_separate_network_namespaces(tmp_path: Path, namespaces) -> None:
    names, addresses = namespaces
    server, agents, out = _start(tmp_path, namespaces, frames=40, seed=3, session="netns")
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


def _server_status(ns: str, session: str) -> dict:
    """`cpslam status --json` asked from inside the server's namespace ({} if no answer)."""
    done = subprocess.run(["ip", "netns", "exec", ns, sys.executable, "-m", "cpslam", "status",
                           "--connect", f"tcp/127.0.0.1:{PORT}", "--session", session, "--json",
                           "--timeout", "10"], capture_output=True, text=True, env=ENV,
                          timeout=60)
    return json.loads(done.stdout) if done.returncode == 0 else {}


PARTITION_S = 10.0


def test_partition_heals_with_nothing_lost(tmp_path: Path, namespaces) -> None:
    """Agent 0's link to the server goes down for 10 s mid-stream (its veth end set down, so
    packets vanish as on a cut cable); when it heals, everything reaches the server: every
    frame pose is in the final trajectories and nothing is left unacknowledged."""
    names, addresses = namespaces
    frames, s = 60, "partition"
    server, agents, out = _start(tmp_path, namespaces, frames=frames, seed=4, session=s)
    agent_if = addresses["0"][1][:-1] + "a"  # the agent's end of its veth pair
    try:
        wait_until("agent 0's first keyframes at the server", lambda: _server_status(
            names["server"], s).get("agents", {}).get("0", {}).get("keyframes", 0) >= 1,
            600, server, *agents)
        _ip("-n", names["0"], "link", "set", agent_if, "down")
        time.sleep(PARTITION_S)
        _ip("-n", names["0"], "link", "set", agent_if, "up")
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

"""Linux network namespaces for multi-host runs on one machine: the server and each agent in a
namespace of its own, each agent's joined to the server's by a veth pair on its own /24, so
traffic crosses real (virtual) interfaces with their own addresses, as between machines.

    net = netns.create("cps123", agents=("0", "1"))
    try:
        Popen([*net.prefix("server"), sys.executable, ...])  # listen on 0.0.0.0
        Popen([*net.prefix("0"), ..., f"tcp/{net.links['0'].server_ip}:7447"])
        net.partition("0"); ...; net.heal("0")
    finally:
        net.remove()

Needs root (CAP_NET_ADMIN), veth support and iproute2 (`ip`). Used by the namespace loopback
test and the partition fault of bench/faults.py.
"""

from __future__ import annotations

import subprocess
from collections.abc import Iterable
from dataclasses import dataclass, field


class NetnsError(RuntimeError):
    """An `ip` step failed; the message says which and why."""


@dataclass(frozen=True)
class Link:
    """One agent's veth pair: the end in the server's namespace and the end in the agent's."""

    server_if: str
    agent_if: str
    server_ip: str
    agent_ip: str


@dataclass
class Network:
    """Namespaces made by `create`: `names` maps "server" and each agent id to its namespace,
    `links` each agent id to its veth pair."""

    names: dict[str, str]
    links: dict[str, Link]
    # `ip` arguments that remove what was made, oldest first.
    undo: list[list[str]] = field(default_factory=list, repr=False)

    def prefix(self, who: str) -> list[str]:
        """The command prefix that runs a program in the namespace of `who` ("server" or an
        agent id)."""
        return ["ip", "netns", "exec", self.names[who]]

    def partition(self, agent: str) -> None:
        """Cut the agent off the server: its veth end goes down, so packets vanish as on a cut
        cable (no reset reaches either side)."""
        _ip("-n", self.names[agent], "link", "set", self.links[agent].agent_if, "down")

    def heal(self, agent: str) -> None:
        """Undo `partition`: the agent's veth end comes back up with its address."""
        _ip("-n", self.names[agent], "link", "set", self.links[agent].agent_if, "up")

    def remove(self) -> None:
        """Remove every namespace and veth pair made, newest first; what is already gone is no
        error, so this may run twice."""
        _remove(self.undo)


def create(tag: str, agents: Iterable[str], subnet: str = "10.77") -> Network:
    """Make the server's namespace `<tag>s` and agent a's `<tag>a<a>`, joined by veth pair
    `<tag>v<a>s`/`<tag>v<a>a`; the i-th agent's pair (from 1) is on `<subnet>.<i>.0/24`, the
    server at .1 and the agent at .2. `tag` keeps concurrent runs apart (interface names share
    the root namespace until moved, and are at most 15 characters). If a step fails, whatever
    was made is removed before `NetnsError` is raised."""
    agents = list(agents)
    names = {"server": f"{tag}s", **{a: f"{tag}a{a}" for a in agents}}
    net = Network(names, {})
    try:
        for ns in names.values():
            _ip("netns", "add", ns)
            net.undo.append(["netns", "del", ns])  # deleting a namespace removes its veth ends
            _ip("-n", ns, "link", "set", "lo", "up")
        _ip("netns", "exec", names["server"], "true")  # exec needs more rights than add
        for i, a in enumerate(agents, start=1):
            link = Link(f"{tag}v{a}s", f"{tag}v{a}a", f"{subnet}.{i}.1", f"{subnet}.{i}.2")
            _ip("link", "add", link.server_if, "type", "veth", "peer", "name", link.agent_if)
            # Until both ends are moved the pair lives in this namespace: remove it by name.
            net.undo.append(["link", "del", link.server_if])
            _ip("link", "set", link.server_if, "netns", names["server"])
            _ip("link", "set", link.agent_if, "netns", names[a])
            _ip("-n", names["server"], "addr", "add", f"{link.server_ip}/24", "dev",
                link.server_if)
            _ip("-n", names[a], "addr", "add", f"{link.agent_ip}/24", "dev", link.agent_if)
            _ip("-n", names["server"], "link", "set", link.server_if, "up")
            _ip("-n", names[a], "link", "set", link.agent_if, "up")
            net.links[a] = link
    except NetnsError:
        net.remove()
        raise
    return net


def _remove(undo: list[list[str]]) -> None:
    for args in reversed(undo):
        _ip(*args, check=False)
    undo.clear()


def _ip(*args: str, check: bool = True) -> None:
    """Run `ip args`; with `check`, a failure raises `NetnsError`, otherwise it is ignored."""
    try:
        done = subprocess.run(["ip", *args], capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.TimeoutExpired) as err:
        if check:
            raise NetnsError(f"`ip {' '.join(args)}` could not run: {err}") from None
        return
    if check and done.returncode != 0:
        why = (done.stderr or done.stdout or "").strip() or f"exit code {done.returncode}"
        raise NetnsError(f"`ip {' '.join(args)}` failed: {why}")

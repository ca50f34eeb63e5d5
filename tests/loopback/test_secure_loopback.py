"""The daemons over Zenoh mutual TLS with the access control of `cpslam secure init`.

- a two-agent run merges over tls/ endpoints with each agent's own certificate;
- against a real server: a client without a certificate cannot connect; agent-1's certificate
  cannot publish as agent-0 (the server never sees it), forge agent-0's acks or updates, hold
  agent-0's presence token, query the status or finalise; the operator's certificate can.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest
from daemons import Daemon, agent_args, finalise, server_args, status, wait_until

from cpslam.common.bus import BusError, ZenohBus, ZenohSecurity, open_client
from cpslam.common.config import load_config
from cpslam.common.place_recognition import descriptor_dim
from cpslam.demo import free_port
from cpslam.protocol import Ack, Control, KeyframeMsg, encode, keys
from cpslam.server.client import query_status
from cpslam.tools.secure.bundle import write_bundle

pytestmark = [pytest.mark.loopback, pytest.mark.slow]

SESSION = "sec"
DESCRIPTOR_DIM = descriptor_dim(load_config("tiny", env={}).place_recognition)


@pytest.fixture(scope="module")
def bundle(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("secure") / "secure"
    write_bundle(out, ["agent-0", "agent-1"])
    return out


@pytest.fixture
def tls_endpoint() -> str:
    # "localhost" is a name in the server certificate, which the clients verify.
    return f"tls/localhost:{free_port()}"


def _client(bundle: Path, role: str, endpoint: str) -> ZenohBus:
    cfg = load_config("tiny", bundle / f"{role}.yaml", [f"transport.connect={endpoint}",
                                                        "transport.open_timeout_s=5"], env={})
    # Retried: the server may still be starting (importing torch).
    bus = open_client(cfg.transport, 120.0, role)
    assert isinstance(bus, ZenohBus), f"{role} could not connect to {endpoint}"
    return bus


def _keyframe(agent: str, seq: int) -> bytes:
    # Orthogonal descriptors per agent: no loop candidate, so no image queries.
    # The server checks the length against its own (tiny) config.
    descriptor = np.zeros(DESCRIPTOR_DIM, np.float32)
    descriptor[int(agent[-1])] = 1.0
    return encode(KeyframeMsg(agent_id=agent, seq=seq, kf_id=seq, frame_index=seq,
                              stamp=float(seq), T_world_cam=np.eye(4), descriptor=descriptor))


def _agents(bus: ZenohBus) -> dict:
    summary = query_status(bus, SESSION, timeout_s=2.0)
    assert summary is not None, "the operator got no status"
    return summary.get("agents", {})


def test_two_agents_merge_over_mutual_tls(tmp_path: Path, tls_endpoint: str, bundle: Path,
                                          apartment, daemons) -> None:
    out, ep = tmp_path / "run", tls_endpoint
    server = Daemon("server", server_args(ep, SESSION, out, "--config",
                                          str(bundle / "server.yaml")), tmp_path)
    daemons.append(server)
    agents = [Daemon(f"agent{a}", agent_args(
        apartment.agent_dirs[a], f"agent-{a}", ep, SESSION, out, "--frames", "0:300:3",
        "--config", str(bundle / f"agent-{a}.yaml")), tmp_path) for a in (0, 1)]
    daemons.extend(agents)
    for agent in agents:
        assert agent.wait(600) == 0, agent.tail() + "\n" + server.tail()
    operator = ("--config", str(bundle / "operator.yaml"))
    summary = status(ep, SESSION, 10.0, *operator)
    assert summary is not None, server.tail()
    assert sorted(summary["agents"]) == ["agent-0", "agent-1"]
    finalise(ep, SESSION, 180.0, *operator)
    assert server.wait(120) == 0, server.tail()
    metrics = json.loads((out / "metrics.json").read_text())
    assert len(metrics["groups"]) == 1, metrics["groups"]
    assert sorted(metrics["groups"][0]["members"]) == ["agent-0", "agent-1"]
    assert metrics["merges"], server.tail()
    for a in ("agent-0", "agent-1"):
        agent_metrics = json.loads((out / f"agent_{a}" / "metrics.json").read_text())
        assert agent_metrics["unacknowledged"] == 0


def test_certificates_bind_identities(tmp_path: Path, tls_endpoint: str, bundle: Path,
                                      daemons) -> None:
    out, ep = tmp_path / "run", tls_endpoint
    server = Daemon("server", server_args(ep, SESSION, out, "--config",
                                          str(bundle / "server.yaml")), tmp_path)
    daemons.append(server)
    operator = _client(bundle, "operator", ep)
    wait_until("the server to answer the operator",
               lambda: query_status(operator, SESSION, 1.0) is not None, 120, server)

    # No client certificate: the mutual-TLS handshake fails, nothing is opened.
    with pytest.raises(BusError):
        ZenohBus(mode="client", connect=[ep], open_timeout_s=2.0,
                 security=ZenohSecurity(root_ca=bundle / "ca.pem"))

    a0, a1 = _client(bundle, "agent-0", ep), _client(bundle, "agent-1", ep)
    try:
        to_a0 = a0.subscribe(keys.server_agent_all(SESSION, "agent-0"), queue_size=64)
        # agent-1 may not query the status, nor pose as agent-0 or as the server.
        assert query_status(a1, SESSION, 1.0) is None
        forged_ack = encode(Ack(agent_id="agent-0", seq=2**63 - 1))
        a1.publish(keys.server_agent_ack(SESSION, "agent-0"), forged_ack)
        a1.publish(keys.server_agent_update(SESSION, "agent-0"), b"forged update")
        a1.publish(keys.agent_keyframe(SESSION, "agent-0"), _keyframe("agent-0", 0))
        a1.publish(keys.server_control(SESSION), encode(Control(action="finalise")))
        forged_presence = a1.declare_liveliness(keys.alive_agent(SESSION, "agent-0"))
        # agent-1's own keyframe gets through: the bus and the server work for it.
        a1.publish(keys.agent_keyframe(SESSION, "agent-1"), _keyframe("agent-1", 0))
        wait_until("agent-1's own keyframe to arrive",
                   lambda: _agents(operator).get("agent-1", {}).get("keyframes", 0) >= 1,
                   30, server, every=0.3)
        # A second one, once Zenoh has told the client who subscribes: a declared publisher
        # sends only to known subscribers, so the ACL must let those declarations through.
        a1.publish(keys.agent_keyframe(SESSION, "agent-1"), _keyframe("agent-1", 1))
        wait_until("agent-1's second keyframe to arrive",
                   lambda: _agents(operator).get("agent-1", {}).get("keyframes", 0) >= 2,
                   30, server, every=0.3)
        assert "agent-0" not in _agents(operator), "a keyframe forged as agent-0 was accepted"

        # agent-0 itself: its keyframe is accepted and the server's real ack reaches it.
        a0_presence = a0.declare_liveliness(keys.alive_agent(SESSION, "agent-0"))
        a0.publish(keys.agent_keyframe(SESSION, "agent-0"), _keyframe("agent-0", 0))
        received: list[tuple[str, bytes]] = []
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and not any(k.endswith("/ack") for k, _ in received):
            sample = to_a0.get(timeout=0.5)
            if sample is not None:
                received.append((sample.key, sample.payload))
        assert any(k.endswith("/ack") for k, _ in received), server.tail()
        time.sleep(0.5)
        while (sample := to_a0.get(timeout=0.1)) is not None:
            received.append((sample.key, sample.payload))
        assert all(p not in (forged_ack, b"forged update") for _, p in received), received
        wait_until("agent-0 to be present",
                   lambda: _agents(operator).get("agent-0", {}).get("alive") is True, 30,
                   server, every=0.3)

        # agent-0 leaves: agent-1's token on alive/agent/agent-0 does not keep it alive.
        a0_presence.undeclare()
        wait_until("agent-0 to be seen leaving",
                   lambda: _agents(operator).get("agent-0", {}).get("alive") is False, 30,
                   server, every=0.3)
        forged_presence.undeclare()

        # agent-1's finalise went nowhere; the operator's finishes the run.
        assert server.proc.poll() is None, server.tail()
    finally:
        for bus in (a0, a1, operator):
            bus.close()
    finalise(ep, SESSION, 120.0, "--config", str(bundle / "operator.yaml"))
    assert server.wait(60) == 0, server.tail()
    assert (out / "metrics.json").is_file()

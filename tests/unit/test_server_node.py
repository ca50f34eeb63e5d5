"""`ServerNode` over the in-memory bus: persistence before acks, restore, bad input, traffic."""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

import numpy as np

from cpslam import protocol
from cpslam.common.bus import InMemoryBus, InMemoryNetwork
from cpslam.common.bus.subscription import Sample, Subscription
from cpslam.common.config import load_config
from cpslam.common.place_recognition import descriptor_dim
from cpslam.protocol import Ack, GroupDecoder, KeyframeImageRequest, KeyframeMsg, keys
from cpslam.server.backend import Outgoing
from cpslam.server.node import ServerNode
from cpslam.server.traffic import traffic_per_agent, traffic_per_group

SESSION = "default"
# The server checks descriptors against the length its own config gives.
DESCRIPTOR_DIM = descriptor_dim(load_config("tiny", env={}).place_recognition)


def _keyframe(agent: str, seq: int, kf: int) -> KeyframeMsg:
    d = np.random.default_rng(kf).standard_normal(DESCRIPTOR_DIM).astype(np.float32)
    return KeyframeMsg(agent_id=agent, seq=seq, kf_id=kf, frame_index=kf * 5, stamp=kf / 6.0,
                       world_epoch=0, T_world_cam=np.eye(4), T_prev_kf_kf=np.eye(4),
                       descriptor=d / np.linalg.norm(d), n_points=0)


def _acks(sub: Subscription, bus: InMemoryBus) -> list[int]:
    """The acks `bus` has received by now (everything sent before has arrived)."""
    _settle(bus)
    out = []
    while (sample := sub.get(timeout=0)) is not None:
        out.append(int(protocol.decode(sample.payload, expected=Ack).seq))
    return out


def _settle(bus: InMemoryBus) -> None:
    """Wait until the in-memory network has delivered everything sent before: its one
    dispatcher runs events in order, so a marker's arrival means every earlier publication
    and liveliness change arrived (a fixed sleep is a guess on a loaded machine)."""
    with bus.subscribe("test/settle") as marker:
        bus.publish("test/settle", b"")
        assert marker.get(timeout=30.0) is not None


def _setup(tmp_path: Path, persist_every_s: float):
    cfg = load_config("tiny")
    network = InMemoryNetwork()
    server_bus, agent_bus = InMemoryBus(network), InMemoryBus(network)
    # The state is written in the poll loop here, so each poll's acks are out when it returns.
    node = ServerNode(cfg, server_bus, tmp_path, state_path=tmp_path / "state.pt",
                      persist_every_s=persist_every_s, persist_background=False).start()
    acks = agent_bus.subscribe(keys.server_agent_ack(SESSION, "a"), queue_size=64)
    return node, agent_bus, acks


def test_acks_wait_for_the_state_on_disk_and_a_restart_restores_it(tmp_path: Path) -> None:
    node, agent_bus, acks = _setup(tmp_path, persist_every_s=3600.0)
    node.acks.last_snapshot = time.monotonic()  # the next write is an hour away
    agent_bus.publish(keys.agent_keyframe(SESSION, "a"), protocol.encode(_keyframe("a", 0, 0)))
    _settle(agent_bus)
    node.poll()
    assert _acks(acks, agent_bus) == [], "acknowledged before the state was persisted"
    assert not (tmp_path / "state.pt").exists()
    node.persist()
    assert (tmp_path / "state.pt").is_file()
    assert _acks(acks, agent_bus) == [0]
    node.close()

    restarted, agent_bus2, acks2 = _setup(tmp_path, persist_every_s=0.0)
    assert restarted.restored
    assert restarted.backend.status()["agents"]["a"]["keyframes"] == 1
    # A resend of what the first server accepted is acknowledged again, not duplicated.
    agent_bus2.publish(keys.agent_keyframe(SESSION, "a"), protocol.encode(_keyframe("a", 0, 0)))
    _settle(agent_bus2)
    restarted.poll()
    assert _acks(acks2, agent_bus2) == [0]
    assert restarted.backend.status()["agents"]["a"]["keyframes"] == 1


def test_bad_payloads_are_dropped_and_counted(tmp_path: Path) -> None:
    node, agent_bus, _ = _setup(tmp_path, persist_every_s=0.0)
    key = keys.agent_keyframe(SESSION, "a")
    agent_bus.publish(key, b"\x00garbage")
    # agent_id in the message that disagrees with the key
    agent_bus.publish(key, protocol.encode(_keyframe("b", 0, 0)))
    _settle(agent_bus)
    assert node.poll() == 0
    assert node.dropped[key] == 2


def test_images_are_not_requested_from_an_agent_that_left(tmp_path: Path,
                                                          monkeypatch) -> None:
    node, agent_bus, _ = _setup(tmp_path, persist_every_s=0.0)
    agent_bus.publish(keys.agent_keyframe(SESSION, "a"), protocol.encode(_keyframe("a", 0, 0)))
    _settle(agent_bus)
    node.poll()
    node.backend.agent_left("a")
    node.image_timeout_s = 30.0
    queries: list[str] = []
    monkeypatch.setattr(node.bus, "query", lambda key, *a, **kw: queries.append(key) or [])
    assert node.fetch_image("a", 0) is None
    assert queries == []  # no query, so no waiting out its 30 s timeout


def test_image_requests_ask_for_the_configured_scale(tmp_path: Path, monkeypatch) -> None:
    node, _, _ = _setup(tmp_path, persist_every_s=0.0)
    node.cfg = node.cfg.model_copy(update={
        "loop": node.cfg.loop.model_copy(update={"image_scale": 0.5})})
    asked: list[KeyframeImageRequest] = []

    def query(key: str, payload: bytes, **kw) -> list:
        asked.append(protocol.decode(payload, expected=KeyframeImageRequest))
        return []

    monkeypatch.setattr(node.bus, "query", query)
    assert node.fetch_image("a", 4) is None
    assert [(r.agent_id, r.kf_id, r.scale) for r in asked] == [("a", 4, 0.5)]


def test_traffic_per_agent_groups_keys_and_rates() -> None:
    traffic = {
        "received": {"cpslam/s/agent/a/keyframe": {"messages": 2, "bytes": 100},
                     "cpslam/s/agent/a/submap": {"messages": 1, "bytes": 900},
                     "cpslam/s/agent/b/frames": {"messages": 1, "bytes": 50},
                     "cpslam/s/agent/*/*": {"messages": 4, "bytes": 1050}},
        "sent": {"cpslam/s/server/agent/a/ack": {"messages": 3, "bytes": 30},
                 "cpslam/s/agent/a/image/4": {"messages": 1, "bytes": 10},
                 "cpslam/s/server/group/g/decoder": {"messages": 1, "bytes": 999},
                 "cpslam/s/server/agent/a/group_decoder": {"messages": 1, "bytes": 999}},
    }
    out = traffic_per_agent("s", traffic, seconds=10.0)
    assert set(out) == {"a", "b"}  # the wildcard row is not an agent
    assert out["a"]["from_agent_bytes"] == 1000 and out["a"]["from_agent_bytes_per_s"] == 100.0
    assert out["a"]["from_agent"]["submap"] == {"messages": 1, "bytes": 900, "bytes_per_s": 90.0}
    # Image queries go to the agent too; a group decoder reaches each member on its key.
    assert out["a"]["to_agent"] == {
        "ack": {"messages": 3, "bytes": 30, "bytes_per_s": 3.0},
        "image": {"messages": 1, "bytes": 10, "bytes_per_s": 1.0},
        "group_decoder": {"messages": 1, "bytes": 999, "bytes_per_s": 99.9}}
    assert out["b"]["from_agent"] == {"frames": {"messages": 1, "bytes": 50, "bytes_per_s": 5.0}}
    assert out["b"]["to_agent"] == {} and out["b"]["to_agent_bytes"] == 0
    assert traffic_per_group("s", traffic["sent"], 10.0) == {
        "g": {"messages": 1, "bytes": 999, "bytes_per_s": 99.9}}


def test_finalise_counts_traffic_per_concrete_key_and_decoders_per_agent(
        tmp_path: Path) -> None:
    node, agent_bus, _ = _setup(tmp_path, persist_every_s=0.0)
    tokens = [agent_bus.declare_liveliness(keys.alive_agent(SESSION, a)) for a in ("a", "b")]
    payload = protocol.encode(_keyframe("a", 0, 0))
    agent_bus.publish(keys.agent_keyframe(SESSION, "a"), payload)
    _settle(agent_bus)
    node.poll()
    tensors = {"w": np.ones((4, 4), np.float32)}
    decoder = GroupDecoder(group_id="a", round=1, members=["a"], n_samples=5, tensors=tensors)
    node.publish([Outgoing("a", decoder, scope="group")])
    sent = len(protocol.encode(decoder))
    node.finalise()
    bus = json.loads((tmp_path / "metrics.json").read_text())["bus"]
    assert bus["received_by_key"] == {keys.agent_keyframe(SESSION, "a"):
                                      {"messages": 1, "bytes": len(payload)}}
    a, b = bus["per_agent"]["a"], bus["per_agent"].get("b", {"to_agent": {}})
    assert a["from_agent"]["keyframe"]["bytes"] == len(payload) == a["from_agent_bytes"]
    assert a["from_agent"]["keyframe"]["bytes_per_s"] > 0
    assert a["to_agent"]["group_decoder"]["bytes"] == sent
    assert "group_decoder" not in b["to_agent"]  # present, but not a member: not sent
    assert bus["per_group"]["a"]["bytes"] == sent and bus["per_group"]["a"]["messages"] == 1
    for token in tokens:
        token.undeclare()
    node.close()


def test_a_join_and_a_leave_are_one_log_line_each(tmp_path: Path, caplog) -> None:
    node, agent_bus, _ = _setup(tmp_path, persist_every_s=0.0)
    caplog.set_level(logging.INFO, logger="cpslam.server")
    token = agent_bus.declare_liveliness(keys.alive_agent(SESSION, "a"))
    agent_bus.publish(keys.agent_keyframe(SESSION, "a"), protocol.encode(_keyframe("a", 0, 0)))
    _settle(agent_bus)
    node.poll()
    token.undeclare()
    _settle(agent_bus)
    node.poll()
    lines = [r.getMessage() for r in caplog.records if r.levelno >= logging.INFO]
    assert [m for m in lines if m.startswith("agent a ")] == ["agent a joined", "agent a left"]
    node.close()


def test_subscription_wait_does_not_consume() -> None:
    sub = Subscription("k", queue_size=4)
    assert sub.wait(0.05) is False
    sub.deliver(Sample("k", b"x", time.time()))
    assert sub.wait(0.05) is True and len(sub) == 1
    assert sub.get(timeout=0).payload == b"x"


def test_cpslam_status_prints_the_node_summary_with_retrying_loops(tmp_path: Path,
                                                                  monkeypatch) -> None:
    from typer.testing import CliRunner

    from cpslam.cli import app
    from cpslam.server import client

    node, agent_bus, _ = _setup(tmp_path, persist_every_s=0.0)
    agent_bus.publish(keys.agent_keyframe(SESSION, "a"), protocol.encode(_keyframe("a", 0, 0)))
    _settle(agent_bus)
    node.poll()
    # The command's own client session, on the node's in-memory network instead of Zenoh.
    monkeypatch.setattr(client, "_client",
                        lambda *a: (load_config("tiny"), InMemoryBus(node.bus.network)))
    raw = CliRunner().invoke(app, ["status", "--json"])
    assert raw.exit_code == 0, raw.output
    summary = json.loads(raw.output)
    # --json is the whole summary the node serves, the back end's loop counts included.
    assert set(node.backend.status()) <= set(summary)
    assert summary["loops"] == node.backend.status()["loops"]
    assert summary["loops"]["retrying"] == 0 and summary["agents"]["a"]["keyframes"] == 1
    text = CliRunner().invoke(app, ["status"])
    assert text.exit_code == 0, text.output
    assert "pending 0, retrying 0" in text.output
    node.close()
    summary["loops"].update(pending=1, retrying=2)
    assert "loops: found 0, accepted 0, rejected 0, pending 1, retrying 2" in \
        client.format_status(summary)

"""Delivery between real nodes on the in-memory bus: a message lost mid-stream is resent while
streaming; an agent restarted with the same id is refused (exit code 5) unless it resumes."""

from __future__ import annotations

import json
import threading
from pathlib import Path

import numpy as np
import pytest

from cpslam import protocol
from cpslam.agent.daemon import ServerPresence, _wait_for_room, run_networked
from cpslam.agent.node import AgentNode
from cpslam.common.bus import InMemoryBus, InMemoryNetwork
from cpslam.common.camera import Intrinsics
from cpslam.common.cli import ExitCode
from cpslam.common.config import load_config
from cpslam.common.datasets import RGBDFrame
from cpslam.common.place_recognition import descriptor_dim
from cpslam.server.node import ServerNode
from tests.fake_clock import FakeClock

INTR = Intrinsics(fx=128.0, fy=128.0, cx=79.5, cy=59.5, width=160, height=120)
N_FRAMES = 8


class WallSequence:
    """A textured wall 2 m ahead, the camera sliding 1 mm per frame (an `RGBDSequence`'s
    interface as the agent uses it)."""

    format = "synthetic-wall"

    def __init__(self, path: Path, n: int = N_FRAMES) -> None:
        self.path, self.intrinsics = path, INTR
        self.timestamps = np.arange(n) / 30.0

    def __len__(self) -> int:
        return len(self.timestamps)

    def __getitem__(self, i: int) -> RGBDFrame:
        v, u = np.mgrid[0:120, 0:160]
        u = u + i * 0.064
        rgb = np.stack(((u * 3) % 256, (v * 4) % 256, ((u + v) * 2) % 256), -1).astype(np.uint8)
        return RGBDFrame(i, i / 30.0, rgb, np.full((120, 160), 2.0, np.float32), None)


def _cfg():
    return load_config(
        "tiny",
        overrides=[
            "mapping.iters_first=10",
            "mapping.iters=3",
            "tracking.iters=3",
            "transport.backend=memory",
            "transport.resend_after_s=5",
        ],
        env={},
    )


# The server checks descriptors against the length its own config gives.
DESCRIPTOR_DIM = descriptor_dim(load_config("tiny", env={}).place_recognition)


def _describe(rgb: np.ndarray) -> np.ndarray:
    d = np.resize(rgb.reshape(-1, 3).mean(0).astype(np.float32) + 1.0, DESCRIPTOR_DIM)
    return d / np.linalg.norm(d)


def _settle(bus: InMemoryBus) -> None:
    """Everything published before has arrived (the network's one dispatcher is in order)."""
    with bus.subscribe("test/settle") as marker:
        bus.publish("test/settle", b"")
        assert marker.get(timeout=30.0) is not None


class LoseOnce:
    """The agent's bus, except that the first agent message with seq `seq` never arrives."""

    def __init__(self, bus: InMemoryBus, seq: int) -> None:
        self._bus, self.seq, self.lost = bus, seq, False

    def publish(self, key: str, payload: bytes) -> None:
        if not self.lost and "/agent/" in key and "/server/" not in key:
            msg = protocol.decode(payload)
            if getattr(msg, "seq", None) == self.seq:
                self.lost = True
                return
        self._bus.publish(key, payload)

    def __getattr__(self, name: str):
        return getattr(self._bus, name)


def test_a_message_lost_mid_stream_is_resent_while_streaming(tmp_path: Path) -> None:
    cfg, clock = _cfg(), FakeClock()
    network = InMemoryNetwork()
    server_bus, agent_bus = InMemoryBus(network), InMemoryBus(network)
    server = ServerNode(cfg, server_bus, tmp_path / "server").start()
    lossy = LoseOnce(agent_bus, seq=1)
    node = AgentNode(
        cfg,
        WallSequence(tmp_path),
        lossy,
        "a",
        tmp_path,
        describe=_describe,
        incarnation=7,
        now=clock,
    ).start()
    waiting = []
    for frame in node.frames():
        node.poll()
        node.resend_due()
        node.step(frame)
        _settle(agent_bus)
        server.poll()
        _settle(agent_bus)
        node.poll()
        waiting.append(list(node.link.outbox))
        clock.advance(1.0)
    assert lossy.lost
    # While seq 1 was missing, the acks' ranges covered everything after it.
    assert [1] in waiting
    rec = server.backend.registry.agents["a"]
    assert node.link.outbox.resent >= 1
    assert len(node.link.outbox) == 0 and rec.seq_floor == node.link.next_seq - 1
    assert waiting[-1] == [], "the floor caught up before the end of the stream"
    node.close()
    server.close()


@pytest.fixture()
def served(tmp_path: Path):
    cfg = _cfg()
    network = InMemoryNetwork()
    server_bus = InMemoryBus(network)
    server = ServerNode(cfg, server_bus, tmp_path / "server").start()
    stop = threading.Event()
    thread = threading.Thread(target=server.run, kwargs={"poll_s": 0.02, "stop": stop})
    thread.start()
    yield cfg, network, server
    stop.set()
    thread.join(timeout=60)
    server.close()


def _agent(cfg, network, run_dir: Path, stop_after: int | None = None, resume=None) -> int:
    stop = threading.Event()
    done = []

    def on_frame(frame, result, odometry) -> None:
        done.append(frame.index)
        if stop_after is not None and len(done) >= stop_after:
            stop.set()

    bus = InMemoryBus(network)
    try:
        return run_networked(
            cfg,
            WallSequence(run_dir),
            "a",
            run_dir,
            "cpu",
            wait_timeout_s=30.0,
            ack_timeout_s=60.0,
            show_progress=False,
            stop=stop,
            on_frame=on_frame,
            bus=bus,
            resume=resume,
        )
    finally:
        bus.close()


def test_restart_without_resume_is_refused_and_with_resume_continues(served, tmp_path) -> None:
    cfg, network, server = served
    first = tmp_path / "first"
    assert _agent(cfg, network, first, stop_after=3) == ExitCode.INTERRUPTED
    state = first / "agent_a" / "state.pt"
    assert state.is_file() and (first / "agent_a" / "link.pt").is_file()
    registry = server.backend.registry
    _wait(lambda: registry.agents.get("a") is not None and registry.agents["a"].frames)
    with server._lock:
        rec = registry.agents["a"]
        incarnation, keyframes = rec.incarnation, sorted(rec.keyframes)
        poses = {k: rec.keyframes[k].T_own_kf.copy() for k in keyframes}

    # The same id without --resume: a new incarnation, refused; nothing of it is taken.
    assert _agent(cfg, network, tmp_path / "again") == ExitCode.REFUSED
    with server._lock:
        assert rec.incarnation == incarnation and sorted(rec.keyframes) == keyframes
        assert all(np.array_equal(rec.keyframes[k].T_own_kf, T) for k, T in poses.items())
        assert registry.dropped["another incarnation"] >= 1

    # With --resume: the same incarnation continues where it stopped, every frame arrives.
    assert _agent(cfg, network, tmp_path / "resumed", resume=state) == 0
    with server._lock:
        assert rec.incarnation == incarnation
        assert sorted(rec.frames) == list(range(N_FRAMES))
        assert sorted(rec.keyframes)[: len(keyframes)] == keyframes
    metrics = {
        name: json.loads((tmp_path / name / "agent_a" / "metrics.json").read_text())
        for name in ("first", "again", "resumed")
    }
    assert metrics["first"]["incarnation"] == metrics["resumed"]["incarnation"] == incarnation
    assert metrics["again"]["incarnation"] != incarnation
    assert metrics["resumed"]["unacknowledged"] == 0


def _wait(condition, timeout_s: float = 60.0) -> None:
    event = threading.Event()
    for _ in range(int(timeout_s / 0.05)):
        if condition():
            return
        event.wait(0.05)
    raise AssertionError("condition not met in time")


def test_a_full_outbox_holds_frames_back_until_acks_make_room(tmp_path, caplog) -> None:
    cfg = _cfg()
    cfg = cfg.model_copy(
        update={"transport": cfg.transport.model_copy(update={"outbox_messages": 2})}
    )
    network = InMemoryNetwork()
    server_bus, agent_bus = InMemoryBus(network), InMemoryBus(network)
    server = ServerNode(cfg, server_bus, tmp_path / "server").start()
    node = AgentNode(
        cfg, WallSequence(tmp_path), agent_bus, "a", tmp_path, describe=_describe
    ).start()
    presence = ServerPresence(agent_bus, cfg.transport.session)
    node.step(next(node.frames()))  # frame 0: keyframe, sub-map and poses, none acked yet
    assert node.link.outbox.full()
    stop = threading.Event()
    thread = threading.Thread(target=server.run, kwargs={"poll_s": 0.02, "stop": stop})
    thread.start()
    try:
        with caplog.at_level("INFO", logger="cpslam.agent.daemon"):
            _wait_for_room(node, presence, stop)
    finally:
        stop.set()
        thread.join(timeout=60)
    assert "outbox full" in caplog.text and "room again" in caplog.text
    assert not node.link.outbox.full()
    assert server.backend.registry.agents["a"].seq_floor >= 0
    presence.close()
    node.close()
    server.close()


def test_networked_resume_needs_the_link_state_beside_state_pt(tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from cpslam.agent_cli import app

    state = tmp_path / "agent_0" / "state.pt"
    state.parent.mkdir()
    state.write_bytes(b"")
    result = CliRunner().invoke(
        app, ["--preset", "tiny", "--no-progress", "--seq", str(tmp_path), "--resume", str(state)]
    )
    assert result.exit_code == ExitCode.USAGE and "link.pt" in result.output


class LoseUpdateOnce:
    """The server's bus, except that the first `ServerUpdate` to `agent` never arrives."""

    def __init__(self, bus: InMemoryBus, agent: str) -> None:
        self._bus, self.key, self.lost = bus, f"/server/agent/{agent}/update", False

    def publish(self, key: str, payload: bytes) -> None:
        if not self.lost and key.endswith(self.key):
            self.lost = True
            return
        self._bus.publish(key, payload)

    def __getattr__(self, name: str):
        return getattr(self._bus, name)


def test_a_server_update_lost_mid_stream_is_repaired(tmp_path: Path) -> None:
    from cpslam.protocol import keys
    from tests.unit.test_delivery import delta, keyframe

    cfg, clock = _cfg(), FakeClock()
    cfg = cfg.model_copy(
        update={"loop": cfg.loop.model_copy(update={"lambda_fine": 1.0, "lambda_coarse": 1.0})}
    )  # no loop candidates: the test merges the groups itself
    network = InMemoryNetwork()
    server_bus, agent_bus, peer_bus = (InMemoryBus(network) for _ in range(3))
    lossy = LoseUpdateOnce(server_bus, "a0")
    server = ServerNode(cfg, lossy, tmp_path / "server", now=clock, image_timeout_s=0.1).start()
    node = AgentNode(
        cfg, WallSequence(tmp_path), agent_bus, "a0", tmp_path, describe=_describe, now=clock
    ).start()
    f = node.odometry.point_map.feature_dim
    # Agent b1 is a plain client: its keyframe and 30 points, 3 m behind a0's wall.
    for msg in (keyframe(0, 0, agent="b1", z=5.0, dim=DESCRIPTOR_DIM),
                delta(1, range(30), agent="b1", f=f)):
        peer_bus.publish(
            keys.agent_topic(
                "default", "b1", {"keyframe": "keyframe", "submap_delta": "submap"}[msg.type]
            ),
            protocol.encode(msg),
        )
    for i, frame in enumerate(node.frames()):
        node.poll()
        node.step(frame)
        _settle(agent_bus)
        if i == 1:
            with server._lock:
                server.backend.groups.merge("a0", "b1", np.eye(4))
        server.poll()
        _settle(agent_bus)
        node.poll()
        _settle(agent_bus)
        clock.advance(2.0)
    assert lossy.lost
    server.poll()  # the last update acks
    delivered = server.backend.sharing.foreign.delivered("a0")
    pm = node.odometry.point_map
    held = set(pm.point_id[pm.agent_id == node.link.foreign_index["b1"]].tolist())
    assert set(delivered["b1"]) == held == set(range(30))
    assert node.link.update_seq >= 2  # the first was lost, a repair arrived
    node.close()
    server.close()

"""A server restarted without its state: the agent sees the new state id on the server's
liveliness token and streams its whole state again as a new incarnation; nothing is lost."""

from __future__ import annotations

import json
import threading
from pathlib import Path

import numpy as np

from cpslam.agent.daemon import run_networked
from cpslam.common.bus import InMemoryBus, InMemoryNetwork
from cpslam.server.node import ServerNode
from tests.unit.test_delivery_nodes import WallSequence, _cfg

N_FRAMES = 14
RESTART_AT = 6


class Served:
    """A `ServerNode` on its own bus, serving on a thread until `stop`."""

    def __init__(self, cfg, network: InMemoryNetwork, run_dir: Path) -> None:
        self.bus = InMemoryBus(network)
        self.node = ServerNode(cfg, self.bus, run_dir).start()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self.node.run,
                                        kwargs={"poll_s": 0.02, "stop": self._stop})
        self._thread.start()

    def stop(self) -> None:
        if self._stop.is_set():
            return
        self._stop.set()
        self._thread.join(timeout=60)
        self.node.close()
        self.bus.close()


def test_a_server_restarted_without_its_state_gets_everything_again(tmp_path: Path) -> None:
    cfg, network = _cfg(), InMemoryNetwork()
    first = Served(cfg, network, tmp_path / "first")
    servers = [first]
    restart, restarted = threading.Event(), threading.Event()

    def on_frame(frame, result, odometry) -> None:
        if frame.index == RESTART_AT:  # hold the agent while the server is replaced
            restart.set()
            assert restarted.wait(60)

    outcome: list[int] = []
    bus = InMemoryBus(network)
    agent = threading.Thread(target=lambda: outcome.append(run_networked(
        cfg, WallSequence(tmp_path, N_FRAMES), "a", tmp_path / "agent", "cpu",
        wait_timeout_s=30.0, ack_timeout_s=60.0, show_progress=False, on_frame=on_frame,
        bus=bus)))
    agent.start()
    try:
        assert restart.wait(120)
        rec = first.node.backend.registry.agents["a"]
        assert rec.keyframes and rec.seq_floor >= 0, "the first server acknowledged data"
        old_incarnation, old_state = rec.incarnation, first.node.backend.state_id
        first.stop()
        second = Served(cfg, network, tmp_path / "second")  # a fresh folder: no state
        servers.append(second)
        assert second.node.backend.state_id != old_state and not second.node.restored
        restarted.set()
        agent.join(timeout=300)
        assert outcome == [0]
    finally:
        restarted.set()
        agent.join(timeout=60)
        bus.close()
        for served in servers:
            served.stop()

    metrics = json.loads((tmp_path / "agent" / "agent_a" / "metrics.json").read_text())
    assert metrics["stream_restarts"] == 1 and metrics["unacknowledged"] == 0
    assert metrics["incarnation"] != old_incarnation
    rec = second.node.backend.registry.agents["a"]
    assert rec.incarnation == metrics["incarnation"]
    # Everything the agent has is on the new server: every frame, keyframe and point.
    assert sorted(rec.frames) == list(range(N_FRAMES))
    assert len(rec.keyframes) == metrics["keyframes"]
    assert len(rec.points) == metrics["points"] and not len(rec.pending_points)
    assert not rec.pending_frames and not dict(second.node.backend.registry.dropped)
    # Poses arrive in the agent's frame: the keyframes' relative motion is the agent's own.
    kfs = sorted(rec.keyframes)
    steps = [np.linalg.norm(rec.keyframes[b].T_own_kf[:3, 3] - rec.keyframes[a].T_own_kf[:3, 3])
             for a, b in zip(kfs, kfs[1:])]
    assert all(np.isfinite(steps)) and max(steps, default=0.0) < 0.5

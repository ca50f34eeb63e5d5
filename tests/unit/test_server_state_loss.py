"""A server restarted without its state: the agent sees the new state id on the server's
liveliness token and streams its whole state again as a new incarnation; nothing is lost."""

from __future__ import annotations

import itertools
import json
import threading
from pathlib import Path

import numpy as np
import pytest

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
             for a, b in itertools.pairwise(kfs)]
    assert all(np.isfinite(steps)) and max(steps, default=0.0) < 0.5


def test_a_restarted_stream_carries_the_whole_state_in_stream_order() -> None:
    from cpslam.agent.link_state import link_state, load_link_state
    from cpslam.protocol import DecoderWeights, FramePoses, KeyframeMsg, SubmapDelta
    from tests.unit.test_link import _link, _run

    link = _link(frames_every=2, rounds=2)
    first = _run(link, 0, 7)
    link.outbox.on_ack(_ack(link, link.next_seq - 1), link.next_seq, link.incarnation)
    link.epoch, link.group_id = 3, "g"  # as if merged by the old server
    sent_kfs = [m for m in first if isinstance(m, KeyframeMsg)]

    # The link state keeps what a restart needs (a resumed agent may meet a new server).
    state = link_state(link)
    again = _link(frames_every=2, rounds=2)
    load_link_state(again, state)
    assert again._frame_index == link._frame_index == list(range(7))
    assert again._descriptors.keys() == link._descriptors.keys()
    del state["frame_index"]
    with pytest.raises(ValueError, match="frame_index"):
        load_link_state(_link(), state)

    out = link.restart(incarnation=99)
    assert [m.seq for m in out] == list(range(len(out))) and link.next_seq == len(out)
    assert all(m.incarnation == 99 for m in out) and len(link.outbox) == len(out)
    assert link.epoch == 0 and link.group_id == link.agent_id and link.update_seq == 0
    kinds = [type(m) for m in out]
    assert kinds == sorted(kinds, key=[KeyframeMsg, SubmapDelta, DecoderWeights,
                                       FramePoses].index), "keyframes first, frame poses last"
    kfs = [m for m in out if isinstance(m, KeyframeMsg)]
    assert [m.kf_id for m in kfs] == [m.kf_id for m in sent_kfs]
    assert all(m.world_epoch == 0 for m in kfs) and kfs[0].T_prev_kf_kf is None
    for new, old in zip(kfs, sent_kfs, strict=True):  # the descriptor as first sent
        np.testing.assert_array_equal(new.descriptor, old.descriptor)
    pm = link.odometry.point_map
    own = int((pm.agent_id == link.own).sum())
    assert sum(m.point_ids.size for m in out if isinstance(m, SubmapDelta)) == own
    frames = [m for m in out if isinstance(m, FramePoses)]
    assert sorted(np.concatenate([m.frame_indices for m in frames]).tolist()) == list(range(7))
    assert not any(isinstance(m, DecoderWeights) and m.base_round is not None for m in out)


def test_a_full_map_goes_in_messages_of_bounded_size() -> None:
    from cpslam.agent.rebase import restart_stream
    from cpslam.protocol import SubmapDelta
    from tests.unit.test_link import _link, _run

    link = _link()
    _run(link, 0, 3)
    own = int((link.odometry.point_map.agent_id == link.own).sum())
    out = restart_stream(link, 5, max_points=own // 3 + 1)
    deltas = [m for m in out if isinstance(m, SubmapDelta)]
    assert len(deltas) == 3 and all(m.point_ids.size <= own // 3 + 1 for m in deltas)
    ids = np.concatenate([m.point_ids for m in deltas])
    assert ids.size == own and np.unique(ids).size == own


def _ack(link, seq: int):
    from cpslam.protocol import Ack

    return Ack(agent_id=link.agent_id, seq=seq, incarnation=link.incarnation)

"""Durable server state on the in-memory bus: acks wait for the fsynced snapshot, a full disk
holds acks without stopping the node, a torn newest generation resumes the previous one."""

from __future__ import annotations

import errno
import logging
import threading
from pathlib import Path

import pytest

from cpslam import protocol
from cpslam.common import durable
from cpslam.common.bus import InMemoryBus, InMemoryNetwork
from cpslam.common.config import load_config
from cpslam.protocol import keys
from cpslam.server.node import ServerNode
from cpslam.server.persist import StateWriter, detach
from tests.fake_clock import FakeClock
from tests.unit.test_server_node import SESSION, _acks, _keyframe, _settle


def _node(tmp_path: Path, background: bool, **kwargs):
    network = InMemoryNetwork()
    server_bus, agent_bus = InMemoryBus(network), InMemoryBus(network)
    node = ServerNode(
        load_config("tiny"),
        server_bus,
        tmp_path,
        state_path=tmp_path / "state.pt",
        persist_every_s=0.0,
        persist_background=background,
        **kwargs,
    ).start()
    acks = agent_bus.subscribe(keys.server_agent_ack(SESSION, "a"), queue_size=64)
    return node, agent_bus, acks


def _send(agent_bus: InMemoryBus, seq: int, kf: int) -> None:
    agent_bus.publish(keys.agent_keyframe(SESSION, "a"), protocol.encode(_keyframe("a", seq, kf)))
    _settle(agent_bus)


def test_acks_are_sent_only_after_the_writer_thread_made_the_snapshot_durable(
    tmp_path: Path,
) -> None:
    node, agent_bus, acks = _node(tmp_path, background=True)
    started, release = threading.Event(), threading.Event()
    real_write = node.writer.write

    def slow_write(path: Path, data: bytes) -> None:
        started.set()
        assert release.wait(60.0)
        real_write(path, data)

    node.writer.write = slow_write
    try:
        _send(agent_bus, 0, 0)
        assert node.poll() == 1
        assert started.wait(60.0), "the poll handed a snapshot to the writer"
        assert node.writer.busy
        node.poll()  # the loop goes on while the write is in flight
        assert _acks(acks, agent_bus) == [], "acknowledged before the state was durable"
        assert not (tmp_path / "state.pt").exists()
    finally:
        release.set()
    assert node.writer.wait(1, timeout_s=60.0)
    assert (tmp_path / "state.pt").is_file()
    node.poll()
    assert _acks(acks, agent_bus) == [0]
    node.close()


def test_a_full_disk_holds_acks_keeps_polling_logs_once_and_recovers(
    tmp_path: Path, caplog
) -> None:
    node, agent_bus, acks = _node(tmp_path, background=False, persist_log_every_s=60.0)
    clock = FakeClock()
    node.writer.clock = clock
    real_write = node.writer.write
    attempts = []

    def full(path: Path, data: bytes) -> None:
        attempts.append(len(data))
        raise OSError(errno.ENOSPC, "No space left on device")

    node.writer.write = full
    with caplog.at_level(logging.ERROR, logger="cpslam.server.persist"):
        _send(agent_bus, 0, 0)
        node.poll()
        for i in range(1, 4):  # the node goes on accepting while the disk is full
            clock.advance(1.0)
            _send(agent_bus, i, i)
            assert node.poll() == 1
        assert _acks(acks, agent_bus) == []
        assert len(node.acks.held) == 1, "held acks are cumulative: one per agent"
        assert len(attempts) >= 3, "the writer retries"
        assert node.backend.status()["agents"]["a"]["keyframes"] == 4
        failures = [r for r in caplog.records if "cannot write the server state" in r.message]
        assert len(failures) == 1, "one log line per interval, not one per attempt"
        assert "No space left on device" in failures[0].message
        clock.advance(60.0)
        node.poll()
        failures = [r for r in caplog.records if "cannot write the server state" in r.message]
        assert len(failures) == 2, "the next interval logs again"
        status = protocol.decode(node._serve_status("", None)).summary
        assert status["persist"]["generation"] == 0 and status["persist"]["failures"] >= 4
    assert not (tmp_path / "state.pt").exists()

    node.writer.write = real_write  # space again
    clock.advance(1.0)
    node.poll()  # the pending snapshot (seq 0) is written on its retry
    node.poll()  # then a snapshot of everything since
    assert _acks(acks, agent_bus) == [0, 3]  # an ack covers every seq up to its own
    assert protocol.decode(node._serve_status("", None)).summary["persist"]["failures"] == 0
    state, _ = durable.load_generation(tmp_path / "state.pt", _torch_load)
    assert len(state["registry"]["agents"][0]["keyframes"]["kf_id"]) == 4
    node.close()


def test_persist_reports_a_failed_write_and_keeps_the_acks(tmp_path: Path) -> None:
    node, agent_bus, acks = _node(tmp_path, background=True)
    node.writer.write = _raise_eio
    _send(agent_bus, 0, 0)
    node.poll()
    assert node.persist(timeout_s=60.0) is False
    assert _acks(acks, agent_bus) == []
    node.writer.write = durable.save_generation
    assert node.persist(timeout_s=60.0) is True
    assert _acks(acks, agent_bus) == [0]
    node.close()


def test_a_restart_after_a_torn_write_resumes_the_previous_generation(
    tmp_path: Path, caplog
) -> None:
    node, agent_bus, _ = _node(tmp_path, background=False)
    _send(agent_bus, 0, 0)
    node.poll()
    _send(agent_bus, 1, 1)
    node.poll()
    node.close()
    path = tmp_path / "state.pt"
    assert (tmp_path / "state.pt.prev").is_file()
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])  # crash mid-write

    with caplog.at_level(logging.WARNING, logger="cpslam.common.durable"):
        restarted, _, _ = _node(tmp_path, background=False)
    assert restarted.restored
    assert restarted.backend.status()["agents"]["a"]["keyframes"] == 1
    assert str(path) in caplog.text
    restarted.close()


def test_a_restart_with_no_good_generation_names_the_files(tmp_path: Path) -> None:
    (tmp_path / "state.pt").write_bytes(b"not a state")
    with pytest.raises(RuntimeError, match=r"state\.pt.*integrity trailer"):
        _node(tmp_path, background=False)


def test_the_writer_keeps_the_newest_snapshot_and_detach_copies_containers(tmp_path: Path) -> None:
    writer = StateWriter(tmp_path / "s.pt", background=False, clock=FakeClock())
    writer.write = _raise_eio
    assert writer.submit({"n": 1}) == 1
    assert writer.busy and writer.durable_gen == 0
    writer.write = durable.save_generation
    assert writer.submit({"n": 2}) == 2  # a newer snapshot replaces the failed one
    assert writer.durable_gen == 2 and not writer.busy
    assert durable.load_generation(tmp_path / "s.pt", _torch_load)[0] == {"n": 2}

    live = {"merges": [1, 2], "nested": {"rounds": [3]}}
    snap = detach(live)
    live["merges"].append(9)
    live["nested"]["rounds"].clear()
    assert snap == {"merges": [1, 2], "nested": {"rounds": [3]}}


def _raise_eio(path: Path, data: bytes) -> None:
    raise OSError(errno.EIO, "Input/output error")


def _torch_load(data: bytes):
    import io

    import torch

    return torch.load(io.BytesIO(data), weights_only=True)


def test_run_outputs_are_renamed_into_place_with_metrics_json_last(
    tmp_path: Path, renamed: list[Path]
) -> None:
    import numpy as np

    from cpslam.protocol import SubmapDelta

    node, agent_bus, _ = _node(tmp_path, background=False)
    _send(agent_bus, 0, 0)
    n = 50
    rng = np.random.default_rng(0)
    points = SubmapDelta(
        agent_id="a",
        seq=1,
        point_ids=np.arange(n),
        anchor_kf_ids=np.zeros(n, np.int32),
        xyz_local=rng.uniform(-1, 1, (n, 3)).astype(np.float32),
        features=rng.standard_normal((n, node.cfg.field.feature_dim)).astype(np.float16),
        colors=rng.integers(0, 256, (n, 3), dtype=np.uint8),
        removed_ids=np.zeros(0, np.int64),
    )
    agent_bus.publish(keys.agent_submap(SESSION, "a"), protocol.encode(points))
    _settle(agent_bus)
    node.poll()
    node.finalise()
    node.close()
    outputs = {p for p in tmp_path.rglob("*") if p.is_file() and not p.name.startswith("state.")}
    assert {p.name for p in outputs} >= {"metrics.json", "fused_map.ply", "fused_map.pt"}
    assert any(p.suffix == ".tum" for p in outputs)
    assert outputs <= set(renamed), "every output was renamed into place (atomic)"
    assert renamed[-1] == tmp_path / "metrics.json", "the completion mark comes last"
    assert not list(tmp_path.rglob("*.tmp")), "no temporary file left"


def test_finalise_without_the_mark_leaves_metrics_json_to_the_caller(tmp_path: Path) -> None:
    from cpslam.server.export import write_metrics

    node, agent_bus, _ = _node(tmp_path, background=False)
    _send(agent_bus, 0, 0)
    node.poll()
    final = node.finalise(mark_complete=False)
    node.close()
    assert not (tmp_path / "metrics.json").exists()
    write_metrics(final, tmp_path)
    assert (tmp_path / "metrics.json").is_file()


def test_the_ack_gate_keeps_the_newest_ack_per_agent_and_snapshots_when_due(
    tmp_path: Path,
) -> None:
    from cpslam.protocol import Ack
    from cpslam.server.backend import Outgoing
    from cpslam.server.persist import AckGate

    clock = FakeClock()
    writer = StateWriter(tmp_path / "s.pt", background=False, clock=clock)
    sent: list[tuple[str, int]] = []
    gate = AckGate(
        writer, 5.0, lambda out: sent.extend((o.target, o.message.seq) for o in out), clock=clock
    )

    def ack(agent: str, seq: int) -> Outgoing:
        return Outgoing(scope="agent", target=agent, message=Ack(agent_id=agent, seq=seq))

    for agent, seq in (("a", 3), ("a", 1), ("b", 0), ("a", 4)):
        gate.hold(ack(agent, seq))
    assert {a: o.message.seq for a, o in gate.held.items()} == {"a": 4, "b": 0}
    gate.tick(lambda: {"n": 1})
    assert sorted(sent) == [("a", 4), ("b", 0)] and not gate.pending
    gate.hold(ack("a", 5))
    clock.advance(4.0)
    gate.tick(lambda: {"n": 2})
    assert len(sent) == 2 and gate.pending, "no snapshot before every_s has passed"
    clock.advance(1.0)
    gate.tick(lambda: {"n": 3})
    assert sent[-1] == ("a", 5) and writer.durable_gen == 2

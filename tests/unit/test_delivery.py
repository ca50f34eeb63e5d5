"""Exactly-once delivery in both directions, incarnations, and the attacks that must do no harm.

Server side with a real `Registry`, `MemberUpdates` and foreign-point ledger; agent side with a
real `AgentLink` and `Outbox`; time from a fake clock.
"""

from __future__ import annotations

import numpy as np
import pytest

from cpslam.agent.link import AgentLink
from cpslam.agent.odometry import Odometry
from cpslam.agent.outbox import Outbox
from cpslam.common.camera import Intrinsics
from cpslam.common.config import load_config
from cpslam.common.datasets import RGBDFrame
from cpslam.protocol import Ack, FramePoses, KeyframeMsg, Refusal, ServerUpdate, SubmapDelta
from cpslam.server.fusion import MemberMap
from cpslam.server.groups import Group
from cpslam.server.registry import Registry
from cpslam.server.sharing import MemberUpdates
from tests.fake_clock import FakeClock

INTR = Intrinsics(fx=64.0, fy=64.0, cx=39.5, cy=29.5, width=80, height=60)
F = 4


def keyframe(seq, kf, inc=1, agent="a", z=0.0, dim=8):
    d = np.zeros(dim, np.float32)
    d[kf % dim] = 1
    T = np.eye(4)
    T[2, 3] = z
    return KeyframeMsg(
        agent_id=agent,
        seq=seq,
        incarnation=inc,
        kf_id=kf,
        frame_index=10 * kf,
        stamp=kf,
        T_world_cam=T,
        descriptor=d,
    )


def delta(seq, ids, anchor=0, inc=1, agent="a", f=F, x0=0.0):
    n = len(ids)
    # spread along x, within the fixed-point range of positions (+-2 km)
    x = x0 + np.arange(n) % 2000 * 0.5
    xyz = np.column_stack([x, np.zeros(n), np.ones(n)]).astype(np.float32)
    return SubmapDelta(
        agent_id=agent,
        seq=seq,
        incarnation=inc,
        point_ids=np.asarray(ids, np.int64),
        anchor_kf_ids=np.full(n, anchor, np.int32),
        xyz_local=xyz,
        features=np.full((n, f), 0.25, np.float16),
        colors=np.zeros((n, 3), np.uint8),
        removed_ids=np.zeros(0, np.int64),
    )


def frames(seq, inc=1, agent="a"):
    return FramePoses(
        agent_id=agent,
        seq=seq,
        incarnation=inc,
        frame_indices=[1],
        stamps=[0.1],
        kf_ids=[0],
        T_kf_frame=np.eye(4)[None],
    )


# --- agent -> server ---------------------------------------------------------------------------


def test_a_lost_message_stalls_nothing_and_its_resend_closes_the_gap():
    reg, clock = Registry(F), FakeClock()
    outbox = Outbox(resend_after_s=5.0, now=clock)
    msgs = [keyframe(0, 0), delta(1, [0, 1]), frames(2), delta(3, [2]), frames(4)]
    for m in msgs:
        outbox.add(m.seq, m)
    acks = [reg.handle(m)[-1] for m in msgs if m.seq != 1]  # seq 1 is lost on the way
    assert acks[-1] == Ack(agent_id="a", seq=0, incarnation=1, received=[(2, 4)])
    assert outbox.on_ack(acks[-1], next_seq=5, incarnation=1) == 4
    assert list(outbox) == [1], "only the lost message waits"
    assert outbox.due() == []  # not yet: it was sent a moment ago
    clock.advance(5.0)
    (again,) = outbox.due()  # while streaming, not only at the end
    assert again.seq == 1
    (ack,) = reg.handle(again)
    assert ack == Ack(agent_id="a", seq=4, incarnation=1)
    outbox.on_ack(ack, next_seq=5, incarnation=1)
    assert len(outbox) == 0 and outbox.bytes == 0 and outbox.floor == 4
    assert len(reg.agents["a"].points) == 3


def test_a_message_whose_handling_raises_is_acked_as_dropped_and_counted(monkeypatch):
    reg = Registry(F)
    reg.handle(keyframe(0, 0))
    real = Registry._submap

    def explode(self, rec, msg):
        if msg.seq == 1:
            raise RuntimeError("boom")
        return real(self, rec, msg)

    monkeypatch.setattr(Registry, "_submap", explode)
    (ack,) = reg.handle(delta(1, [0]))
    assert ack.seq == 1 and ack.dropped == [1]
    assert reg.dropped["handling raised"] == 1 and reg.agents["a"].dropped["handling raised"] == 1
    (ack,) = reg.handle(delta(2, [5]))  # the server goes on
    assert ack.seq == 2 and len(reg.agents["a"].points) == 1
    outbox = Outbox()
    for m in (delta(1, [0]), delta(2, [5])):
        outbox.add(m.seq, m)
    assert outbox.on_ack(Ack(agent_id="a", seq=0, incarnation=1, dropped=[1]), 3, 1) == 1
    assert outbox.dropped_by_server == [1] and list(outbox) == [2]


@pytest.mark.parametrize(
    "forged",
    [
        Ack(agent_id="a", seq=2**63 - 1, incarnation=1),
        Ack(agent_id="a", seq=0, incarnation=1, received=[(2, 2**63 - 1)]),
        Ack(agent_id="a", seq=0, incarnation=1, dropped=[9]),
        Ack(agent_id="a", seq=3, incarnation=2),  # another incarnation's
    ],
)
def test_forged_acks_leave_the_outbox_alone(forged):
    outbox = Outbox()
    for seq in range(4):
        outbox.add(seq, frames(seq))
    assert outbox.on_ack(forged, next_seq=4, incarnation=1) == 0
    assert list(outbox) == [0, 1, 2, 3] and outbox.floor == -1 and outbox.ignored_acks == 1


def test_outbox_is_bounded_by_messages_and_bytes():
    outbox = Outbox(max_messages=3, max_mb=1.0)
    for seq in range(2):
        outbox.add(seq, frames(seq))
    assert not outbox.full()
    outbox.add(2, frames(2))
    assert outbox.full()
    outbox.on_ack(Ack(agent_id="a", seq=0, incarnation=1), 3, 1)
    assert not outbox.full()
    big = delta(3, range(20_000), f=16)  # 20k points of 16 float16 features: ~1 MiB
    outbox.add(3, big)
    assert outbox.full() and outbox.bytes >= 1 << 20


def test_seqs_far_above_the_floor_are_dropped_unacknowledged():
    reg = Registry(F, max_seq_ahead=100)
    reg.handle(keyframe(0, 0))
    assert reg.handle(frames(2**62)) == []
    assert reg.agents["a"].seqs_above == set() and reg.dropped["seq too far ahead"] == 1


# --- incarnations ------------------------------------------------------------------------------


def test_another_incarnation_is_refused_and_never_joins_the_old_world():
    reg = Registry(F)
    reg.handle(keyframe(0, 0, inc=11))
    reg.handle(delta(1, [0, 1], inc=11))
    before = reg.agents["a"].keyframes[0].T_own_kf.copy()
    # The same id restarted without --resume: a new incarnation, its own world and ids from 0.
    for msg in (
        keyframe(0, 0, inc=22, z=3.0),
        delta(1, [0, 1, 2], inc=22, x0=7.0),
        keyframe(2, 1, inc=22, z=4.0),
    ):
        (reply,) = reg.handle(msg)
        assert isinstance(reply, Refusal) and reply.incarnation == 22 and "--resume" in reply.reason
    rec = reg.agents["a"]
    assert list(rec.keyframes) == [0] and np.array_equal(rec.keyframes[0].T_own_kf, before)
    assert len(rec.points) == 2 and rec.seq_floor == 1
    assert reg.dropped["another incarnation"] == 3
    # The known incarnation goes on (a resumed agent keeps it and its seq counter).
    (ack,) = reg.handle(keyframe(2, 1, inc=11, z=0.5))
    assert ack == Ack(agent_id="a", seq=2, incarnation=11) and sorted(rec.keyframes) == [0, 1]
    # The binding survives a server restart.
    other = Registry(F)
    other.load_state_dict(reg.state_dict())
    assert isinstance(other.handle(frames(3, inc=22))[0], Refusal)


# --- server -> agent ---------------------------------------------------------------------------


def _frame(i: int) -> RGBDFrame:
    """A textured wall 2 m ahead; the camera slides 1 mm per frame."""
    v, u = np.mgrid[0:60, 0:80]
    u = u + i * 0.032
    rgb = np.stack(((u * 3) % 256, (v * 4) % 256, ((u + v) * 2) % 256), -1).astype(np.uint8)
    return RGBDFrame(i, i / 30.0, rgb, np.full((60, 80), 2.0, np.float32), None)


def _describe(rgb: np.ndarray) -> np.ndarray:
    d = rgb.reshape(-1, 3).mean(0).astype(np.float32) + 1.0
    return d / np.linalg.norm(d)


class Sharing:
    """A server holding agent a0 (a real `AgentLink`) and b1 (synthetic) in one group."""

    def __init__(self, max_points: int = 200_000, n_b1: int = 30) -> None:
        cfg = load_config(
            "tiny",
            overrides=["mapping.iters_first=5", "mapping.iters=2", "tracking.iters=2"],
            env={},
        )
        odometry = Odometry.from_config(cfg, INTR, "cpu", agent_id=0)
        self.link = AgentLink(
            "a0", odometry, _describe, frames_every=100, round_every_mappings=99, incarnation=5
        )
        self.f = odometry.point_map.feature_dim
        self.clock = FakeClock()
        self.reg = Registry(self.f)
        for i in range(2):
            for msg in self.link.after_step(_frame(i), odometry.step(_frame(i))):
                self.reg.handle(msg)
        self.reg.handle(keyframe(0, 0, agent="b1", z=5.0, dim=3))  # as _describe's
        self.reg.handle(delta(1, range(n_b1), agent="b1", f=self.f, x0=-7.0))
        self.group = Group("a0", "a0", {"a0": np.eye(4), "b1": np.eye(4)}, {"a0": 1, "b1": 1})
        self.sharing = MemberUpdates(
            self.reg,
            self.kf_poses,
            0.1,
            10.0,
            self.clock,
            resend_after_s=5.0,
            max_points=max_points,
        )

    def kf_poses(self, agent: str) -> dict[int, np.ndarray]:
        return {k: r.T_own_kf for k, r in self.reg.agents[agent].keyframes.items()}

    def updates(self) -> list[ServerUpdate]:
        maps = [
            MemberMap(a, r.index, r.points.to_point_map(r.index, self.kf_poses(a), self.f, 0.1))
            for a, r in self.reg.agents.items()
        ]
        return [u for u in self.sharing.updates(self.group, maps) if u.agent_id == "a0"]

    def deliver(self, update: ServerUpdate) -> None:
        """The agent applies the update and its `UpdateAck` reaches the server."""
        self.link.apply_update(update)
        self.sharing.acked("a0", self.link.update_seq)

    def agent_holds(self) -> set[int]:
        pm = self.link.odometry.point_map
        key = self.link.foreign_index.get("b1")
        return set(pm.point_id[pm.agent_id == key].tolist()) if key is not None else set()


def test_a_lost_update_is_repaired_and_the_agent_holds_all_the_server_believes_delivered():
    s = Sharing()
    (lost,) = s.updates()
    assert len(lost.foreign[0].point_ids) == 30
    assert s.sharing.foreign.delivered("a0") == {}  # nothing is delivered before its ack
    assert s.sharing.due([s.group]) == []
    s.clock.advance(5.0)
    assert s.sharing.due([s.group]) == [s.group]  # unacknowledged: the group is due again
    (repair,) = s.updates()
    s.deliver(repair)
    delivered = set(s.sharing.foreign.delivered("a0")["b1"])
    assert delivered == set(range(30)) and s.agent_holds() == delivered
    s.deliver(lost)  # the lost one turns up late: applied never (older than the last)
    assert s.link.stats["updates"] == 1 and s.agent_holds() == delivered
    assert not s.sharing.foreign.pending("a0")  # nothing left to repair for a0


def test_a_large_update_is_split_and_a_lost_part_is_repaired():
    s = Sharing(max_points=8)
    parts = s.updates()
    assert len(parts) == 4 and [u.seq for u in parts] == [1, 2, 3, 4]
    assert sum(len(u.foreign[0].point_ids) for u in parts) == 30
    for u in parts:
        if u.seq != 2:  # part 2 is lost
            s.deliver(u)
    lost = set(parts[1].foreign[0].point_ids.tolist())
    assert s.agent_holds() == set(range(30)) - lost
    assert set(s.sharing.foreign.delivered("a0")["b1"]) <= s.agent_holds()
    s.clock.advance(5.0)
    for u in s.updates():
        s.deliver(u)
    assert s.agent_holds() == set(range(30)) == set(s.sharing.foreign.delivered("a0")["b1"])


def test_a_forged_huge_update_seq_is_ignored_and_real_updates_still_apply():
    s = Sharing()
    (real,) = s.updates()
    forged = real.model_copy(update={"seq": 2**63 - 1})
    assert not s.link.apply_update(forged)
    assert s.link.update_seq == 0
    s.deliver(real)
    assert s.link.update_seq == 1 and s.agent_holds() == set(range(30))
    # A forged update ack above what the server sent is ignored too.
    assert not s.sharing.acked("a0", 2**62) and s.sharing.ignored_acks == 1

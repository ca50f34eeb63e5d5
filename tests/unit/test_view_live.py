"""The live observer on the in-memory bus: real protocol messages from an agent and a server
stand-in become keyframes, points, trajectories, loop edges, events and time series, and the
observer publishes nothing."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest
from view_rrd import last, positions, read_rrd, strips

from cpslam import protocol
from cpslam.common.bus import InMemoryBus, InMemoryNetwork
from cpslam.protocol import (
    FramePoses,
    GroupDecoder,
    KeyframeImage,
    KeyframeMsg,
    ServerUpdate,
    Status,
    SubmapDelta,
    keys,
)

pytest.importorskip("rerun")

S = "viewtest"


def _pose(x: float = 0.0, y: float = 0.0, yaw: float = 0.0) -> np.ndarray:
    T = np.eye(4)
    c, s = np.cos(yaw), np.sin(yaw)
    T[:2, :2] = [[c, -s], [s, c]]
    T[:3, 3] = [x, y, 0.0]
    return T


def _descriptor() -> np.ndarray:
    d = np.ones(8, np.float32)
    return d / np.linalg.norm(d)


class _Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def _wait(condition, what: str) -> None:
    deadline = time.monotonic() + 20.0  # only bounds a hang; the messages arrive in ms
    while not condition():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.005)


def _image(kf: int) -> bytes:
    rgb = np.full((12, 16, 3), 40 * kf, np.uint8)
    return protocol.encode(KeyframeImage(agent_id="a0", kf_id=kf, fx=10.0, fy=10.0, cx=7.5,
                                         cy=5.5, width=16, height=12, rgb_codec="png",
                                         rgb=rgb))


def test_observer_follows_a_session_without_publishing(tmp_path: Path) -> None:
    from cpslam.tools.view.live import Observer
    from cpslam.tools.view.sink import Scene, open_recording

    network = InMemoryNetwork()
    agent, server, viewer = (InMemoryBus(network) for _ in range(3))
    published = []
    viewer.publish = lambda *args: published.append(args)  # must never be called
    T_kf = {0: _pose(), 1: _pose(1.0, 0.0, 0.3)}
    recent = [{"loop_id": 0, "agent_a": "a0", "kf_a": 1, "agent_b": "a1", "kf_b": 0,
               "score": 0.91, "kind": "fine", "accepted": True},
              {"loop_id": 1, "agent_a": "a0", "kf_a": 0, "agent_b": "a0", "kf_b": 1,
               "score": 0.55, "kind": "coarse", "accepted": False}]
    summary = {"agents": {"a0": {"keyframes": 2, "frames": 3, "points": 2, "bytes": 5000}},
               "groups": {"a0": {"members": ["a0", "a1"]}}, "merges": 1,
               "rounds": {"closed": 1, "open": []},
               "loops": {"found": 2, "accepted": 1, "rejected": 1, "pending": 0,
                         "recent": recent}}
    server.declare_queryable(keys.server_status(S), lambda k, p: protocol.encode(
        Status(stamp=1.0, summary=summary)))
    agent.declare_queryable(keys.agent_image_queryable(S, "a0"),
                            lambda k, p: _image(int(k.rsplit("/", 1)[1])))
    clock = _Clock()
    rrd = tmp_path / "live.rrd"
    scene = Scene(open_recording("live-test", save=rrd))
    observer = Observer(viewer, S, scene, clock=clock)
    observer.start()

    for kf, T in T_kf.items():
        agent.publish(keys.agent_keyframe(S, "a0"), protocol.encode(KeyframeMsg(
            agent_id="a0", seq=kf, kf_id=kf, frame_index=10 * kf, stamp=kf * 1.0,
            T_world_cam=T, descriptor=_descriptor())))
    _wait(lambda: observer.messages == 2, "the keyframes")
    xyz = np.array([[0, 0, 1], [0, 0, 2], [0.5, 0, 1]], np.float32)
    agent.publish(keys.agent_submap(S, "a0"), protocol.encode(SubmapDelta(
        agent_id="a0", seq=2, point_ids=np.arange(3), anchor_kf_ids=np.array([0, 1, 1], np.int32),
        xyz_local=xyz, features=np.zeros((3, 4), np.float16),
        colors=np.full((3, 3), 200, np.uint8), removed_ids=np.zeros(0, np.int64))))
    agent.publish(keys.agent_submap(S, "a0"), protocol.encode(SubmapDelta(
        agent_id="a0", seq=3, point_ids=np.zeros(0, np.int64),
        anchor_kf_ids=np.zeros(0, np.int32), xyz_local=np.zeros((0, 3), np.float32),
        features=np.zeros((0, 4), np.float16), colors=np.zeros((0, 3), np.uint8),
        removed_ids=np.array([1]))))
    T_kf_frame = np.stack([_pose(0.1), _pose(0.2), _pose(0.1)])
    agent.publish(keys.agent_frames(S, "a0"), protocol.encode(FramePoses(
        agent_id="a0", seq=4, frame_indices=np.array([1, 2, 11]),
        stamps=np.array([0.1, 0.2, 1.1]), kf_ids=np.array([0, 0, 1], np.int32),
        T_kf_frame=T_kf_frame)))
    agent.publish(keys.agent_keyframe("other", "a9"), protocol.encode(KeyframeMsg(
        agent_id="a9", seq=0, kf_id=0, frame_index=0, stamp=0.0, T_world_cam=_pose(),
        descriptor=_descriptor())))  # another session: not ours
    agent.publish(keys.agent_keyframe(S, "a1"), b"\x93not a message")
    agent.publish(keys.agent_keyframe(S, "a1"), protocol.encode(KeyframeMsg(
        agent_id="a1", seq=0, kf_id=0, frame_index=0, stamp=0.0, T_world_cam=_pose(),
        descriptor=_descriptor())))
    _wait(lambda: observer.messages == 6 and observer.rejected == 1, "agent messages")
    # The server aligns a1 into a0's group: a1's world is 2 m along y in the group frame.
    T_group_a1 = _pose(0.0, 2.0)
    server.publish(keys.server_agent_update(S, "a1"), protocol.encode(ServerUpdate(
        agent_id="a1", seq=0, epoch=1, group_id="a0", group_members=["a0", "a1"],
        T_group_agent=T_group_a1, kf_ids=np.zeros(0, np.int32),
        T_group_kf=np.zeros((0, 4, 4)))))
    server.publish(keys.server_group_decoder(S, "a0"), protocol.encode(GroupDecoder(
        group_id="a0", round=1, members=["a0", "a1"], n_samples=500,
        tensors={"w": np.ones((2, 2), np.float32)})))
    _wait(lambda: observer.messages == 8, "server messages")
    clock.t = 3.0
    assert observer.poll(final=True) == summary
    observer.close()
    scene.close()
    for bus in (agent, server, viewer):
        bus.close()

    assert not published
    data = read_rrd(rrd)
    for kf, T in T_kf.items():
        rows = data[f"world/agents/a0/keyframes/{kf}"]
        np.testing.assert_allclose(last(rows, "Transform3D:translation")[0], T[:3, 3])
        assert last(rows, "Pinhole:resolution") == [[16.0, 12.0]]  # from the image reply
        assert last(data[f"world/agents/a0/keyframes/{kf}/image"], "EncodedImage:blob")
    # Point 1 was removed; the others sit at their keyframe's pose.
    expected = np.stack([T_kf[0][:3, :3] @ xyz[0] + T_kf[0][:3, 3],
                         T_kf[1][:3, :3] @ xyz[2] + T_kf[1][:3, 3]])
    np.testing.assert_allclose(positions(data["world/agents/a0/points"]), expected, atol=1e-6)
    (line,) = strips(data["world/agents/a0/trajectory"])
    np.testing.assert_allclose(line, np.stack([(T_kf[k] @ T)[:3, 3] for k, T in
                                               zip((0, 0, 1), T_kf_frame, strict=True)]))
    assert len(data["world/agents/a0/camera"]) == 3
    # a1's keyframe moved into the group frame with T_group_agent.
    a1 = data["world/agents/a1/keyframes/0"]
    np.testing.assert_allclose(last(a1, "Transform3D:translation")[0], [0.0, 2.0, 0.0])
    (accepted,) = strips(data["world/loops/accepted"])
    np.testing.assert_allclose(accepted, [T_kf[1][:3, 3], [0.0, 2.0, 0.0]])
    (rejected,) = strips(data["world/loops/rejected"])
    np.testing.assert_allclose(rejected, [T_kf[0][:3, 3], T_kf[1][:3, 3]])
    assert len(data["events/loops"]) == 2 and len(data["events/merges"]) == 1
    assert len(data["events/rounds"]) == 1
    assert last(data["status/agents/a0/keyframes"], "Scalars:scalars") == [2.0]
    assert last(data["status/loops/accepted"], "Scalars:scalars") == [1.0]
    assert not any(p.startswith("world/agents/a9") for p in data)

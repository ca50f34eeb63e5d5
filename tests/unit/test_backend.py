"""The back end driven with the messages of two fake agents in a synthetic apartment.

Ground truth is used only to build the inputs: each agent's poses are the truth re-expressed
in its own first camera plus a small drift, sub-maps come from the true depth, and descriptors
are planted as a bag of the world voxels a keyframe sees (so that cosine similarity follows
true overlap); the database is a plain cosine search. Registration is the real one.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from fake_clock import FakeClock
from spec_helpers import finetune_args, spec
from voxel_place import voxel_descriptor

from cpslam.common.config.collab import (
    FederationConfig,
    LoopConfig,
    PoseGraphConfig,
    RefinementConfig,
)
from cpslam.common.field import Decoders, FeatureCNN, patch_points
from cpslam.common.geometry import compose, invert, se3_exp
from cpslam.protocol import (
    Ack,
    DecoderWeights,
    FramePoses,
    GroupDecoder,
    KeyframeImage,
    KeyframeMsg,
    ServerUpdate,
    SubmapDelta,
)
from cpslam.server.backend import Backend
from cpslam.server.export import export_run
from cpslam.server.loops import LoopCandidate

F = 8
KF_EVERY = 50
FRAMES = 300
AGENTS = ("a0", "a1")

pytestmark = pytest.mark.slow  # one shared scenario: ~30 s with the real registration


SPEC = spec(feature_dim=F, pe_offset_order=2, c_hidden=16, g_hidden=16, u_hidden=16,
            u_layers=1)


def small_decoders(seed: int = 0) -> Decoders:
    return SPEC.decoders(seed)


class CosineDatabase:
    """Inter-agent cosine search with the two thresholds (stands in for `DescriptorDatabase`)."""

    def __init__(self, fine: float, coarse: float) -> None:
        self.fine, self.coarse = fine, coarse
        self.entries: list[tuple[str, int, np.ndarray]] = []

    def add(self, agent: str, kf: int, descriptor: np.ndarray, group: str) -> None:
        self.entries.append((agent, kf, descriptor))

    def query(self, agent: str, kf: int, descriptor: np.ndarray) -> list[LoopCandidate]:
        out = []
        for other, okf, d in self.entries:
            score = float(d @ descriptor)
            if other != agent and score >= self.coarse:
                kind = "fine" if score >= self.fine else "coarse"
                out.append(LoopCandidate(other, okf, agent, kf, score, kind))
        return sorted(out, key=lambda c: -c.score)[:1]


@pytest.fixture(scope="module")
def scenario():
    from cpslam.tools.synth.render import Renderer, default_intrinsics
    from cpslam.tools.synth.scene import build_scene
    from cpslam.tools.synth.trajectory import plan_trajectories

    world = build_scene("apartment", 0)
    truth = plan_trajectories(world, 2, FRAMES, False, 0)
    intr = default_intrinsics(160, 120)
    renderer = Renderer(world, intr)
    cnn = FeatureCNN(F, seed=0)
    agents = {}
    for i, agent in enumerate(AGENTS):
        T_gt = truth[i]
        own = compose(invert(T_gt[0])[None], T_gt)  # truth in the agent's first camera
        drift = np.stack([se3_exp(np.array([1e-3, 0, 5e-4, 0, 5e-4, 0]) * f / KF_EVERY)
                          for f in range(FRAMES)])
        reported = compose(drift, own)
        kfs = list(range(0, FRAMES, KF_EVERY))
        images, descs = {}, {}
        for kf_id, f in enumerate(kfs):
            img = renderer.render(T_gt[f])
            images[kf_id] = (img.rgb, img.depth.astype(np.float32))
            descs[kf_id] = voxel_descriptor(img.depth, intr, T_gt[f])
        agents[agent] = dict(kfs=kfs, reported=reported, images=images, descs=descs,
                             T_world_own=T_gt[0])
    T_0_1 = compose(invert(truth[0][0]), truth[1][0])  # agent 1's world in agent 0's
    return dict(intr=intr, agents=agents, cnn=cnn, T_0_1=T_0_1)


def agent_messages(scenario, agent: str, seq0: int = 0):
    """Keyframes, sub-map deltas, frame poses and decoder weights of one agent, in order."""
    a = scenario["agents"][agent]
    intr, cnn = scenario["intr"], scenario["cnn"]
    msgs, seq, next_id = [], seq0, 0
    rep = a["reported"]
    for kf_id, f in enumerate(a["kfs"]):
        prev = None if kf_id == 0 else compose(invert(rep[a["kfs"][kf_id - 1]]), rep[f])
        msgs.append(KeyframeMsg(agent_id=agent, seq=seq, kf_id=kf_id, frame_index=f,
                                stamp=f / 30.0, T_world_cam=rep[f], T_prev_kf_kf=prev,
                                descriptor=a["descs"][kf_id]))
        seq += 1
        rgb, depth = a["images"][kf_id]
        xyz, feats, colors = patch_points(rgb, depth, intr, np.eye(4), cnn, patch=8)
        keep = np.arange(0, len(xyz), 2)
        n = len(keep)
        msgs.append(SubmapDelta(agent_id=agent, seq=seq, point_ids=np.arange(next_id, next_id + n),
                                anchor_kf_ids=np.full(n, kf_id, np.int32),
                                xyz_local=xyz[keep].numpy(), features=feats[keep].numpy(),
                                colors=colors[keep].numpy(), removed_ids=np.zeros(0, np.int64)))
        next_id += n
        seq += 1
        frames = np.arange(f + 5, min(f + KF_EVERY, FRAMES), 5)
        msgs.append(FramePoses(agent_id=agent, seq=seq, frame_indices=frames,
                               stamps=frames / 30.0, kf_ids=np.full(len(frames), kf_id, np.int32),
                               T_kf_frame=compose(invert(rep[f])[None], rep[frames])))
        seq += 1
    weights = {k: v.numpy() for k, v in small_decoders(AGENTS.index(agent)).state_dict().items()}
    msgs.append(DecoderWeights(agent_id=agent, seq=seq, group_id=agent, round=0,
                               n_samples=1000, tensors=weights))
    return msgs


def make_backend(scenario, clock, **kw):
    agents = scenario["agents"]
    intr = scenario["intr"]

    def fetch(agent: str, kf: int) -> KeyframeImage | None:
        rgb, depth = agents[agent]["images"][kf]
        return KeyframeImage.from_metres(depth, 1000.0, agent_id=agent, kf_id=kf, fx=intr.fx,
                                         fy=intr.fy, cx=intr.cx, cy=intr.cy, width=intr.width,
                                         height=intr.height, rgb_codec="png", rgb=rgb)

    args = dict(loop=LoopConfig(lambda_fine=0.9, lambda_coarse=0.85, icp_voxel_size=0.08),
                federation=FederationConfig(finetune_iters=2, round_timeout_s=5.0),
                pose_graph=PoseGraphConfig(), refinement=RefinementConfig(finetune_iters=2),
                fetch_image=fetch, spec=SPEC, now=clock,
                database=CosineDatabase(0.9, 0.85), decoders_factory=small_decoders,
                **finetune_args())
    args.update(kw)
    return Backend(**args)


def rotation_deg(R):
    return np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1)))


@pytest.fixture(scope="module")
def run(scenario):
    clock = FakeClock(0.0)
    backend = make_backend(scenario, clock)
    streams = [agent_messages(scenario, a) for a in AGENTS]
    out = []
    for i in range(max(map(len, streams))):
        for s in streams:
            if i < len(s):
                out += backend.handle(s[i], nbytes=100)
        if i % 3 == 2:
            clock.advance(1.0)
            out += backend.step()
    clock.advance(1.0)
    out += backend.step()
    return backend, out, clock


def test_inter_agent_loop_merges_groups_and_aligns(run, scenario):
    backend, out, _ = run
    accepted = [lp for lp in backend.loops if lp.accepted]
    assert backend.loops_found >= 1 and accepted, [lp.reason for lp in backend.loops]
    assert backend.merges, "no merge happened"
    # Each stage of the merge is timed; the whole is their sum.
    stages = backend.merges[0]["stages"]
    assert set(stages) == {"verify_s", "align_s", "decoders_s", "pose_graph_s", "push_s"}
    assert all(v >= 0 for v in stages.values()) and stages["verify_s"] > 0
    assert backend.merges[0]["seconds"] == pytest.approx(sum(stages.values()), abs=1e-3)
    assert len(backend.groups.groups) == 1
    group = backend.groups.group_of("a1")
    assert sorted(group.members) == ["a0", "a1"]
    T = group.T_group_agent["a1"] if group.anchor == "a0" else invert(group.T_group_agent["a0"])
    err = compose(invert(scenario["T_0_1"]), T)
    assert np.linalg.norm(err[:3, 3]) < 0.03
    assert rotation_deg(err[:3, :3]) < 2.0


def test_updates_and_group_decoder_emitted(run):
    backend, out, _ = run
    updates = [o.message for o in out if isinstance(o.message, ServerUpdate)]
    assert {u.agent_id for u in updates} == set(AGENTS)
    merged = [u for u in updates if len(u.group_members) == 2]
    for agent in AGENTS:
        last = [u for u in merged if u.agent_id == agent][-1]
        assert last.foreign and last.foreign[0].source_agent_id != agent
        assert sum(len(u.foreign[0].point_ids) for u in merged if u.agent_id == agent) > 0
        assert len(last.kf_ids) == len(backend.registry.agents[agent].keyframes)
    decoders = [o for o in out if isinstance(o.message, GroupDecoder)]
    assert decoders and decoders[0].scope == "group"
    assert sorted(decoders[0].message.members) == sorted(AGENTS)
    acks = [o.message for o in out if isinstance(o.message, Ack)]
    assert max(a.seq for a in acks if a.agent_id == "a0") == backend.registry.agents[
        "a0"].seq_floor


def test_fused_map_is_grid_filtered(run):
    from cpslam.common.field.grid import grid_winners
    from cpslam.server.fusion import fuse

    backend, _, _ = run
    group = backend.groups.group_of("a0")
    members = backend.member_maps(group)
    fused = fuse(members, F, backend.spec.grid_size)
    assert 0 < len(fused) < sum(len(m.point_map) for m in members)
    xyz = fused.xyz_world().double().numpy()
    assert grid_winners(xyz, backend.spec.grid_size).all()


def test_federated_round_closes_on_timeout(run, scenario):
    backend, _, clock = run
    group = backend.groups.group_of("a0")
    weights = {k: v.numpy() for k, v in small_decoders(5).state_dict().items()}
    msg = DecoderWeights(agent_id="a0", seq=10_000, group_id=group.group_id, round=group.round,
                         n_samples=10, tensors=weights)
    backend.registry.agents["a0"].seqs_above.discard(10_000)
    backend.handle(msg)
    out = backend.step()
    assert not [o for o in out if isinstance(o.message, GroupDecoder)]
    assert group.group_id in backend.rounds
    clock.advance(6.0)  # a1 stays silent past the 5 s timeout
    out = backend.step()
    dec = [o.message for o in out if isinstance(o.message, GroupDecoder)]
    assert len(dec) == 1 and dec[0].members == ["a0"]
    assert backend.rounds_closed[-1]["timed_out"]
    np.testing.assert_allclose(dec[0].tensors["c_out.weight"], weights["c_out.weight"])


def test_state_dict_round_trip_reproduces_status(run, scenario, tmp_path):
    backend, _, clock = run
    path = tmp_path / "state.pt"
    torch.save(backend.state_dict(), path)
    other = make_backend(scenario, clock)
    other.load_state_dict(torch.load(path, weights_only=True))
    assert other.status() == backend.status()
    assert len(other.database.entries) == sum(len(r.keyframes) for r in
                                              backend.registry.agents.values())


def test_a_restored_backend_applies_decoder_deltas_against_the_current_group_decoder(
        run, scenario, tmp_path):
    backend, _, clock = run
    other = make_backend(scenario, clock)
    other.load_state_dict(backend.state_dict())
    shared = [g for g in other.groups.groups.values() if g.decoder is not None and g.round > 0]
    assert shared, "the scenario closes no federated round"
    for group in shared:
        zero = {k: np.zeros_like(v) for k, v in group.decoder.items()}
        rebuilt = other.registry.decoder_bases.apply(group.group_id, group.round, zero)
        assert not isinstance(rebuilt, str), rebuilt
        for name, value in group.decoder.items():
            np.testing.assert_array_equal(rebuilt[name], value)


def test_finalise_and_export_write_every_file(run, scenario, tmp_path):
    backend, _, _ = run
    result = backend.finalise()
    written = export_run(result, tmp_path)
    for agent in AGENTS:
        for kind in ("local", "global"):
            assert (tmp_path / "trajectories" / f"agent_{agent}_{kind}.tum").is_file()
    for name in ("fused_map.ply", "fused_map.pt", "pose_graph.g2o", "metrics.json"):
        assert (tmp_path / name).stat().st_size > 0, name
    assert "metrics.json" in written
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert metrics["loops"]["accepted"] >= 1 and metrics["merges"]
    assert metrics["agents"]["a1"]["merged"] and metrics["agents"]["a0"]["bytes"] > 0
    a1 = next(a for a in result.agents if a.agent_id == "a1")
    # The global trajectory of a1 starts near its true start in a0's world.
    T_truth = scenario["T_0_1"]
    start = a1.T_group_cam[0] if result.agents[0].group_id == "a0" else None
    if start is not None:
        assert np.linalg.norm(start[:3, 3] - T_truth[:3, 3]) < 0.05
    frames = {a.agent_id: len(a.stamps) for a in result.agents}
    assert frames["a0"] == len(range(0, FRAMES, 5))

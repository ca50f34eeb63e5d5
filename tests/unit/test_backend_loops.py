"""Loops within one agent through the back end: a drifting agent's loop is found, verified
by the real registration and accepted, and the pose graph pulls its keyframes and frames back
towards the truth; pairs whose keyframe images could not be pulled are tried again (a few
times) while verified pairs are not; ``loop.coarse_method: none`` starts the refinement at
the identity.

Ground truth builds the inputs only: the agent reports the truth in its first camera plus a
drift that grows with every frame; descriptors are planted as the bag of world voxels a
keyframe sees (cosine follows true overlap, as in test_backend.py); the loop database is the
real `DescriptorDatabase`.
"""

from __future__ import annotations

import numpy as np
import pytest
from fake_clock import FakeClock
from spec_helpers import finetune_args, spec
from voxel_place import voxel_descriptor

from cpslam.common.config.collab import (
    FederationConfig,
    LoopConfig,
    PoseGraphConfig,
    RefinementConfig,
)
from cpslam.common.geometry import compose, invert, se3_exp
from cpslam.common.registration import Registration
from cpslam.protocol import FramePoses, KeyframeImage, KeyframeMsg, ServerUpdate
from cpslam.server.backend import Backend
from cpslam.server.loops import DescriptorDatabase, LoopCandidate

FRAMES = 120
KF_EVERY = 10
AGENT = "solo"
# Per-frame drift of the reported odometry: 0.6 mm and 0.4 mrad (6.6 cm, 2.5 deg at the end).
DRIFT = np.array([6e-4, 0.0, 2e-4, 0.0, 4e-4, 0.0])


def rotation_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))


@pytest.fixture(scope="module")
def scenario() -> dict:
    """A closed loop in the synthetic room: true poses in the agent's own world (its first
    camera), drifted reported poses, keyframe images and planted descriptors."""
    from cpslam.tools.synth.render import Renderer, default_intrinsics
    from cpslam.tools.synth.scene import build_scene
    from cpslam.tools.synth.trajectory import plan_trajectories

    world = build_scene("room", 0)
    gt = plan_trajectories(world, 1, FRAMES, True, 0)[0]
    intr = default_intrinsics(160, 120)
    renderer = Renderer(world, intr)
    truth = compose(invert(gt[0])[None], gt)
    drift = np.stack([se3_exp(DRIFT * f) for f in range(FRAMES)])
    reported = compose(drift, truth)
    kfs = list(range(0, FRAMES, KF_EVERY))
    images, descs = {}, {}
    for kf_id, f in enumerate(kfs):
        img = renderer.render(gt[f])
        images[kf_id] = (img.rgb, img.depth.astype(np.float32))
        descs[kf_id] = voxel_descriptor(img.depth, intr, gt[f])
    return dict(intr=intr, truth=truth, reported=reported, kfs=kfs, images=images, descs=descs)


def image(scenario: dict, kf: int) -> KeyframeImage:
    intr = scenario["intr"]
    rgb, depth = scenario["images"][kf]
    return KeyframeImage.from_metres(depth, 1000.0, agent_id=AGENT, kf_id=kf, fx=intr.fx,
                                     fy=intr.fy, cx=intr.cx, cy=intr.cy, width=intr.width,
                                     height=intr.height, rgb_codec="png", rgb=rgb)


def messages(scenario: dict) -> list:
    """Keyframes (with their odometry links) and frame poses of the drifting agent."""
    rep, kfs = scenario["reported"], scenario["kfs"]
    msgs, seq = [], 0
    for kf_id, f in enumerate(kfs):
        prev = None if kf_id == 0 else compose(invert(rep[kfs[kf_id - 1]]), rep[f])
        msgs.append(KeyframeMsg(agent_id=AGENT, seq=seq, kf_id=kf_id, frame_index=f,
                                stamp=f / 30.0, T_world_cam=rep[f], T_prev_kf_kf=prev,
                                descriptor=scenario["descs"][kf_id]))
        frames = np.arange(f + 5, min(f + KF_EVERY, FRAMES), 5)
        msgs.append(FramePoses(agent_id=AGENT, seq=seq + 1, frame_indices=frames,
                               stamps=frames / 30.0,
                               kf_ids=np.full(len(frames), kf_id, np.int32),
                               T_kf_frame=compose(invert(rep[f])[None], rep[frames])))
        seq += 2
    return msgs


def loop_config(**kw) -> LoopConfig:
    # Thresholds for the planted descriptors; keyframes 5 apart and more may close a loop.
    return LoopConfig(**{"lambda_fine": 0.95, "lambda_coarse": 0.9, "min_keyframe_gap": 5,
                         "max_candidates": 2, **kw})


def backend(scenario: dict, clock: FakeClock, fetch=None, **kw) -> Backend:
    loop = kw.pop("loop", loop_config())
    args = dict(loop=loop, federation=FederationConfig(enabled=False),
                pose_graph=PoseGraphConfig(), refinement=RefinementConfig(finetune_iters=0),
                fetch_image=fetch or (lambda agent, kf: image(scenario, kf)),
                spec=spec(feature_dim=8), now=clock, **finetune_args(),
                database=DescriptorDatabase.from_config(loop))
    args.update(kw)
    return Backend(**args)


def position_errors(poses: np.ndarray, truth: np.ndarray) -> np.ndarray:
    return np.linalg.norm(poses[:, :3, 3] - truth[:, :3, 3], axis=1)


def test_single_agent_loop_closure_corrects_the_drift(scenario):
    clock = FakeClock(0.0)
    be = backend(scenario, clock)
    out = []
    for msg in messages(scenario):
        out += be.handle(msg)
        if isinstance(msg, FramePoses):
            clock.advance(1.0)
            out += be.step()
    accepted = [lp for lp in be.loops if lp.accepted]
    assert accepted, [(lp.kf_a, lp.kf_b, lp.reason) for lp in be.loops]
    assert all(lp.agent_a == lp.agent_b == AGENT for lp in be.loops)
    assert not be.merges and len(be.groups.groups) == 1
    truth, kfs = scenario["truth"], scenario["kfs"]
    # Each accepted edge is close to the true relative pose (the registration is real).
    for lp in accepted:
        T_true = compose(invert(truth[kfs[lp.kf_a]]), truth[kfs[lp.kf_b]])
        err = compose(invert(T_true), np.asarray(lp.T_a_b))
        assert np.linalg.norm(err[:3, 3]) < 0.02 and rotation_deg(err[:3, :3]) < 1.0

    # Keyframes: the corrected poses the agent is sent, against the reported ones.
    update = [o.message for o in out if isinstance(o.message, ServerUpdate)][-1]
    kf_truth = truth[[kfs[k] for k in update.kf_ids]]
    kf_reported = scenario["reported"][[kfs[k] for k in update.kf_ids]]
    before = position_errors(kf_reported, kf_truth)
    after = position_errors(update.T_group_kf, kf_truth)
    assert before.max() > 0.05  # the drift is there to be fixed
    assert after.mean() < before.mean() / 3, (before.round(3), after.round(3))
    assert after.max() < before.max() / 2

    # Frames: the final trajectory (every frame reported, keyframes included).
    result = be.finalise()
    (agent,) = result.agents
    frames = np.rint(agent.stamps * 30.0).astype(int)
    assert len(frames) == len(range(0, FRAMES, 5))
    before = position_errors(scenario["reported"][frames], truth[frames])
    after = position_errors(agent.T_own_cam, truth[frames])
    assert after.mean() < before.mean() / 3, (before.round(3), after.round(3))
    rot_before = [rotation_deg(invert(t)[:3, :3] @ r[:3, :3])
                  for t, r in zip(truth[frames], scenario["reported"][frames], strict=True)]
    rot_after = [rotation_deg(invert(t)[:3, :3] @ r[:3, :3])
                 for t, r in zip(truth[frames], agent.T_own_cam, strict=True)]
    assert np.mean(rot_after) < np.mean(rot_before) / 2


def feed(be: Backend, scenario: dict, clock: FakeClock, until_kf: int) -> list:
    """Keyframes 0..until_kf and their frames, a step after each."""
    out = []
    for msg in messages(scenario):
        if getattr(msg, "kf_id", None) is not None and msg.kf_id > until_kf:
            break
        if isinstance(msg, FramePoses) and int(msg.kf_ids[0]) > until_kf:
            break
        out += be.handle(msg)
        if isinstance(msg, FramePoses):
            out += be.step()
    return out


class FlakyImages:
    """Keyframe images, except that keyframe `missing` is unavailable for its first
    `failures` requests."""

    def __init__(self, scenario: dict, missing: int, failures: int) -> None:
        self.scenario, self.missing, self.failures = scenario, missing, failures
        self.requests: list[int] = []

    def __call__(self, agent: str, kf: int) -> KeyframeImage | None:
        self.requests.append(kf)
        if kf == self.missing and self.requests.count(kf) <= self.failures:
            return None
        return image(self.scenario, kf)


def test_unavailable_image_is_retried_until_the_pair_verifies(scenario):
    clock = FakeClock(0.0)
    fetch = FlakyImages(scenario, missing=0, failures=2)
    be = backend(scenario, clock, fetch=fetch, loop=loop_config(max_attempts=3),
                 retry_after_s=5.0)
    feed(be, scenario, clock, until_kf=5)  # keyframe 5 finds keyframe 0; its image is missing
    assert fetch.requests.count(0) == 1 and not be.loops  # a failed try is no verdict
    assert be.status()["loops"]["retrying"] == 1
    be.step()
    assert fetch.requests.count(0) == 1  # not due yet
    # The retry survives a restart of the server.
    other = backend(scenario, clock, fetch=fetch, loop=loop_config(max_attempts=3))
    other.load_state_dict(be.state_dict())
    assert other.book.attempts(other._candidates[0]) == 1
    clock.advance(5.0)
    be.step()
    assert fetch.requests.count(0) == 2 and not be.loops  # second failure: image fetched again
    clock.advance(5.0)
    be.step()
    assert fetch.requests.count(0) == 3
    (record,) = be.loops
    assert (record.kf_a, record.kf_b, record.accepted) == (5, 0, True)
    loops = be.status()["loops"]
    # The status lists the verified pair itself (what a live view draws).
    assert loops.pop("recent") == [{"loop_id": record.loop_id, "agent_a": record.agent_a,
                                    "kf_a": 5, "agent_b": record.agent_b, "kf_b": 0,
                                    "score": record.score, "kind": record.kind,
                                    "accepted": True}]
    assert loops == {"found": 1, "skipped": 0, "accepted": 1, "rejected": 0, "pending": 0,
                     "retrying": 0}
    clock.advance(50.0)
    be.step()
    assert fetch.requests.count(0) == 3 and len(be.loops) == 1  # verified: never again


def test_image_that_never_comes_rejects_the_pair_after_max_attempts(scenario):
    clock = FakeClock(0.0)
    fetch = FlakyImages(scenario, missing=0, failures=10**6)
    be = backend(scenario, clock, fetch=fetch, loop=loop_config(max_attempts=2),
                 retry_after_s=1.0)
    feed(be, scenario, clock, until_kf=5)
    for _ in range(4):
        clock.advance(1.0)
        be.step()
    assert fetch.requests.count(0) == 2
    (record,) = be.loops
    assert not record.accepted and record.reason == "keyframe image unavailable (2 tries)"
    assert be.book.status(record) == "rejected"


def test_verified_pair_is_not_verified_again(scenario):
    """A database that offers the same rejected pair with every keyframe: one registration."""
    clock = FakeClock(0.0)
    pair = LoopCandidate(AGENT, 5, AGENT, 0, 0.99, "fine")

    class Always:
        def add(self, *args, **kwargs):
            pass

        def query(self, agent, kf, descriptor):
            return [pair] if kf >= 5 else []

    calls = []

    def register(src, dst):
        calls.append((src.kf_id, dst.kf_id))
        return Registration(np.eye(4), 0.1, 0.2, 10, "ransac+icp", False, "no overlap")

    be = backend(scenario, clock, database=Always(), register=register)
    feed(be, scenario, clock, until_kf=9)
    assert calls == [(0, 5)]
    (record,) = be.loops
    assert not record.accepted and record.reason == "no overlap"
    assert be.loops_found == 1


def test_coarse_method_none_refines_from_the_identity(scenario):
    """No coarse stage (the paper): the refinement starts at the identity and is run although
    the identity itself fails verification; without a refiner the pair is judged at the
    identity."""
    from cpslam.common.registration import RegistrationParams, verify

    truth, kfs, intr = scenario["truth"], scenario["kfs"], scenario["intr"]
    T_true = compose(invert(truth[kfs[5]]), truth[kfs[0]])  # T_a_b of the pair (5, 0)
    starts = []

    def refine(cand, T_a_b, img_a, img_b):
        # Stands in for the PoseRefiner converging to the true pose.
        starts.append(np.array(T_a_b))
        out = verify((img_b.rgb, img_b.depth_metres()), (img_a.rgb, img_a.depth_metres()),
                     intr, T_true, RegistrationParams())
        out.method = "render"
        return out

    for refine_pose in (refine, None):
        clock = FakeClock(0.0)
        be = backend(scenario, clock, loop=loop_config(coarse_method="none"),
                     refine_pose=refine_pose)
        feed(be, scenario, clock, until_kf=5)
        (record,) = be.loops
        if refine_pose is None:
            assert record.method == "identity" and not record.accepted
            assert np.allclose(record.T_a_b, np.eye(4))
        else:
            np.testing.assert_array_equal(starts[0], np.eye(4))
            assert record.method == "render" and record.accepted, record.reason
            np.testing.assert_allclose(record.T_a_b, T_true, atol=1e-9)


def test_without_verification_the_identity_is_kept(scenario):
    """`loop.verify: false` (the paper preset): the same pair that fails verification at the
    identity becomes a loop at the identity, without an information matrix (sigmas weigh it)."""
    clock = FakeClock(0.0)
    be = backend(scenario, clock, loop=loop_config(coarse_method="none", verify=False),
                 refine_pose=None)
    feed(be, scenario, clock, until_kf=5)
    (record,) = be.loops
    assert record.method == "identity" and record.accepted, record.reason
    assert record.information is None

"""Loop pose refinement (`cpslam.server.loops.refinement`): tracking a keyframe against
another agent's sub-map held by the registry recovers a perturbed relative pose; the coarse
pose is kept (and rejected when it does not verify) where the refinement cannot help or is not
needed; intra-agent sub-maps leave out the query keyframe's own points; the back end gets a
refiner by default."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest
import torch
from spec_helpers import spec, tracker_args

from cpslam.common.field import Decoders, patch_points
from cpslam.common.geometry import compose, invert, se3_exp
from cpslam.common.registration import RegistrationParams, verify
from cpslam.protocol import DecoderWeights, KeyframeImage, KeyframeMsg, SubmapDelta
from cpslam.server.fusion import View, finetune_decoders
from cpslam.server.loops import PoseRefiner
from cpslam.server.registry import Registry

F = 8
CELL = 0.1
B_FRAMES = (0, 15, 30)  # agent b's keyframes 0, 1, 2
A_FRAME = 22  # the loop keyframe, between b's keyframes 1 and 2


@dataclass(frozen=True)
class Cand:
    agent_a: str
    kf_a: int
    agent_b: str
    kf_b: int
    score: float = 0.9
    kind: str = "fine"


SPEC = spec(feature_dim=F, grid_size=CELL, k_neighbors=6, radius=0.15, pe_offset_order=2,
            c_hidden=16, g_hidden=16, u_hidden=16, u_layers=1, n_near=8, n_uniform=2)


def small_decoders() -> Decoders:
    return SPEC.decoders(seed=0)


def image(agent: str, kf: int, rgbd, intr) -> KeyframeImage:
    rgb, depth = rgbd
    return KeyframeImage.from_metres(depth, 1000.0, agent_id=agent, kf_id=kf, fx=intr.fx,
                                     fy=intr.fy, cx=intr.cx, cy=intr.cy, width=intr.width,
                                     height=intr.height, rgb_codec="png", rgb=rgb)


@pytest.fixture(scope="module")
def scene() -> dict:
    """Agent b's sub-map of a synthetic room (fitted on three views, in b's own world) as the
    registry holds it, and a render function of the true scene."""
    from cpslam.tools.synth.render import Renderer, default_intrinsics
    from cpslam.tools.synth.scene import build_scene
    from cpslam.tools.synth.trajectory import plan_trajectories

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    world = build_scene("room", 0)
    gt = plan_trajectories(world, 1, 40, False, 0)[0]
    intr = default_intrinsics(160, 120)
    renderer = Renderer(world, intr)

    def render(T_world_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        img = renderer.render(T_world_cam)
        return img.rgb, img.depth.astype(np.float32)

    T_b_world = invert(gt[0])  # b's own world is its first camera
    point_map = SPEC.point_map(0, "cpu")
    cnn = SPEC.cnn(0)
    views = []
    for kf, f in enumerate(B_FRAMES):
        T = compose(T_b_world, gt[f])
        rgb, depth = render(gt[f])
        point_map.set_keyframe_poses(kf, T)
        xyz, feats, colors = patch_points(rgb, depth, intr, T, cnn, patch=4)
        point_map.add_points(xyz, kf, feats, colors)
        views.append(View(rgb, depth, T, intr))
    decoders = small_decoders()
    finetune_decoders(decoders, point_map, views, 200, 0.02, 0, SPEC, color_weight=0.2,
                      n_pixels=1200, lr_features=0.02)
    torch.set_num_threads(before)

    registry = Registry(F)
    for kf, f in enumerate(B_FRAMES):
        registry.handle(KeyframeMsg(agent_id="b", seq=kf, kf_id=kf, frame_index=f, stamp=f / 30,
                                    T_world_cam=compose(T_b_world, gt[f]),
                                    descriptor=np.full(4, 0.5, np.float32)))
    n = len(point_map)
    registry.handle(SubmapDelta(
        agent_id="b", seq=3, point_ids=point_map.point_id.numpy(),
        anchor_kf_ids=point_map.anchor_kf.numpy().astype(np.int32),
        xyz_local=point_map.xyz_local.numpy(), features=point_map.features.detach().numpy(),
        colors=point_map.color.numpy(), removed_ids=np.zeros(0, np.int64)))
    assert len(registry.agents["b"].points) == n
    return dict(gt=gt, intr=intr, render=render, registry=registry, decoders=decoders)


def with_weights(registry: Registry, decoders: Decoders) -> Registry:
    registry.handle(DecoderWeights(agent_id="b", seq=4, group_id="b", round=0, n_samples=100,
                                   tensors={k: v.detach().numpy() for k, v in
                                            decoders.state_dict().items()}))
    return registry


def refiner(registry: Registry | None, **kwargs) -> PoseRefiner:
    args = dict(params=RegistrationParams(), seed=0,
                **tracker_args(iters=100, n_pixels=400, lr=0.002))
    args.update(kwargs)
    return PoseRefiner(registry, SPEC, **args)


def errors(T: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """Translation (m) and rotation (degrees) between two poses."""
    E = invert(T_true) @ T
    angle = np.degrees(np.arccos(np.clip((np.trace(E[:3, :3]) - 1) / 2, -1, 1)))
    return float(np.linalg.norm(E[:3, 3])), float(angle)


def loop_pair(scene: dict, T_world_a: np.ndarray) -> tuple[KeyframeImage, KeyframeImage,
                                                           np.ndarray]:
    """Images of keyframe a (agent "a") and b's keyframe 1, and the true T_a_b."""
    gt, intr, render = scene["gt"], scene["intr"], scene["render"]
    img_a = image("a", 0, render(T_world_a), intr)
    img_b = image("b", 1, render(gt[B_FRAMES[1]]), intr)
    return img_a, img_b, compose(invert(T_world_a), gt[B_FRAMES[1]])


def test_refinement_recovers_a_perturbed_relative_pose(scene: dict) -> None:
    registry = with_weights(scene["registry"], scene["decoders"])
    img_a, img_b, T_true = loop_pair(scene, scene["gt"][A_FRAME])
    T_init = se3_exp(np.array([0.02, -0.015, 0.01, 0.02, -0.01, 0.015])) @ T_true
    t0, r0 = errors(T_init, T_true)
    assert t0 > 0.025 and r0 > 1.5
    result = refiner(registry)(Cand("a", 0, "b", 1), T_init, img_a, img_b)
    assert result is not None and result.method == "render", result and result.details
    t1, r1 = errors(result.T_dst_src, T_true)
    assert t1 < 0.5 * t0 and r1 < 0.3, (t1, r1)  # the fitted map is good to about 1 cm
    info = result.details["refinement"]
    assert info["used"] and info["loss_refined"] < info["loss_coarse"]
    np.testing.assert_allclose(info["T_coarse"], T_init)
    # Overlap and residual are those of the refined pose, so the back end's thresholds apply.
    check = verify((img_b.rgb, img_b.depth_metres()), (img_a.rgb, img_a.depth_metres()),
                   scene["intr"], result.T_dst_src)
    assert result.success and result.fitness == check.fitness
    assert result.inlier_rmse == check.inlier_rmse


def test_coarse_pose_that_is_already_right_is_kept(scene: dict) -> None:
    registry = with_weights(scene["registry"], scene["decoders"])
    img_a, img_b, T_true = loop_pair(scene, scene["gt"][A_FRAME])
    result = refiner(registry)(Cand("a", 0, "b", 1), T_true, img_a, img_b)
    # Tracking against the map moves the pose by the map's own error, but the two keyframes
    # agree less there: the coarse pose stays. How far it moves, and whether its loss against
    # the map ends below the coarse pose's, depends on the CPU code path (AVX-512: over 2 mm,
    # lower; AVX2 kernels: 1.7 mm, higher); either way the coarse pose must be kept.
    info = result.details["refinement"]
    assert info["moved_m"] > 1e-4
    assert result.method == "coarse" and info["rmse_refined"] > info["rmse_coarse"]
    np.testing.assert_array_equal(result.T_dst_src, T_true)
    assert result.success and result.inlier_rmse == info["rmse_coarse"]


def test_refinement_that_makes_things_worse_keeps_the_coarse_pose(scene: dict) -> None:
    registry = with_weights(scene["registry"], scene["decoders"])
    img_a, img_b, T_true = loop_pair(scene, scene["gt"][A_FRAME])
    # Steps far too large and the last pose returned: the pose is thrown off the true one.
    wild = refiner(registry, lr=0.05, iters=8, keep_best=False)
    result = wild(Cand("a", 0, "b", 1), T_true, img_a, img_b)
    assert result is not None and result.method == "coarse"
    info = result.details["refinement"]
    assert not info["used"] and "coarse kept" in info["note"] and info["moved_m"] > 0.05
    np.testing.assert_array_equal(result.T_dst_src, T_true)
    assert result.success  # the coarse pose is right and still passes verification


def test_no_overlap_keeps_the_coarse_pose_and_fails_verification(scene: dict) -> None:
    registry = with_weights(scene["registry"], scene["decoders"])
    # Keyframe a looks the other way, where b's camera never looked: neither the map nor b's
    # image can place it. Its coarse pose (here: the truth) does not verify, and stays.
    T_world_a = compose(scene["gt"][B_FRAMES[1]], se3_exp(np.array([0, 0, 0, 0, np.pi, 0])))
    img_a, img_b, T_true = loop_pair(scene, T_world_a)
    result = refiner(registry)(Cand("a", 0, "b", 1), T_true, img_a, img_b)
    assert result is not None and result.method == "coarse" and not result.success
    assert "overlap" in result.reason
    np.testing.assert_array_equal(result.T_dst_src, T_true)


def test_without_decoder_weights_nothing_is_refined(scene: dict) -> None:
    registry = Registry(F)
    registry.agents = {"b": scene["registry"].agents["b"]}
    saved, registry.agents["b"].decoder = registry.agents["b"].decoder, None
    try:
        assert "no decoder weights" in refiner(registry).submap(Cand("a", 0, "b", 1))
        img_a, img_b, T_true = loop_pair(scene, scene["gt"][A_FRAME])
        assert refiner(registry)(Cand("a", 0, "b", 1), T_true, img_a, img_b) is None
        assert refiner(registry)(Cand("a", 0, "zz", 1), T_true, img_a, img_b) is None
    finally:
        registry.agents["b"].decoder = saved


def test_intra_agent_submap_leaves_out_points_mapped_near_the_query_keyframe() -> None:
    registry = Registry(F)
    for kf in range(7):
        registry.handle(KeyframeMsg(agent_id="x", seq=kf, kf_id=10 * kf, frame_index=50 * kf,
                                    stamp=kf, T_world_cam=np.eye(4),
                                    descriptor=np.full(4, 0.5, np.float32)))
    registry.handle(SubmapDelta(
        agent_id="x", seq=7, point_ids=np.arange(7),
        anchor_kf_ids=10 * np.arange(7, dtype=np.int32),
        xyz_local=np.zeros((7, 3), np.float32), features=np.zeros((7, F), np.float32),
        colors=np.zeros((7, 3), np.uint8), removed_ids=np.zeros(0, np.int64)))
    registry.handle(DecoderWeights(
        agent_id="x", seq=8, group_id="x", round=0, n_samples=1,
        tensors={k: v.detach().numpy() for k, v in small_decoders().state_dict().items()}))
    point_map, _, T_x_b = refiner(registry).submap(Cand("x", 50, "x", 10))
    # Keyframe ranks 0-6; b has rank 1, a rank 5: ranks nearer to 1 than to 5 are 0, 1, 2.
    assert sorted(point_map.anchor_kf.tolist()) == [0, 10, 20]
    np.testing.assert_array_equal(T_x_b, np.eye(4))
    other, _, _ = refiner(registry).submap(Cand("y", 0, "x", 10))  # another agent: all of x
    assert len(other) == 7


def test_backend_from_config_gets_a_refiner_unless_switched_off() -> None:
    from cpslam.common.config import load_config
    from cpslam.server.backend import Backend

    cfg = load_config("tiny", overrides=["loop.refine=true"], env={})
    backend = Backend.from_config(cfg, lambda agent, kf: None)
    assert isinstance(backend.refine_pose, PoseRefiner)
    assert backend.refine_pose.registry is backend.registry
    assert backend.refine_pose.tracker_args["iters"] == cfg.loop.register_iters
    off = Backend.from_config(load_config("tiny", env={}), lambda agent, kf: None)
    assert off.refine_pose is None  # the tiny and cpu presets switch it off (docs/loops.md)
    assert load_config("paper", env={}).loop.refine

"""Pose graph: drift removal by loops, robustness to a false loop, several agents, frames, g2o."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from cpslam.common.config.collab import PoseGraphConfig
from cpslam.common.geometry import compose, invert, pose_error, se3_exp
from cpslam.server.pose_graph import (
    CHI2_6DOF_95,
    AgentTrajectory,
    PoseGraph,
    correct_frames,
    loop_sigmas,
)

N_KF = 40
SIDE = 4.0


def graph_with(**changes) -> PoseGraph:
    """A graph with the `pose_graph` section's defaults and `changes`."""
    return PoseGraph(**{**PoseGraphConfig().model_dump(), **changes})


def square(n: int, side: float = SIDE) -> np.ndarray:
    """``T_world_cam [n, 4, 4]`` walking a square counter-clockwise, camera looking ahead."""
    per = n // 4
    corners = np.array([[0.0, 0.0], [side, 0.0], [side, side], [0.0, side]])
    poses = np.tile(np.eye(4), (n, 1, 1))
    for i in range(n):
        s, k = divmod(i, per)
        d = np.array([np.cos(s * np.pi / 2), np.sin(s * np.pi / 2), 0.0])
        y = np.array([0.0, 0.0, -1.0])  # camera y points down
        poses[i, :3, :3] = np.stack([np.cross(y, d), y, d], axis=1)
        poses[i, :2, 3] = corners[s] + d[:2] * side * k / per
    return poses


def odometry(gt: np.ndarray, seed: int, sigma_t: float, sigma_r: float, bias: float):
    """Noisy relative poses ``[n-1]`` with a yaw bias, and the dead-reckoned track ``[n]``."""
    rng = np.random.default_rng(seed)
    rel = compose(invert(gt[:-1]), gt[1:])
    xi = np.concatenate(
        [rng.normal(0, sigma_t, (len(rel), 3)), rng.normal(0, sigma_r, (len(rel), 3))], axis=1
    )
    xi[:, 4] += bias  # about the camera y axis = vertical: a drifting heading
    meas = compose(rel, se3_exp(xi))
    track = [gt[0]]
    for m in meas:
        track.append(track[-1] @ m)
    return meas, np.stack(track)


def true_loops(gt: np.ndarray, seed: int, min_gap: int = 10, radius: float = 1.2):
    """Loop measurements between keyframes near each other, with small noise."""
    rng = np.random.default_rng(seed)
    loops = []
    for i in range(len(gt)):
        for j in range(i + min_gap, len(gt)):
            if np.linalg.norm(gt[i, :3, 3] - gt[j, :3, 3]) < radius:
                noise = se3_exp(np.r_[rng.normal(0, 0.02, 3), rng.normal(0, 0.01, 3)])
                loops.append((i, j, compose(invert(gt[i]), gt[j], noise)))
    return loops


def rmse(est: np.ndarray, gt: np.ndarray) -> float:
    return float(np.sqrt(np.mean(pose_error(est, gt)[0] ** 2)))


@pytest.fixture(scope="module")
def scene():
    gt = square(N_KF)
    meas, track = odometry(gt, seed=1, sigma_t=0.01, sigma_r=0.01, bias=0.005)
    return gt, meas, track, true_loops(gt, seed=2)


def build(scene, kernel: str, false_loop: bool = False, scale: float = 1.0) -> PoseGraph:
    gt, meas, track, loops = scene
    graph = graph_with(robust_kernel=kernel, kernel_scale=scale, all_frames=False)
    for i in range(N_KF):
        graph.add_keyframe("a", i, track[i])
    for i, m in enumerate(meas):
        graph.add_sequential("a", i, i + 1, m)
    for i, j, T in loops:
        graph.add_loop("a", i, "a", j, T, loop_id=f"{i}-{j}")
    if false_loop:  # opposite sides of the square claimed to be 10 cm apart
        graph.add_loop("a", 5, "a", 25, se3_exp(np.r_[0.1, 0, 0, 0, 0.1, 0]), loop_id="false")
    return graph


def keyframe_poses(result, agent: str = "a", n: int = N_KF) -> np.ndarray:
    return np.stack([result.poses[(agent, i)] for i in range(n)])


def test_loops_remove_most_of_the_drift(scene):
    gt, _, track, loops = scene
    assert len(loops) >= 4
    result = build(scene, "cauchy").optimize()
    before, after = rmse(track, gt), rmse(keyframe_poses(result), gt)
    assert before > 0.25  # the test scene really drifts
    assert after < before / 3
    assert result.error_after < result.error_before
    assert result.outlier_loops == [] and len(result.inlier_loops) == len(loops)
    # The anchor (first keyframe) does not move.
    np.testing.assert_allclose(result.poses[("a", 0)], track[0], atol=1e-6)


@pytest.mark.parametrize("kernel", ["cauchy", "huber", "gnc"])
def test_false_loop_is_ignored_and_flagged(scene, kernel):
    gt = scene[0]
    clean = keyframe_poses(build(scene, kernel).optimize())
    result = build(scene, kernel, false_loop=True).optimize()
    dirty = keyframe_poses(result)
    assert np.abs(dirty[:, :3, 3] - clean[:, :3, 3]).max() < 0.06
    assert rmse(dirty, gt) < 1.2 * rmse(clean, gt) + 0.01
    assert result.outlier_loops == ["false"]
    assert result.loop_chi2["false"] > 100 * CHI2_6DOF_95


@pytest.mark.parametrize("kernel", ["cauchy", "gnc"])
def test_a_true_loop_measured_30cm_off_changes_the_result_by_under_10_percent(scene, kernel):
    """A loop between the right keyframes whose measurement is 30 cm off (a registration
    that slid), with the sigmas of the good loops: rejected or down-weighted, flagged."""
    gt, meas, track, loops = scene
    i, j, T = loops[len(loops) // 2]
    clean = rmse(keyframe_poses(build(scene, kernel).optimize()), gt)
    graph = build(scene, kernel)
    bad = T @ se3_exp(np.r_[0.3, 0.0, 0.0, 0.0, 0.0, 0.0])
    graph.add_loop("a", i, "a", j, bad, sigma_t=0.02, sigma_r=0.01, loop_id="bad")
    result = graph.optimize()
    assert rmse(keyframe_poses(result), gt) < 1.1 * clean
    assert "bad" in result.outlier_loops


def test_reset_estimate_starts_again_from_the_initial_poses(scene):
    gt, _, track, _ = scene
    graph = build(scene, "none")
    first = graph.optimize()
    assert rmse(np.stack([graph.estimate("a", i) for i in range(N_KF)]), gt) < rmse(track, gt)
    graph.reset_estimate()
    np.testing.assert_allclose(np.stack([graph.estimate("a", i) for i in range(N_KF)]), track)
    again = graph.optimize()
    assert again.error_before == pytest.approx(first.error_before)
    np.testing.assert_allclose(keyframe_poses(again), keyframe_poses(first), atol=1e-9)


def test_false_loop_bends_the_map_without_a_robust_kernel(scene):
    gt = scene[0]
    clean = keyframe_poses(build(scene, "none").optimize())
    dirty = keyframe_poses(build(scene, "none", false_loop=True).optimize())
    assert np.abs(dirty[:, :3, 3] - clean[:, :3, 3]).max() > 1.0
    assert rmse(dirty, gt) > 5 * rmse(clean, gt)


def agent_trajectory(T_world_kf: np.ndarray, frames_per_kf: int = 1) -> AgentTrajectory:
    """Keyframes only (every frame a keyframe) unless frames_per_kf > 1."""
    k = len(T_world_kf)
    ids = np.arange(k)
    return AgentTrajectory(
        kf_ids=ids,
        kf_frame_indices=ids * frames_per_kf,
        T_world_kf=T_world_kf,
        frame_indices=np.zeros(0, np.int64),
        frame_kf_ids=np.zeros(0, np.int64),
        T_kf_frame=np.zeros((0, 4, 4)),
    )


def test_two_agents_joined_by_a_loop_share_one_frame(scene):
    gt_a, _, track_a, loops_a = scene
    # Agent b walks the same square starting at a's keyframe 20, in its own world (first
    # camera = identity), and knows nothing of a except through inter-agent loops.
    gt_b = np.roll(gt_a, -20, axis=0)
    _, track_b_own = odometry(
        invert(gt_b[0]) @ gt_b, seed=3, sigma_t=0.01, sigma_r=0.01, bias=-0.004
    )
    rng = np.random.default_rng(4)
    inter = []
    for j in (0, 10, 25, 35):  # b's keyframe j is at a's keyframe (j + 20) % 40
        i = (j + 20) % N_KF
        noise = se3_exp(np.r_[rng.normal(0, 0.02, 3), rng.normal(0, 0.01, 3)])
        inter.append((i, j, compose(invert(gt_a[i]), gt_b[j], noise)))
    # The server aligns b with the first inter-agent loop before optimising.
    i0, j0, T0 = inter[0]
    T_a_worldb = compose(track_a[i0], T0, invert(track_b_own[j0]))

    graph = graph_with(robust_kernel="cauchy", all_frames=False)
    graph.add_trajectory("a", agent_trajectory(track_a))
    graph.add_trajectory("b", agent_trajectory(track_b_own), T_group_world=T_a_worldb)
    for i, j, T in loops_a:
        graph.add_loop("a", i, "a", j, T)
    for i, j, T in inter:
        graph.add_loop("a", i, "b", j, T)
    result = graph.optimize()

    est_b_before = compose(T_a_worldb, track_b_own)
    est_b = keyframe_poses(result, "b")
    assert rmse(est_b, gt_b) < rmse(est_b_before, gt_b) / 2
    assert rmse(est_b, gt_b) < 0.15
    assert rmse(keyframe_poses(result, "a"), gt_a) < 0.15
    assert result.outlier_loops == []
    # One component: only a's first keyframe is held; b's first keyframe moves.
    np.testing.assert_allclose(result.poses[("a", 0)], track_a[0], atol=1e-6)
    assert pose_error(result.poses[("b", 0)], est_b_before[0])[0] > 1e-3


def test_disconnected_agents_are_each_anchored(scene):
    gt, meas, track, loops = scene
    graph = build(scene, "cauchy")
    # Agent c: the same square in its own world, no loop to a.
    track_c = invert(track[0]) @ track
    for i in range(N_KF):
        graph.add_keyframe("c", i, track_c[i])
    for i, m in enumerate(meas):
        graph.add_sequential("c", i, i + 1, m)
    for i, j, T in loops:
        graph.add_loop("c", i, "c", j, T)
    result = graph.optimize()
    np.testing.assert_allclose(result.poses[("a", 0)], track[0], atol=1e-6)
    np.testing.assert_allclose(result.poses[("c", 0)], np.eye(4), atol=1e-6)
    # Both corrected alike, each in its own frame.
    est_a, est_c = keyframe_poses(result, "a"), keyframe_poses(result, "c")
    np.testing.assert_allclose(invert(est_a[0]) @ est_a, est_c, atol=1e-4)
    assert rmse(est_a, gt) < rmse(track, gt) / 3


def test_all_frames_and_keyframes_only_agree():
    per_kf, n_kf = 5, N_KF
    gt = square(n_kf * per_kf)
    _, track = odometry(gt, seed=5, sigma_t=0.004, sigma_r=0.004, bias=0.001)
    kf_frames = np.arange(n_kf) * per_kf
    frames = np.arange(len(gt))
    frame_kf = frames // per_kf
    traj = AgentTrajectory(
        kf_ids=np.arange(n_kf),
        kf_frame_indices=kf_frames,
        T_world_kf=track[kf_frames],
        frame_indices=frames,
        frame_kf_ids=frame_kf,
        T_kf_frame=compose(invert(track[kf_frames[frame_kf]]), track[frames]),
    )
    loops = true_loops(gt[kf_frames], seed=6)
    corrected = {}
    for all_frames in (False, True):
        graph = graph_with(seq_sigma_t=0.004, seq_sigma_r=0.004, all_frames=all_frames)
        graph.add_trajectory("a", traj)
        for i, j, T in loops:
            graph.add_loop("a", i, "a", j, T)
        result = graph.optimize()
        assert len(result.frame_poses) == (len(frames) - n_kf if all_frames else 0)
        corrected[all_frames] = graph.corrected_frames(result, "a")
    assert rmse(corrected[False], gt) < rmse(track, gt) / 3
    assert rmse(corrected[True], gt) < rmse(track, gt) / 3
    gap = pose_error(corrected[False], corrected[True])[0]
    assert gap.max() < 0.05


def test_correct_frames_composes_with_the_new_keyframe_pose():
    kf_new = {0: se3_exp(np.r_[1.0, 0, 0, 0, 0, 0.3]), 3: se3_exp(np.r_[0, 2.0, 0, 0.1, 0, 0])}
    T_kf_frame = se3_exp(np.array([[0.1, 0, 0, 0, 0, 0], [0, 0, 0.2, 0, 0.2, 0]]))
    out = correct_frames(kf_new, np.array([0, 3]), T_kf_frame)
    np.testing.assert_allclose(out[0], kf_new[0] @ T_kf_frame[0])
    np.testing.assert_allclose(out[1], kf_new[3] @ T_kf_frame[1])
    with pytest.raises(ValueError, match=r"keyframes \[7\]"):
        correct_frames(kf_new, np.array([0, 7]), T_kf_frame)


def test_g2o_round_trip(scene, tmp_path):
    graph = build(scene, "cauchy", false_loop=True)
    result = graph.optimize()
    path = tmp_path / "pose_graph.g2o"
    graph.export_g2o(path)
    read_graph, values = gtsam.readG2o(str(path), True)
    assert values.size() == graph.num_nodes == N_KF
    assert read_graph.size() == graph.num_edges
    for i in range(N_KF):
        np.testing.assert_allclose(values.atPose3(i).matrix(), result.poses[("a", i)], atol=1e-6)
    # The first edge is a sequential one: its information comes back, rotation first in gtsam.
    seq_info = read_graph.at(0).noiseModel().information()
    np.testing.assert_allclose(np.diag(seq_info), [1e4] * 6, rtol=1e-6)
    np.testing.assert_allclose(read_graph.at(0).measured().matrix(), scene[1][0], atol=1e-9)
    assert "FIX 0" in path.read_text()


def test_loop_information_matrix_matches_sigmas(scene):
    a = build(scene, "cauchy")
    b = graph_with(robust_kernel="cauchy", all_frames=False)
    _, meas, track, loops = scene
    for i in range(N_KF):
        b.add_keyframe("a", i, track[i])
    for i, m in enumerate(meas):
        b.add_sequential("a", i, i + 1, m)
    info = np.diag([1 / 0.05**2] * 6)
    info[0, 3] = info[3, 0] = 10.0  # a correlated term exercises the full Gaussian model
    for i, j, T in loops:
        b.add_loop("a", i, "a", j, T, information=info)
    pa, pb = keyframe_poses(a.optimize()), keyframe_poses(b.optimize())
    assert np.abs(pa[:, :3, 3] - pb[:, :3, 3]).max() < 0.01


def test_loop_sigmas_grow_with_residual_and_shrinking_overlap():
    assert loop_sigmas(0.05, 0.02, residual_m=0.005, overlap=1.0) == (0.05, 0.02)
    st, sr = loop_sigmas(0.05, 0.02, residual_m=0.03, overlap=0.25)
    assert st == pytest.approx(0.05 * 3 * 2) and sr == pytest.approx(0.02 * 3 * 2)
    with pytest.raises(ValueError, match="overlap"):
        loop_sigmas(0.05, 0.02, residual_m=0.01, overlap=0.0)


def test_bad_input_is_refused(scene):
    graph = build(scene, "cauchy")
    with pytest.raises(ValueError, match="no kf node 99 of agent 'a'"):
        graph.add_loop("a", 0, "a", 99, np.eye(4))
    with pytest.raises(ValueError, match="already used"):
        graph.add_loop("a", 0, "a", 20, np.eye(4), loop_id="0-38")
    with pytest.raises(ValueError, match="rigid"):
        graph.add_loop("a", 0, "a", 20, 2 * np.eye(4))
    with pytest.raises(ValueError, match="already in the pose graph"):
        graph.add_keyframe("a", 3, np.eye(4))
    with pytest.raises(ValueError, match="positive definite"):
        graph.add_loop("a", 0, "a", 20, np.eye(4), information=-np.eye(6))
    with pytest.raises(ValueError, match="robust_kernel"):
        graph_with(robust_kernel="tukey")
    with pytest.raises(ValueError, match="no nodes"):
        graph_with().optimize()


def test_from_config_takes_the_section_values():
    cfg = PoseGraphConfig(
        robust_kernel="huber",
        kernel_scale=2.0,
        seq_sigma_t=0.02,
        loop_sigma_r=0.1,
        max_iters=7,
        all_frames=False,
    )
    graph = PoseGraph.from_config(cfg)
    assert (graph.robust_kernel, graph.kernel_scale, graph.seq_sigma_t) == ("huber", 2.0, 0.02)
    assert (graph.loop_sigma_r, graph.max_iters, graph.all_frames) == (0.1, 7, False)


def test_rerun_after_a_new_loop_starts_from_the_corrected_map(scene):
    gt, meas, track, loops = scene
    one_shot = keyframe_poses(build(scene, "cauchy").optimize())
    graph = graph_with(robust_kernel="cauchy", all_frames=False)
    for i in range(N_KF):
        graph.add_keyframe("a", i, track[i])
    for i, m in enumerate(meas):
        graph.add_sequential("a", i, i + 1, m)
    first = graph.optimize()  # no loops yet: odometry is already optimal
    assert first.error_after < 1e-9 and first.inlier_loops == []
    ids = [graph.add_loop("a", i, "a", j, T) for i, j, T in loops]
    assert ids == list(range(len(loops)))
    second = graph.optimize()
    assert second.error_before > second.error_after
    np.testing.assert_allclose(keyframe_poses(second), one_shot, atol=1e-4)
    np.testing.assert_allclose(graph.estimate("a", 7), second.poses[("a", 7)])
    third = graph.optimize()  # nothing new: starts where the second run ended
    assert third.error_before == pytest.approx(second.error_after, rel=1e-9)


def test_sigmas_are_translation_first():
    # The tracking edge is sure of translation, the loop of rotation: each should win its part.
    graph = graph_with(robust_kernel="none", all_frames=False)
    graph.add_keyframe("a", 0, np.eye(4))
    graph.add_keyframe("a", 1, se3_exp(np.r_[1.0, 0, 0, 0, 0, 0]))
    graph.add_sequential("a", 0, 1, se3_exp(np.r_[1.0, 0, 0, 0, 0, 0]), sigma_t=1e-3, sigma_r=1.0)
    loop = compose(se3_exp(np.r_[1.5, 0, 0, 0, 0, 0]), se3_exp(np.r_[0, 0, 0, 0, 0, 0.2]))
    graph.add_loop("a", 0, "a", 1, loop, sigma_t=1.0, sigma_r=1e-3)
    T = graph.optimize().poses[("a", 1)]
    np.testing.assert_allclose(T[:3, 3], [1.0, 0, 0], atol=1e-3)
    np.testing.assert_allclose(T[:3, :3], loop[:3, :3], atol=1e-3)


def test_g2o_information_order(tmp_path):
    graph = graph_with(all_frames=False)
    graph.add_keyframe("a", 0, np.eye(4))
    graph.add_keyframe("a", 1, se3_exp(np.r_[1.0, 0, 0, 0, 0, 0.1]))
    graph.add_sequential("a", 0, 1, se3_exp(np.r_[1.0, 0, 0, 0, 0, 0.1]), 0.02, 0.005)
    path = tmp_path / "g.g2o"
    graph.export_g2o(path)
    edge = next(line for line in path.read_text().splitlines() if line.startswith("EDGE"))
    info = np.array(edge.split()[10:], dtype=float)
    assert info[0] == pytest.approx(0.02**-2) and info[-1] == pytest.approx(0.005**-2)
    read_graph, _ = gtsam.readG2o(str(path), True)
    diag = np.diag(read_graph.at(0).noiseModel().information())  # gtsam: rotation first
    np.testing.assert_allclose(diag, [0.005**-2] * 3 + [0.02**-2] * 3, rtol=1e-9)

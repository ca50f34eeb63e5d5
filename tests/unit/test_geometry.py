"""SO(3)/SE(3) geometry: numpy against scipy and gtsam, torch against numpy, gradients."""

from __future__ import annotations

import subprocess
import sys

import gtsam
import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation, Slerp

from cpslam.common import geometry as g
from cpslam.common import geometry_torch as gt

N_RANDOM = 300


def random_rotvecs(rng: np.random.Generator, n: int, max_angle: float = np.pi - 1e-3) -> np.ndarray:
    axis = rng.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    return axis * rng.uniform(0.0, max_angle, size=(n, 1))


def special_rotvecs(rng: np.random.Generator) -> np.ndarray:
    """Tiny angles, zero, angles just below pi and exactly pi, about random axes."""
    angles = [0.0, 1e-12, 1e-9, 1e-6, 1e-3, 0.0499, 0.0501, np.pi - 1e-3, np.pi - 1e-6]
    angles += [np.pi - 1e-9, np.pi]
    axis = rng.normal(size=(len(angles), 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    return axis * np.asarray(angles)[:, None]


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(1234)


@pytest.fixture
def twists(rng: np.random.Generator) -> np.ndarray:
    phi = np.concatenate([random_rotvecs(rng, N_RANDOM), special_rotvecs(rng)])
    rho = rng.normal(scale=2.0, size=phi.shape)
    return np.concatenate([rho, phi], axis=1)


# ------------------------------------------------------------------------------------ SO(3)


def test_so3_exp_log_match_scipy(rng: np.random.Generator) -> None:
    phi = np.concatenate([random_rotvecs(rng, N_RANDOM), special_rotvecs(rng)[:-1]])
    R = g.so3_exp(phi)
    np.testing.assert_allclose(R, Rotation.from_rotvec(phi).as_matrix(), atol=1e-12)
    np.testing.assert_allclose(g.so3_log(R), phi, atol=1e-9)


@pytest.mark.parametrize("module", [g, gt])
def test_so3_coefficients_against_high_precision(module) -> None:
    """sin(t)/t, (1 - cos t)/t^2, (t - sin t)/t^3 on both sides of the series switch."""
    mpmath = pytest.importorskip("mpmath")
    mpmath.mp.dps = 40
    angles = np.array([0.0, 1e-9, 1e-4, 0.01, 0.0499, 0.0501, 0.1, 0.199, 0.201, 1.0, 3.1])
    phi = np.stack([np.zeros_like(angles), np.zeros_like(angles), angles], axis=1)
    if module is gt:
        coeffs = [c.numpy() for c in gt._so3_coeffs(torch.from_numpy(phi))]
    else:
        coeffs = g._so3_coeffs(phi)
    for theta, a, b, c in zip(angles, *coeffs, strict=True):
        t = mpmath.mpf(float(theta))
        if t == 0:
            ref = (1.0, 0.5, 1.0 / 6.0)
        else:
            ref = (mpmath.sin(t) / t, (1 - mpmath.cos(t)) / t**2, (t - mpmath.sin(t)) / t**3)
        np.testing.assert_allclose([a, b, c], [float(r) for r in ref], rtol=1e-12, atol=0)


def test_so3_tiny_angles_keep_relative_precision() -> None:
    for angle in (1e-12, 1e-9, 1e-6):
        phi = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8]) * angle
        R = g.so3_exp(phi)
        np.testing.assert_allclose(R - np.eye(3), g.skew(phi), rtol=0, atol=angle * 1e-6)
        np.testing.assert_allclose(g.so3_log(R), phi, rtol=1e-6, atol=0)
    np.testing.assert_array_equal(g.so3_exp(np.zeros(3)), np.eye(3))
    np.testing.assert_array_equal(g.so3_log(np.eye(3)), np.zeros(3))


def test_so3_log_near_pi_recovers_rotation(rng: np.random.Generator) -> None:
    for gap in (1e-3, 1e-6, 1e-9, 0.0):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        R = Rotation.from_rotvec(axis * (np.pi - gap)).as_matrix()
        phi = g.so3_log(R)
        assert np.linalg.norm(phi) == pytest.approx(np.pi - gap, abs=1e-9)
        # At exactly pi the axis sign is ambiguous; the rotation is not.
        assert abs(abs(phi @ axis) - (np.pi - gap)) < 1e-8
        np.testing.assert_allclose(g.so3_exp(phi), R, atol=1e-12)


def test_quaternions_match_scipy(rng: np.random.Generator) -> None:
    q = rng.normal(size=(N_RANDOM, 4)) * rng.uniform(0.1, 10.0, size=(N_RANDOM, 1))
    R = g.quat_to_matrix(q)  # non-unit input is normalised
    np.testing.assert_allclose(R, Rotation.from_quat(q).as_matrix(), atol=1e-12)
    q_back = g.matrix_to_quat(R)
    assert np.all(q_back[:, 3] >= 0.0)
    np.testing.assert_allclose(np.linalg.norm(q_back, axis=1), 1.0, atol=1e-14)
    np.testing.assert_allclose(q_back, Rotation.from_matrix(R).as_quat(canonical=True), atol=1e-12)
    # near-pi rotations exercise every Shepperd branch
    R_pi = g.so3_exp(special_rotvecs(rng))
    np.testing.assert_allclose(g.quat_to_matrix(g.matrix_to_quat(R_pi)), R_pi, atol=1e-12)


def test_quat_to_matrix_rejects_zero_norm() -> None:
    with pytest.raises(ValueError, match="non-zero norm"):
        g.quat_to_matrix(np.zeros(4))
    with pytest.raises(ValueError, match="non-zero norm"):
        g.quat_to_matrix(np.array([[0, 0, 0, 1.0], [0, 0, 0, 0]]))
    with pytest.raises(ValueError, match=r"\[\.\.\., 4\]"):
        g.quat_to_matrix(np.zeros(3))


# ------------------------------------------------------------------------------------ SE(3)


def test_se3_exp_log_match_gtsam(twists: np.ndarray) -> None:
    T = g.se3_exp(twists)
    below_pi = np.linalg.norm(twists[:, 3:], axis=1) < np.pi  # where the log is unique
    np.testing.assert_allclose(g.se3_log(T[below_pi]), twists[below_pi], rtol=0, atol=1e-12)
    for xi, T_i, unique in zip(twists, T, below_pi, strict=True):
        # gtsam orders twists [omega, v]: rotation first.
        xi_gtsam = np.concatenate([xi[3:], xi[:3]])
        np.testing.assert_allclose(T_i, gtsam.Pose3.Expmap(xi_gtsam).matrix(), atol=1e-12)
        if unique:
            # gtsam's own Logmap loses ~1e-8 close to pi; ours holds 1e-12 (checked above).
            log_gtsam = gtsam.Pose3.Logmap(gtsam.Pose3(T_i))
            np.testing.assert_allclose(
                g.se3_log(T_i), np.r_[log_gtsam[3:], log_gtsam[:3]], atol=1e-7
            )


def test_se3_exp_is_not_plain_translation() -> None:
    xi = np.array([1.0, 0.0, 0.0, 0.0, 0.0, np.pi / 2])
    T = g.se3_exp(xi)
    # rotating while moving along x bends the path: t = V rho, not rho
    np.testing.assert_allclose(T[:3, 3], [2 / np.pi, 2 / np.pi, 0.0], atol=1e-12)


def test_se3_log_exp_round_trip_any_pose(twists: np.ndarray) -> None:
    T = g.se3_exp(twists)
    np.testing.assert_allclose(g.se3_exp(g.se3_log(T)), T, atol=1e-9)
    tiny = np.array([1e-10, -2e-10, 3e-10, 1e-12, -1e-12, 2e-12])
    np.testing.assert_allclose(g.se3_log(g.se3_exp(tiny)), tiny, rtol=1e-6, atol=1e-22)


def test_batched_shapes(rng: np.random.Generator) -> None:
    xi = rng.normal(scale=0.5, size=(2, 5, 6))
    T = g.se3_exp(xi)
    assert T.shape == (2, 5, 4, 4)
    np.testing.assert_allclose(T[1, 3], g.se3_exp(xi[1, 3]))
    assert g.se3_log(T).shape == (2, 5, 6)
    assert g.so3_log(T[..., :3, :3]).shape == (2, 5, 3)
    t, q = g.pose_to_tq(T)
    assert t.shape == (2, 5, 3) and q.shape == (2, 5, 4)
    np.testing.assert_allclose(g.pose_from_tq(t, q), T, atol=1e-12)
    with pytest.raises(ValueError, match=r"\[\.\.\., 4, 4\]"):
        g.invert(np.eye(3))


def test_invert_compose_transform(rng: np.random.Generator) -> None:
    T_a_b, T_b_c = g.se3_exp(rng.normal(size=(2, 10, 6)))
    np.testing.assert_allclose(
        g.compose(T_a_b, g.invert(T_a_b)), np.broadcast_to(np.eye(4), (10, 4, 4)), atol=1e-12
    )
    np.testing.assert_allclose(g.invert(T_a_b), np.linalg.inv(T_a_b), atol=1e-12)
    T_a_c = g.compose(T_a_b, T_b_c)
    xyz_c = rng.normal(size=(10, 7, 3))
    xyz_a = g.transform_points(T_a_c, xyz_c)
    np.testing.assert_allclose(
        xyz_a, g.transform_points(T_a_b, g.transform_points(T_b_c, xyz_c)), atol=1e-12
    )
    homog = np.concatenate([xyz_c, np.ones((10, 7, 1))], axis=-1)
    np.testing.assert_allclose(xyz_a, (homog @ np.swapaxes(T_a_c, -1, -2))[..., :3], atol=1e-12)
    assert g.compose(T_a_b[0]).shape == (4, 4)
    with pytest.raises(ValueError):
        g.compose()


def test_interpolate_pose_against_scipy_slerp(rng: np.random.Generator) -> None:
    T0, T1 = g.se3_exp(rng.normal(size=(2, 6)))
    alphas = np.linspace(0.0, 1.0, 7)
    T = g.interpolate_pose(T0, T1, alphas)
    assert T.shape == (7, 4, 4)
    np.testing.assert_allclose(T[0], T0, atol=1e-12)
    np.testing.assert_allclose(T[-1], T1, atol=1e-12)
    slerp = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([T0[:3, :3], T1[:3, :3]])))
    np.testing.assert_allclose(T[:, :3, :3], slerp(alphas).as_matrix(), atol=1e-12)
    np.testing.assert_allclose(T[3, :3, 3], 0.5 * (T0[:3, 3] + T1[:3, 3]), atol=1e-12)
    assert g.interpolate_pose(T0, T1, 0.25).shape == (4, 4)
    with pytest.raises(ValueError, match="alpha"):
        g.interpolate_pose(T0, T1, 1.5)


def test_is_rigid_and_project_to_rigid(rng: np.random.Generator) -> None:
    T = g.se3_exp(rng.normal(size=(5, 6)))
    assert g.is_rigid(T) and g.is_rigid(T[0])
    scaled = T.copy()
    scaled[2, :3, :3] *= 1.01
    assert not g.is_rigid(scaled)
    mirrored = T[0] @ np.diag([1.0, 1.0, -1.0, 1.0])
    assert not g.is_rigid(mirrored)
    bad_row = T[0].copy()
    bad_row[3, 0] = 0.1
    assert not g.is_rigid(bad_row)
    nan = T[0].copy()
    nan[0, 3] = np.nan
    assert not g.is_rigid(nan)
    assert not g.is_rigid(np.eye(3))

    drifted = T + rng.normal(scale=1e-3, size=T.shape) * np.r_[1, 1, 1, 0][:, None]
    fixed = g.project_to_rigid(drifted)
    assert not g.is_rigid(drifted, tol=1e-6) and g.is_rigid(fixed, tol=1e-12)
    np.testing.assert_allclose(fixed, T, atol=1e-2)
    np.testing.assert_allclose(fixed[:, :3, 3], drifted[:, :3, 3])
    assert np.linalg.det(g.project_to_rigid(mirrored)[:3, :3]) == pytest.approx(1.0)


def test_pose_error() -> None:
    T_a = g.se3_exp(np.array([0.1, 0.2, 0.3, 0.4, -0.1, 0.2]))
    delta = g.pose_from_tq(np.array([0.0, 0.3, 0.4]), Rotation.from_rotvec([0, 0, 0.25]).as_quat())
    T_b = T_a.copy()
    T_b[:3, :3] = T_a[:3, :3] @ delta[:3, :3]
    T_b[:3, 3] += delta[:3, 3]
    trans, rot = g.pose_error(T_a, T_b)
    assert trans == pytest.approx(0.5) and rot == pytest.approx(0.25)
    trans, rot = g.pose_error(np.stack([T_a, T_b]), T_a)
    np.testing.assert_allclose(trans, [0.0, 0.5], atol=1e-12)
    np.testing.assert_allclose(rot, [0.0, 0.25], atol=1e-7)


def test_numpy_side_imports_without_torch() -> None:
    code = (
        "import sys; import cpslam.common.geometry, cpslam.common.camera, "
        "cpslam.common.trajectory; assert 'torch' not in sys.modules, 'torch was imported'"
    )
    subprocess.run([sys.executable, "-c", code], check=True)


# ------------------------------------------------------------------------------------ torch


def test_torch_matches_numpy(twists: np.ndarray, rng: np.random.Generator) -> None:
    xi = torch.from_numpy(twists)
    np.testing.assert_allclose(gt.torch_se3_exp(xi).numpy(), g.se3_exp(twists), atol=1e-12)
    np.testing.assert_allclose(
        gt.torch_so3_exp(xi[:, 3:]).numpy(), g.so3_exp(twists[:, 3:]), atol=1e-12
    )
    q = rng.normal(size=(50, 4))
    R = gt.torch_quat_to_matrix(torch.from_numpy(q))
    np.testing.assert_allclose(R.numpy(), g.quat_to_matrix(q), atol=1e-12)
    R_all = torch.from_numpy(g.so3_exp(twists[:, 3:]))
    np.testing.assert_allclose(
        gt.torch_matrix_to_quat(R_all).numpy(), g.matrix_to_quat(R_all.numpy()), atol=1e-12
    )
    T = g.se3_exp(twists)
    xyz = rng.normal(size=(len(T), 4, 3))
    np.testing.assert_allclose(
        gt.torch_invert(torch.from_numpy(T)).numpy(), g.invert(T), atol=1e-12
    )
    np.testing.assert_allclose(
        gt.torch_transform_points(torch.from_numpy(T), torch.from_numpy(xyz)).numpy(),
        g.transform_points(T, xyz),
        atol=1e-12,
    )
    t = rng.normal(size=(50, 3))
    np.testing.assert_allclose(
        gt.torch_pose_from_tq(torch.from_numpy(t), torch.from_numpy(q)).numpy(),
        g.pose_from_tq(t, q),
        atol=1e-12,
    )
    Ts = torch.from_numpy(T[:3])
    np.testing.assert_allclose(
        gt.torch_compose(Ts[0], Ts[1], Ts[2]).numpy(), g.compose(T[0], T[1], T[2]), atol=1e-12
    )


def test_torch_keeps_dtype_and_float32_is_accurate(twists: np.ndarray) -> None:
    xi32 = torch.from_numpy(twists).float()
    T32 = gt.torch_se3_exp(xi32)
    assert T32.dtype == torch.float32 and T32.device == xi32.device
    np.testing.assert_allclose(T32.numpy(), g.se3_exp(twists), atol=2e-5)
    q32 = gt.torch_matrix_to_quat(T32[:, :3, :3])
    assert q32.dtype == torch.float32
    assert gt.torch_invert(T32).dtype == torch.float32


@pytest.mark.parametrize("at", ["zero", "random", "small", "threshold"])
def test_torch_se3_exp_gradcheck(at: str) -> None:
    gen = torch.Generator().manual_seed(7)
    xi = {
        "zero": torch.zeros(6, dtype=torch.float64),
        "random": torch.randn(3, 6, generator=gen, dtype=torch.float64),
        "small": 1e-7 * torch.randn(6, generator=gen, dtype=torch.float64),
        "threshold": torch.tensor([0.1, 0.2, 0.3, 0.05, 0.0, 0.0], dtype=torch.float64),
    }[at].requires_grad_(True)
    assert torch.autograd.gradcheck(gt.torch_se3_exp, (xi,), eps=1e-6, atol=1e-6)
    assert torch.autograd.gradcheck(
        lambda v: gt.torch_so3_exp(v[..., 3:]), (xi,), eps=1e-6, atol=1e-6
    )


def test_torch_gradients_finite_and_exact_at_zero_rotation() -> None:
    phi = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    jac = torch.autograd.functional.jacobian(gt.torch_so3_exp, phi)  # [3, 3, 3]
    assert torch.isfinite(jac).all()
    for i in range(3):  # dR/dphi_i at identity is the i-th generator
        e = torch.zeros(3, dtype=torch.float64)
        e[i] = 1.0
        torch.testing.assert_close(jac[..., i], gt.torch_skew(e))
    for dtype in (torch.float32, torch.float64):
        xi = torch.zeros(6, dtype=dtype, requires_grad=True)
        gt.torch_se3_exp(xi).sum().backward()
        assert torch.isfinite(xi.grad).all()
        q = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=dtype, requires_grad=True)
        gt.torch_quat_to_matrix(q).sum().backward()
        assert torch.isfinite(q.grad).all()


def test_torch_quat_to_matrix_gradcheck() -> None:
    q = torch.tensor([[0.1, -0.2, 0.3, 0.9], [0.0, 0.0, 0.0, 2.0]], dtype=torch.float64)
    assert torch.autograd.gradcheck(gt.torch_quat_to_matrix, (q.requires_grad_(True),))


def test_torch_shape_errors() -> None:
    with pytest.raises(ValueError, match="xi"):
        gt.torch_se3_exp(torch.zeros(3))
    with pytest.raises(ValueError, match="T"):
        gt.torch_invert(torch.eye(3))


# ------------------------------------------------------------------------------ torch logs


def test_torch_logs_match_numpy_and_scipy(twists: np.ndarray) -> None:
    T = g.se3_exp(twists)
    below_pi = np.linalg.norm(twists[:, 3:], axis=1) < np.pi  # where the log is unique
    R = torch.from_numpy(T[:, :3, :3])
    phi = gt.torch_so3_log(R).numpy()
    np.testing.assert_allclose(phi, g.so3_log(T[:, :3, :3]), rtol=0, atol=1e-12)
    np.testing.assert_allclose(phi[below_pi], twists[below_pi, 3:], rtol=0, atol=1e-9)
    scipy_phi = Rotation.from_matrix(T[below_pi, :3, :3]).as_rotvec()
    np.testing.assert_allclose(phi[below_pi], scipy_phi, rtol=0, atol=1e-9)
    xi = gt.torch_se3_log(torch.from_numpy(T)).numpy()
    np.testing.assert_allclose(xi, g.se3_log(T), rtol=0, atol=1e-12)
    np.testing.assert_allclose(xi[below_pi], twists[below_pi], rtol=0, atol=1e-9)
    # at exactly pi the axis sign is ambiguous; the pose is not
    np.testing.assert_allclose(g.se3_exp(xi), T, atol=1e-9)
    # batched over leading dimensions, like the numpy versions
    T_b = torch.from_numpy(T[:300].reshape(3, 100, 4, 4))
    assert gt.torch_se3_log(T_b).shape == (3, 100, 6)
    assert gt.torch_so3_log(T_b[..., :3, :3]).shape == (3, 100, 3)


def test_torch_logs_tiny_angles_and_float32(twists: np.ndarray) -> None:
    for angle in (0.0, 1e-12, 1e-9, 1e-6, 1e-3):
        phi = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8]) * angle
        out = gt.torch_so3_log(torch.from_numpy(g.so3_exp(phi))).numpy()
        np.testing.assert_allclose(out, phi, rtol=1e-6, atol=1e-300)
    tiny = np.array([1e-10, -2e-10, 3e-10, 1e-12, -1e-12, 2e-12])
    out = gt.torch_se3_log(torch.from_numpy(g.se3_exp(tiny))).numpy()
    np.testing.assert_allclose(out, tiny, rtol=1e-6, atol=1e-22)
    T32 = torch.from_numpy(g.se3_exp(twists)).float()
    xi32 = gt.torch_se3_log(T32)
    assert xi32.dtype == torch.float32
    # float32 poses hold ~1e-7 relative; the log near pi amplifies that a little
    np.testing.assert_allclose(xi32.numpy(), g.se3_log(T32.double().numpy()), atol=1e-5)


@pytest.mark.parametrize("angle", [0.0, 1e-7, 0.0499, 0.0501, 1.0, np.pi - 0.05])
def test_torch_logs_gradients_invert_exp(angle: float) -> None:
    """d log(exp(xi)) / d xi is the identity, on both sides of every series switch."""
    axis = torch.tensor([0.3, -0.5, 0.8], dtype=torch.float64)
    phi = axis / torch.linalg.vector_norm(axis) * angle
    xi = torch.cat([torch.tensor([0.2, -0.1, 0.4], dtype=torch.float64), phi])
    eye = torch.eye(6, dtype=torch.float64)
    jac = torch.autograd.functional.jacobian(lambda v: gt.torch_se3_log(gt.torch_se3_exp(v)), xi)
    torch.testing.assert_close(jac, eye, atol=1e-7, rtol=0)
    jac = torch.autograd.functional.jacobian(lambda v: gt.torch_so3_log(gt.torch_so3_exp(v)), phi)
    torch.testing.assert_close(jac, eye[:3, :3], atol=1e-7, rtol=0)
    R = gt.torch_so3_exp(phi).requires_grad_(True)
    assert torch.autograd.gradcheck(gt.torch_so3_log, (R,), eps=1e-7, atol=1e-6)
    T = gt.torch_se3_exp(xi).requires_grad_(True)
    assert torch.autograd.gradcheck(gt.torch_se3_log, (T,), eps=1e-7, atol=1e-6)


def test_torch_log_gradients_finite_at_identity_and_pi() -> None:
    for dtype in (torch.float32, torch.float64):
        for angle in (0.0, np.pi):
            R = gt.torch_so3_exp(torch.tensor([0.0, 0.0, angle], dtype=dtype))
            T = torch.eye(4, dtype=dtype)
            T[:3, :3] = R
            T.requires_grad_(True)
            gt.torch_se3_log(T).sum().backward()
            assert torch.isfinite(T.grad).all(), (dtype, angle)


def test_torch_interpolate_pose_matches_numpy_and_slerp(rng: np.random.Generator) -> None:
    T0, T1 = g.se3_exp(rng.normal(size=(2, 6)))
    alphas = np.linspace(0.0, 1.0, 7)
    T = gt.torch_interpolate_pose(
        torch.from_numpy(T0), torch.from_numpy(T1), torch.from_numpy(alphas)
    ).numpy()
    assert T.shape == (7, 4, 4)
    np.testing.assert_allclose(T, g.interpolate_pose(T0, T1, alphas), atol=1e-12)
    slerp = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([T0[:3, :3], T1[:3, :3]])))
    np.testing.assert_allclose(T[:, :3, :3], slerp(alphas).as_matrix(), atol=1e-12)
    np.testing.assert_allclose(T[0], T0, atol=1e-12)
    np.testing.assert_allclose(T[-1], T1, atol=1e-12)
    # batched poses with one alpha each
    A, B = g.se3_exp(rng.normal(size=(2, 20, 6)))
    a = rng.uniform(size=20)
    out = gt.torch_interpolate_pose(torch.from_numpy(A), torch.from_numpy(B), torch.from_numpy(a))
    np.testing.assert_allclose(out.numpy(), g.interpolate_pose(A, B, a), atol=1e-12)
    one = gt.torch_interpolate_pose(
        torch.from_numpy(T0).float(), torch.from_numpy(T1).float(), 0.25
    )
    assert one.shape == (4, 4) and one.dtype == torch.float32
    np.testing.assert_allclose(one.numpy(), g.interpolate_pose(T0, T1, 0.25), atol=1e-5)
    with pytest.raises(ValueError, match="alpha"):
        gt.torch_interpolate_pose(torch.from_numpy(T0), torch.from_numpy(T1), 1.5)


def test_torch_interpolate_pose_gradcheck() -> None:
    gen = torch.Generator().manual_seed(3)
    xi0, xi1 = torch.randn(2, 6, generator=gen, dtype=torch.float64)
    alpha = torch.tensor([0.0, 0.3, 1.0], dtype=torch.float64)

    def interp(a: torch.Tensor, v0: torch.Tensor, v1: torch.Tensor) -> torch.Tensor:
        return gt.torch_interpolate_pose(gt.torch_se3_exp(v0), gt.torch_se3_exp(v1), a)

    inputs = tuple(x.clone().requires_grad_(True) for x in (alpha, xi0, xi1))
    assert torch.autograd.gradcheck(interp, inputs, eps=1e-6, atol=1e-6)
    # equal poses: the relative rotation is the identity, where the log switches to its series
    same = tuple(x.clone().requires_grad_(True) for x in (alpha, xi0, xi0))
    assert torch.autograd.gradcheck(interp, same, eps=1e-6, atol=1e-6)

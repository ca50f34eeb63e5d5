"""Rigid-body geometry in numpy (float64): SO(3)/SE(3) exp and log, quaternions, poses.

Conventions (shared by the whole project):

- A pose is a 4x4 float64 matrix ``T_a_b`` mapping points from frame b to frame a; a camera
  pose is ``T_world_cam``.
- A twist ``xi`` is ``[rho (3, translation part), phi (3, rotation)]`` -- translation first.
  ``se3_exp`` is the true SE(3) exponential, ``t = V(phi) @ rho`` with V the left Jacobian of
  SO(3), not ``t = rho``. (gtsam's Pose3.Expmap uses the same map with rotation first.)
- Quaternions are ``[x, y, z, w]`` (TUM and scipy order); ``matrix_to_quat`` returns w >= 0.
- Every function is batched over leading dimensions: ``[..., 3]``, ``[..., 4, 4]``.

This module imports numpy only, so the protocol and dataset side can use it without torch.
The differentiable torch versions live in ``cpslam.common.geometry_torch``.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "compose",
    "interpolate_pose",
    "invert",
    "is_rigid",
    "matrix_to_quat",
    "pose_error",
    "pose_from_tq",
    "pose_to_tq",
    "project_to_rigid",
    "quat_to_matrix",
    "se3_exp",
    "se3_log",
    "skew",
    "so3_exp",
    "so3_log",
    "transform_points",
]

# Below this angle (radians) the closed forms lose digits to cancellation, so the truncated
# Taylor series (error below 1e-20 here) is used instead.
_SMALL_ANGLE = 0.05


def so3_exp(phi: np.ndarray) -> np.ndarray:
    """Rotation matrices ``[..., 3, 3]`` from rotation vectors ``phi [..., 3]`` (Rodrigues)."""
    phi = _as_vectors(phi, 3, "phi")
    a, b, _ = _so3_coeffs(phi)
    k = skew(phi)
    return np.eye(3) + a[..., None, None] * k + b[..., None, None] * (k @ k)


def so3_log(R: np.ndarray) -> np.ndarray:
    """Rotation vectors ``[..., 3]`` (angle in [0, pi]) from rotation matrices ``[..., 3, 3]``.

    Goes through the quaternion (Shepperd's method), which stays accurate both at tiny angles
    and near pi, where the textbook ``vee(R - R^T) / (2 sin)`` formula breaks down.
    """
    q = matrix_to_quat(R)
    v, w = q[..., :3], q[..., 3]
    n = np.linalg.norm(v, axis=-1)
    tiny = n < 1e-12
    n_safe = np.where(tiny, 1.0, n)
    # angle = 2 atan2(|v|, w); w >= 0 so the angle is in [0, pi].
    scale = np.where(tiny, 2.0 / np.maximum(w, 1e-300), 2.0 * np.arctan2(n, w) / n_safe)
    return scale[..., None] * v


def se3_exp(xi: np.ndarray) -> np.ndarray:
    """Poses ``[..., 4, 4]`` from twists ``xi [..., 6] = [rho, phi]`` (true SE(3) exp)."""
    xi = _as_vectors(xi, 6, "xi")
    rho, phi = xi[..., :3], xi[..., 3:]
    a, b, c = _so3_coeffs(phi)
    k = skew(phi)
    k2 = k @ k
    eye = np.eye(3)
    R = eye + a[..., None, None] * k + b[..., None, None] * k2
    V = eye + b[..., None, None] * k + c[..., None, None] * k2
    return _assemble(R, (V @ rho[..., None])[..., 0])


def se3_log(T: np.ndarray) -> np.ndarray:
    """Twists ``[..., 6] = [rho, phi]`` from poses ``[..., 4, 4]``; inverse of ``se3_exp``."""
    T = _as_poses(T, "T")
    R, t = T[..., :3, :3], T[..., :3, 3]
    phi = so3_log(R)
    theta2 = np.sum(phi * phi, axis=-1)
    theta = np.sqrt(theta2)
    small = theta < _SMALL_ANGLE
    th = np.where(small, 1.0, theta)
    # V^-1 = I - K/2 + d K^2 with d = (1 - (th/2) cot(th/2)) / th^2; finite up to and at pi.
    d_closed = (1.0 - 0.5 * th * np.sin(th) / (1.0 - np.cos(th))) / (th * th)
    d_series = 1.0 / 12.0 + theta2 * (1.0 / 720.0 + theta2 * (1.0 / 30240.0 + theta2 / 1209600.0))
    d = np.where(small, d_series, d_closed)
    k = skew(phi)
    V_inv = np.eye(3) - 0.5 * k + d[..., None, None] * (k @ k)
    rho = (V_inv @ t[..., None])[..., 0]
    return np.concatenate([rho, phi], axis=-1)


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrices ``[..., 3, 3]`` of vectors ``v [..., 3]`` (skew(a) @ b = a x b)."""
    v = np.asarray(v, dtype=np.float64)
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    o = np.zeros_like(x)
    return np.stack([o, -z, y, z, o, -x, -y, x, o], axis=-1).reshape(*v.shape[:-1], 3, 3)


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices ``[..., 3, 3]`` from quaternions ``[..., 4]`` (xyzw, any norm > 0).

    Raises:
        ValueError: if a quaternion has (near) zero norm or is not finite.
    """
    q = _as_vectors(q, 4, "q")
    norm = np.linalg.norm(q, axis=-1)
    if not np.all(np.isfinite(norm)) or np.any(norm < 1e-12):
        raise ValueError("quat_to_matrix: quaternions must be finite with non-zero norm")
    x, y, z, w = np.moveaxis(q / norm[..., None], -1, 0)
    R = np.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
            2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
            2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y),
        ],
        axis=-1,
    )  # fmt: skip
    return R.reshape(*q.shape[:-1], 3, 3)


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """Unit quaternions ``[..., 4]`` (xyzw, w >= 0) from rotation matrices ``[..., 3, 3]``.

    Shepperd's method: builds the quaternion from whichever of w, x, y, z is largest, so no
    division by a small number happens at any angle.
    """
    R = np.asarray(R, dtype=np.float64)
    if R.shape[-2:] != (3, 3):
        raise ValueError(f"matrix_to_quat: expected R of shape [..., 3, 3], got {R.shape}")
    candidates = _quat_candidates(R)  # [..., 4 choices, 4]
    diag = np.stack([R[..., 0, 0], R[..., 1, 1], R[..., 2, 2], np.trace(R, axis1=-2, axis2=-1)], -1)
    choice = np.argmax(diag, axis=-1)
    q = np.take_along_axis(candidates, choice[..., None, None], axis=-2)[..., 0, :]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., 3:4] < 0.0, -q, q)


def pose_from_tq(t: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Pose ``[..., 4, 4]`` from translation ``t [..., 3]`` and quaternion ``q [..., 4]`` xyzw."""
    t = _as_vectors(t, 3, "t")
    return _assemble(quat_to_matrix(q), t)


def pose_to_tq(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Translation ``[..., 3]`` and quaternion ``[..., 4]`` (xyzw, w >= 0) of poses."""
    T = _as_poses(T, "T")
    return T[..., :3, 3].copy(), matrix_to_quat(T[..., :3, :3])


def invert(T: np.ndarray) -> np.ndarray:
    """Inverse of rigid poses ``[..., 4, 4]`` using R^T (T_b_a from T_a_b)."""
    T = _as_poses(T, "T")
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    return _assemble(Rt, -(Rt @ T[..., :3, 3:4])[..., 0])


def compose(*Ts: np.ndarray) -> np.ndarray:
    """Product ``Ts[0] @ Ts[1] @ ...`` (left to right), e.g. compose(T_a_b, T_b_c) = T_a_c."""
    if not Ts:
        raise ValueError("compose: needs at least one pose")
    out = _as_poses(Ts[0], "Ts[0]")
    for i, T in enumerate(Ts[1:], start=1):
        out = out @ _as_poses(T, f"Ts[{i}]")
    return out


def transform_points(T: np.ndarray, xyz: np.ndarray) -> np.ndarray:
    """Apply poses ``T [..., 4, 4]`` to points ``xyz [..., N, 3]`` -> ``[..., N, 3]``."""
    T = _as_poses(T, "T")
    xyz = np.asarray(xyz)
    if xyz.shape[-1] != 3:
        raise ValueError(f"transform_points: expected xyz of shape [..., N, 3], got {xyz.shape}")
    return xyz @ np.swapaxes(T[..., :3, :3], -1, -2) + T[..., None, :3, 3]


def interpolate_pose(T0: np.ndarray, T1: np.ndarray, alpha: float | np.ndarray) -> np.ndarray:
    """Pose between T0 (alpha=0) and T1 (alpha=1): slerp on rotation, lerp on translation.

    ``alpha`` may be a scalar or an array; its shape broadcasts against the poses' leading
    dimensions (alpha ``[M]`` with single poses gives ``[M, 4, 4]``).
    """
    T0, T1 = _as_poses(T0, "T0"), _as_poses(T1, "T1")
    alpha = np.asarray(alpha, dtype=np.float64)
    if np.any(~np.isfinite(alpha)) or np.any(alpha < 0.0) or np.any(alpha > 1.0):
        raise ValueError("interpolate_pose: alpha must lie in [0, 1]")
    R0, R1 = T0[..., :3, :3], T1[..., :3, :3]
    dphi = so3_log(np.swapaxes(R0, -1, -2) @ R1)
    R = R0 @ so3_exp(alpha[..., None] * dphi)
    a = alpha[..., None]
    t = (1.0 - a) * T0[..., :3, 3] + a * T1[..., :3, 3]
    return _assemble(R, t)


def is_rigid(T: np.ndarray, tol: float = 1e-4) -> bool:
    """True if every pose in ``T [..., 4, 4]`` is finite, orthonormal with det +1, and has
    last row ``[0, 0, 0, 1]``, each within ``tol``."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape[-2:] != (4, 4) or not np.all(np.isfinite(T)):
        return False
    R = T[..., :3, :3]
    ortho = np.abs(R @ np.swapaxes(R, -1, -2) - np.eye(3)).max(initial=0.0) <= tol
    det = np.abs(np.linalg.det(R) - 1.0).max(initial=0.0) <= tol
    row = np.abs(T[..., 3, :] - np.array([0.0, 0.0, 0.0, 1.0])).max(initial=0.0) <= tol
    return bool(ortho and det and row)


def project_to_rigid(T: np.ndarray) -> np.ndarray:
    """Nearest rigid poses (Frobenius norm on the rotation, via SVD), e.g. to remove the drift
    of long products; translation kept, last row reset to ``[0, 0, 0, 1]``."""
    T = _as_poses(T, "T")
    U, _, Vt = np.linalg.svd(T[..., :3, :3])
    sign = np.sign(np.linalg.det(U @ Vt))
    sign = np.where(sign == 0.0, 1.0, sign)
    D = np.broadcast_to(np.eye(3), U.shape).copy()
    D[..., 2, 2] = sign
    return _assemble(U @ D @ Vt, T[..., :3, 3])


def pose_error(T_a: np.ndarray, T_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Translation distance (metres) and rotation angle (radians) between two poses.

    Both poses must map into the same frame (e.g. two estimates of ``T_world_cam``); the
    translation error is ``|t_a - t_b|`` and the rotation error the angle of ``R_a^T R_b``.
    Returns float64 arrays with the broadcast leading shape (0-d for single poses).
    """
    T_a, T_b = _as_poses(T_a, "T_a"), _as_poses(T_b, "T_b")
    trans = np.linalg.norm(T_a[..., :3, 3] - T_b[..., :3, 3], axis=-1)
    dR = np.swapaxes(T_a[..., :3, :3], -1, -2) @ T_b[..., :3, :3]
    rot = np.linalg.norm(so3_log(dR), axis=-1)
    return trans, rot


# --------------------------------------------------------------------------------------------
# helpers


def _so3_coeffs(phi: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """a = sin(th)/th, b = (1 - cos th)/th^2, c = (th - sin th)/th^3 for th = |phi|."""
    theta2 = np.sum(phi * phi, axis=-1)
    theta = np.sqrt(theta2)
    small = theta < _SMALL_ANGLE
    th = np.where(small, 1.0, theta)
    half_sin = np.sin(0.5 * th)
    a_closed = np.sin(th) / th
    b_closed = 2.0 * half_sin * half_sin / (th * th)  # 1 - cos without the cancellation
    c_closed = (th - np.sin(th)) / (th * th * th)
    x = theta2
    a_series = 1.0 - x / 6.0 * (1.0 - x / 20.0 * (1.0 - x / 42.0 * (1.0 - x / 72.0)))
    b_series = 0.5 - x / 24.0 * (1.0 - x / 30.0 * (1.0 - x / 56.0 * (1.0 - x / 90.0)))
    c_series = 1.0 / 6.0 - x / 120.0 * (1.0 - x / 42.0 * (1.0 - x / 72.0 * (1.0 - x / 110.0)))
    return (
        np.where(small, a_series, a_closed),
        np.where(small, b_series, b_closed),
        np.where(small, c_series, c_closed),
    )


def _quat_candidates(R: np.ndarray) -> np.ndarray:
    """The four Shepperd candidates (unnormalised, xyzw) stacked as ``[..., 4, 4]``."""
    r00, r01, r02 = R[..., 0, 0], R[..., 0, 1], R[..., 0, 2]
    r10, r11, r12 = R[..., 1, 0], R[..., 1, 1], R[..., 1, 2]
    r20, r21, r22 = R[..., 2, 0], R[..., 2, 1], R[..., 2, 2]
    tr = r00 + r11 + r22
    from_x = np.stack([1 + r00 - r11 - r22, r01 + r10, r02 + r20, r21 - r12], -1)
    from_y = np.stack([r01 + r10, 1 + r11 - r00 - r22, r12 + r21, r02 - r20], -1)
    from_z = np.stack([r02 + r20, r12 + r21, 1 + r22 - r00 - r11, r10 - r01], -1)
    from_w = np.stack([r21 - r12, r02 - r20, r10 - r01, 1 + tr], -1)
    return np.stack([from_x, from_y, from_z, from_w], axis=-2)


def _assemble(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """4x4 poses from rotations ``[..., 3, 3]`` and translations ``[..., 3]`` (broadcast)."""
    lead = np.broadcast_shapes(R.shape[:-2], t.shape[:-1])
    T = np.zeros((*lead, 4, 4), dtype=np.float64)
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def _as_vectors(x: np.ndarray, size: int, name: str) -> np.ndarray:
    x = np.asarray(x, dtype=np.float64)
    if x.ndim == 0 or x.shape[-1] != size:
        raise ValueError(f"expected {name} of shape [..., {size}], got {x.shape}")
    return x


def _as_poses(T: np.ndarray, name: str) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    if T.ndim < 2 or T.shape[-2:] != (4, 4):
        raise ValueError(f"expected {name} of shape [..., 4, 4], got {T.shape}")
    return T

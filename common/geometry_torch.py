"""Differentiable torch counterparts of ``cpslam.common.geometry`` (same conventions).

Kept in a separate module so that ``cpslam.common.geometry`` imports without torch. Every
function works on its input's device and dtype, is batched over leading dimensions, and avoids
in-place writes on tensors that autograd needs. Small-angle branches use the "double where"
pattern (the closed form is evaluated on a safe dummy angle where it would divide by zero), so
gradients stay finite at exactly zero rotation.

Twists are ``[rho (translation), phi (rotation)]``; quaternions are xyzw.
"""

from __future__ import annotations

import math

import torch

__all__ = [
    "torch_compose",
    "torch_interpolate_pose",
    "torch_invert",
    "torch_matrix_to_quat",
    "torch_pose_from_tq",
    "torch_quat_to_matrix",
    "torch_se3_exp",
    "torch_se3_log",
    "torch_skew",
    "torch_so3_exp",
    "torch_so3_log",
    "torch_transform_points",
]

# Below this angle the Taylor series replace the closed forms (see geometry._SMALL_ANGLE);
# float32 needs the larger switch point because (th - sin th) cancels sooner.
_SMALL_ANGLE_FLOAT64 = 0.05
_SMALL_ANGLE_LOW_PRECISION = 0.2


def torch_so3_exp(phi: torch.Tensor) -> torch.Tensor:
    """Rotation matrices ``[..., 3, 3]`` from rotation vectors ``phi [..., 3]``."""
    _check_last(phi, 3, "phi")
    a, b, _ = _so3_coeffs(phi)
    k = torch_skew(phi)
    eye = torch.eye(3, dtype=phi.dtype, device=phi.device)
    return eye + a[..., None, None] * k + b[..., None, None] * (k @ k)


def torch_so3_log(R: torch.Tensor) -> torch.Tensor:
    """Rotation vectors ``[..., 3]`` (angle in [0, pi]) from rotation matrices ``[..., 3, 3]``.

    Through the quaternion (Shepperd), as ``geometry.so3_log``: accurate at tiny angles and
    near pi. The log jumps at pi (the axis flips sign), so its gradient is only meaningful
    below pi.
    """
    q = torch_matrix_to_quat(R)
    v, w = q[..., :3], q[..., 3]
    n2 = (v * v).sum(-1)
    # Small angle <=> x = tan^2(angle / 2) small; there w ~ 1, far from zero.
    limit = _SMALL_ANGLE_FLOAT64 if R.dtype == torch.float64 else _SMALL_ANGLE_LOW_PRECISION
    small = n2 < (math.tan(0.5 * limit) ** 2) * (w * w)
    # angle / |v| = 2 atan2(|v|, w) / |v|. Its derivative cancels badly for small |v|, so the
    # series of atan(s)/s in x = s^2 (s = |v| / w) is used there; dummy values on the branch
    # not taken keep both value and gradient finite ("double where").
    n = torch.sqrt(torch.where(small, torch.ones_like(n2), n2))
    scale_closed = 2.0 * torch.atan2(n, w) / n
    w_safe = torch.where(small, w, torch.ones_like(w))
    x = torch.where(small, n2, torch.zeros_like(n2)) / (w_safe * w_safe)
    atan_series = 1.0 - x / 3.0 * (1.0 - 0.6 * x * (1.0 - x * 5.0 / 7.0 * (1.0 - x * 7.0 / 9.0)))
    scale = torch.where(small, 2.0 * atan_series / w_safe, scale_closed)
    return scale[..., None] * v


def torch_se3_exp(xi: torch.Tensor) -> torch.Tensor:
    """Poses ``[..., 4, 4]`` from twists ``xi [..., 6] = [rho, phi]`` (true SE(3) exp)."""
    _check_last(xi, 6, "xi")
    rho, phi = xi[..., :3], xi[..., 3:]
    a, b, c = _so3_coeffs(phi)
    k = torch_skew(phi)
    k2 = k @ k
    eye = torch.eye(3, dtype=xi.dtype, device=xi.device)
    R = eye + a[..., None, None] * k + b[..., None, None] * k2
    V = eye + b[..., None, None] * k + c[..., None, None] * k2
    return _assemble(R, (V @ rho[..., None])[..., 0])


def torch_se3_log(T: torch.Tensor) -> torch.Tensor:
    """Twists ``[..., 6] = [rho, phi]`` from poses ``[..., 4, 4]``; inverse of ``torch_se3_exp``."""
    _check_pose(T, "T")
    phi = torch_so3_log(T[..., :3, :3])
    theta2 = (phi * phi).sum(-1)
    limit = _SMALL_ANGLE_FLOAT64 if T.dtype == torch.float64 else _SMALL_ANGLE_LOW_PRECISION
    small = theta2 < limit * limit
    th = torch.sqrt(torch.where(small, torch.ones_like(theta2), theta2))
    # V^-1 = I - K/2 + d K^2 with d = (1 - h cot h) / th^2, h = th / 2: finite up to and at
    # pi, since the log's angle is at most pi (h <= pi/2, so sin h > 0).
    half = 0.5 * th
    d_closed = (1.0 - half * torch.cos(half) / torch.sin(half)) / (th * th)
    x = theta2
    d_series = 1.0 / 12.0 + x * (1.0 / 720.0 + x * (1.0 / 30240.0 + x / 1209600.0))
    d = torch.where(small, d_series, d_closed)
    k = torch_skew(phi)
    eye = torch.eye(3, dtype=T.dtype, device=T.device)
    V_inv = eye - 0.5 * k + d[..., None, None] * (k @ k)
    rho = (V_inv @ T[..., :3, 3:4])[..., 0]
    return torch.cat([rho, phi], dim=-1)


def torch_skew(v: torch.Tensor) -> torch.Tensor:
    """Cross-product matrices ``[..., 3, 3]`` of vectors ``v [..., 3]``."""
    x, y, z = v.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack([o, -z, y, z, o, -x, -y, x, o], dim=-1).reshape(*v.shape[:-1], 3, 3)


def torch_quat_to_matrix(q: torch.Tensor) -> torch.Tensor:
    """Rotation matrices ``[..., 3, 3]`` from quaternions ``[..., 4]`` xyzw (normalised here).

    No zero-norm check (it would force a device sync every call); a zero quaternion gives NaN.
    """
    _check_last(q, 4, "q")
    q = q / torch.linalg.vector_norm(q, dim=-1, keepdim=True)
    x, y, z, w = q.unbind(-1)
    R = torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
            2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
            2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    )  # fmt: skip
    return R.reshape(*q.shape[:-1], 3, 3)


def torch_matrix_to_quat(R: torch.Tensor) -> torch.Tensor:
    """Unit quaternions ``[..., 4]`` (xyzw, w >= 0) from rotations ``[..., 3, 3]`` (Shepperd)."""
    if R.shape[-2:] != (3, 3):
        raise ValueError(f"torch_matrix_to_quat: expected R of shape [..., 3, 3], got {R.shape}")
    r00, r01, r02 = R[..., 0, 0], R[..., 0, 1], R[..., 0, 2]
    r10, r11, r12 = R[..., 1, 0], R[..., 1, 1], R[..., 1, 2]
    r20, r21, r22 = R[..., 2, 0], R[..., 2, 1], R[..., 2, 2]
    tr = r00 + r11 + r22
    candidates = torch.stack(
        [
            torch.stack([1 + r00 - r11 - r22, r01 + r10, r02 + r20, r21 - r12], -1),
            torch.stack([r01 + r10, 1 + r11 - r00 - r22, r12 + r21, r02 - r20], -1),
            torch.stack([r02 + r20, r12 + r21, 1 + r22 - r00 - r11, r10 - r01], -1),
            torch.stack([r21 - r12, r02 - r20, r10 - r01, 1 + tr], -1),
        ],
        dim=-2,
    )
    choice = torch.stack([r00, r11, r22, tr], -1).argmax(-1)
    index = choice[..., None, None].expand(*choice.shape, 1, 4)
    q = torch.gather(candidates, -2, index)[..., 0, :]
    q = q / torch.linalg.vector_norm(q, dim=-1, keepdim=True)
    return torch.where(q[..., 3:4] < 0, -q, q)


def torch_pose_from_tq(t: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
    """Poses ``[..., 4, 4]`` from translations ``[..., 3]`` and quaternions ``[..., 4]`` xyzw."""
    _check_last(t, 3, "t")
    return _assemble(torch_quat_to_matrix(q), t)


def torch_invert(T: torch.Tensor) -> torch.Tensor:
    """Inverse of rigid poses ``[..., 4, 4]`` using R^T."""
    _check_pose(T, "T")
    Rt = T[..., :3, :3].transpose(-1, -2)
    return _assemble(Rt, -(Rt @ T[..., :3, 3:4])[..., 0])


def torch_compose(*Ts: torch.Tensor) -> torch.Tensor:
    """Product ``Ts[0] @ Ts[1] @ ...`` left to right."""
    if not Ts:
        raise ValueError("torch_compose: needs at least one pose")
    out = Ts[0]
    for T in Ts[1:]:
        out = out @ T
    return out


def torch_transform_points(T: torch.Tensor, xyz: torch.Tensor) -> torch.Tensor:
    """Apply poses ``T [..., 4, 4]`` to points ``xyz [..., N, 3]`` -> ``[..., N, 3]``."""
    _check_pose(T, "T")
    _check_last(xyz, 3, "xyz")
    return xyz @ T[..., :3, :3].transpose(-1, -2) + T[..., None, :3, 3]


def torch_interpolate_pose(
    T0: torch.Tensor, T1: torch.Tensor, alpha: float | torch.Tensor
) -> torch.Tensor:
    """Pose between T0 (alpha=0) and T1 (alpha=1): slerp on rotation, lerp on translation.

    ``alpha`` may be a number or a tensor whose shape broadcasts against the poses' leading
    dimensions (alpha ``[M]`` with single poses gives ``[M, 4, 4]``); gradients flow to the
    poses and to alpha. A number outside [0, 1] is refused; a tensor is not checked (that
    would force a device sync every call).
    """
    _check_pose(T0, "T0")
    _check_pose(T1, "T1")
    if not isinstance(alpha, torch.Tensor):
        if not 0.0 <= alpha <= 1.0:  # also refuses NaN
            raise ValueError("torch_interpolate_pose: alpha must lie in [0, 1]")
    alpha = torch.as_tensor(alpha, dtype=T0.dtype, device=T0.device)
    R0, R1 = T0[..., :3, :3], T1[..., :3, :3]
    dphi = torch_so3_log(R0.transpose(-1, -2) @ R1)
    a = alpha[..., None]
    R = R0 @ torch_so3_exp(a * dphi)
    t = (1.0 - a) * T0[..., :3, 3] + a * T1[..., :3, 3]
    return _assemble(R, t)


# --------------------------------------------------------------------------------------------
# helpers


def _so3_coeffs(phi: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """a = sin(th)/th, b = (1 - cos th)/th^2, c = (th - sin th)/th^3, safe at th = 0."""
    theta2 = (phi * phi).sum(-1)
    limit = _SMALL_ANGLE_FLOAT64 if phi.dtype == torch.float64 else _SMALL_ANGLE_LOW_PRECISION
    small = theta2 < limit * limit
    # Closed forms on a dummy angle of 1 where small: neither value nor gradient becomes NaN.
    th = torch.sqrt(torch.where(small, torch.ones_like(theta2), theta2))
    sin = torch.sin(th)
    half_sin = torch.sin(0.5 * th)
    a_closed = sin / th
    b_closed = 2.0 * half_sin * half_sin / (th * th)
    c_closed = (th - sin) / (th * th * th)
    x = theta2
    a_series = 1.0 - x / 6.0 * (1.0 - x / 20.0 * (1.0 - x / 42.0 * (1.0 - x / 72.0)))
    b_series = 0.5 - x / 24.0 * (1.0 - x / 30.0 * (1.0 - x / 56.0 * (1.0 - x / 90.0)))
    c_series = 1.0 / 6.0 - x / 120.0 * (1.0 - x / 42.0 * (1.0 - x / 72.0 * (1.0 - x / 110.0)))
    return (
        torch.where(small, a_series, a_closed),
        torch.where(small, b_series, b_closed),
        torch.where(small, c_series, c_closed),
    )


def _assemble(R: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """4x4 poses from ``R [..., 3, 3]`` and ``t [..., 3]`` without in-place writes."""
    lead = torch.broadcast_shapes(R.shape[:-2], t.shape[:-1])
    top = torch.cat([R.expand(*lead, 3, 3), t.expand(*lead, 3)[..., None]], dim=-1)
    bottom = torch.zeros(4, dtype=R.dtype, device=R.device)
    bottom = torch.cat([bottom[:3], torch.ones_like(bottom[:1])]).expand(*lead, 1, 4)
    return torch.cat([top, bottom], dim=-2)


def _check_last(x: torch.Tensor, size: int, name: str) -> None:
    if x.ndim == 0 or x.shape[-1] != size:
        raise ValueError(f"expected {name} of shape [..., {size}], got {tuple(x.shape)}")


def _check_pose(T: torch.Tensor, name: str) -> None:
    if T.ndim < 2 or T.shape[-2:] != (4, 4):
        raise ValueError(f"expected {name} of shape [..., 4, 4], got {tuple(T.shape)}")

"""ICP between two RGB-D clouds: symmetric point-to-plane with a photometric term, and the
information matrix of its result.

The clouds are `cpslam.common.registration`'s views: ``xyz``/``normals`` (coarse),
``fine_xyz``/``fine_normals``/``fine_intensity`` and ``gradient`` (the intensity gradient in
each fine point's tangent plane), KD-trees ``coarse_tree`` and ``tree``. ``T`` maps cloud a
(src) into cloud b (dst). numpy only: the same inputs give bit-identical poses.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from cpslam.common.geometry import skew, so3_exp

__all__ = ["icp", "icp_information"]

_LAMBDA_GEOMETRIC = 0.968  # weight of the geometric term in coloured ICP (Park et al.)
_COLOR_KERNEL = 0.1  # Tukey width of the intensity residual (intensity 0..1)


def icp(a: Any, b: Any, T: np.ndarray, fine: bool, max_distance: float, kernel: float,
        iters: int = 40, tol: float = 1e-6) -> np.ndarray:
    """Gauss-Newton on r = (p - q) . n, n the mean of both normals (symmetric ICP), plus on
    the fine clouds the intensity residual against q's tangent-plane intensity gradient
    (Park et al., "Colored point cloud registration revisited", ICCV 2017); Tukey kernels of
    width `kernel` (m) and 0.1 (intensity). Correspondences within max_distance."""
    T = T.copy()
    for _ in range(iters):
        terms = _linearise(a, b, T, fine, max_distance, kernel)
        if terms is None:
            break
        (J, r, w), colour = terms
        H, g = (J * w[:, None]).T @ J, (J * w[:, None]).T @ r
        if colour is not None:
            J_c, r_c, w_c = colour
            H = _LAMBDA_GEOMETRIC * H + (1.0 - _LAMBDA_GEOMETRIC) * (J_c * w_c[:, None]).T @ J_c
            g = _LAMBDA_GEOMETRIC * g + (1.0 - _LAMBDA_GEOMETRIC) * (J_c * w_c[:, None]).T @ r_c
        try:
            delta = -np.linalg.solve(H + 1e-9 * np.eye(6), g)
        except np.linalg.LinAlgError:
            break
        step = np.eye(4)
        step[:3, :3], step[:3, 3] = so3_exp(delta[:3]), delta[3:]
        T = step @ T
        if np.linalg.norm(delta) < tol:
            break
    return T


def icp_information(a: Any, b: Any, T: np.ndarray, max_distance: float, kernel: float
                    ) -> tuple[np.ndarray, int]:
    """Gauss-Newton information [6, 6] of the pose T (fine clouds) and the number of
    correspondences it rests on.

    Each residual kind (point-to-plane, intensity) is divided by its own robustly weighted
    variance, so the matrix is the inverse covariance the residuals would give if they were
    independent; they are not (neighbouring points share the depth sensor's errors), which a
    caller corrects with one calibrated factor. The perturbation is on the right, translation
    first (the pose graph's and g2o's convention): T exp(xi), xi = [rho, phi] in the src
    frame. Zero when fewer than six correspondences remain.
    """
    terms = _linearise(a, b, T, True, max_distance, kernel)
    if terms is None:
        return np.zeros((6, 6)), 0
    H = np.zeros((6, 6))
    for J, r, w in (t for t in terms if t is not None):
        variance = float(np.sum(w * r * r) / max(np.sum(w), 1e-12))
        H += (J * w[:, None]).T @ J / max(variance, 1e-12)
    # H is for a left step (rotation, translation) in the dst frame: exp(d) T = T exp(Ad d').
    R, t = T[:3, :3], T[:3, 3]
    adjoint = np.zeros((6, 6))  # Ad_T in (rotation, translation) order
    adjoint[:3, :3], adjoint[3:, 3:], adjoint[3:, :3] = R, R, skew(t) @ R
    H_right = adjoint.T @ H @ adjoint
    order = [3, 4, 5, 0, 1, 2]  # to (translation, rotation)
    return H_right[np.ix_(order, order)], len(terms[0][1])


def _linearise(a: Any, b: Any, T: np.ndarray, fine: bool, max_distance: float, kernel: float):
    """Correspondences at T and their residuals: ((J, r, w), colour (J_c, r_c, w_c) or None),
    rows of J in the (rotation, translation) order of a left step; None below 6 pairs."""
    if fine:
        xyz_a, normals_a, xyz_b, normals_b = a.fine_xyz, a.fine_normals, b.fine_xyz, b.fine_normals
        tree, gradient_b = b.tree, b.gradient
    else:
        xyz_a, normals_a, xyz_b, normals_b = a.xyz, a.normals, b.xyz, b.normals
        tree, gradient_b = b.coarse_tree, None
    p = xyz_a @ T[:3, :3].T + T[:3, 3]
    dist, j = tree.query(p, distance_upper_bound=max_distance)
    ok = np.flatnonzero(np.isfinite(dist))
    p, n_p, j = p[ok], normals_a[ok] @ T[:3, :3].T, j[ok]
    q, n_q = xyz_b[j], normals_b[j]
    agree = np.einsum("ni,ni->n", n_p, n_q) > 0.5  # the same side of the same surface
    p, n_p, q, n_q, ok, j = p[agree], n_p[agree], q[agree], n_q[agree], ok[agree], j[agree]
    if len(p) < 6:
        return None
    n = n_p + n_q
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    r = np.einsum("ni,ni->n", p - q, n)
    J = np.hstack([np.cross(p, n) + np.cross(n_p, p - q), n])
    geometric = (J, r, _tukey(r, kernel))
    if gradient_b is None:
        return geometric, None
    d = gradient_b[j]  # in q's tangent plane
    on_plane = p - np.einsum("ni,ni->n", p - q, n_q)[:, None] * n_q
    r_c = a.fine_intensity[ok] - b.fine_intensity[j] - np.einsum("ni,ni->n", d, on_plane - q)
    J_c = -np.hstack([np.cross(p, d), d])
    return geometric, (J_c, r_c, _tukey(r_c, _COLOR_KERNEL))


def _tukey(r: np.ndarray, k: float) -> np.ndarray:
    """Tukey biweight weights of residuals r for kernel width k."""
    return np.where(np.abs(r) < k, (1.0 - (r / k) ** 2) ** 2, 0.0)

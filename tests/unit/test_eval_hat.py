"""The three-cornered hat: each trajectory's own error from pairwise differences alone."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cpslam.common.geometry import se3_exp
from cpslam.tools.eval.hat import hat_table, pairwise_differences, three_cornered_hat


def _walk(n: int, rng: np.random.Generator) -> np.ndarray:
    """A smooth camera path T_world_cam [n, 4, 4]."""
    poses, T = [], np.eye(4)
    for _ in range(n):
        T = T @ se3_exp(np.r_[0.01, 0.002, 0.004, rng.normal(0, 0.003, 3)])
        poses.append(T.copy())
    return np.stack(poses)


def _noisy(truth: np.ndarray, sigma_m: float, rng: np.random.Generator) -> np.ndarray:
    """Each position off by independent isotropic noise of RMS norm sigma_m."""
    out = truth.copy()
    out[:, :3, 3] += rng.normal(0.0, sigma_m / math.sqrt(3), (len(truth), 3))
    return out


def test_exact_differences_give_exact_errors() -> None:
    a, b, c = 0.02, 0.01, 0.005
    d_ab, d_ac, d_bc = math.hypot(a, b), math.hypot(a, c), math.hypot(b, c)
    assert three_cornered_hat(d_ab, d_ac, d_bc) == pytest.approx((a, b, c))


def test_inconsistent_differences_give_a_negative_estimate() -> None:
    # c cannot differ from a by less than b does while b and c differ a lot.
    est = three_cornered_hat(0.01, 0.001, 0.05)
    assert est[0] < 0


def test_negative_difference_is_an_error() -> None:
    with pytest.raises(ValueError, match="below 0"):
        three_cornered_hat(0.01, -0.01, 0.01)


def test_hat_recovers_each_sources_own_error() -> None:
    """Three noisy copies of one path with known, different noise: the hat finds each one's
    error within a tenth, though no copy is the truth (over eight seeds of this draw the
    estimates fell within 4 %; a source far smaller than the others is resolved less well)."""
    rng = np.random.default_rng(3)
    truth = _walk(3000, rng)
    sigmas = {"reference": 0.02, "first": 0.012, "second": 0.008}
    trajectories = {name: _noisy(truth, s, rng) for name, s in sigmas.items()}
    pairs = pairwise_differences(trajectories, deltas=(1, 10))
    assert set(pairs) == {"reference|first", "reference|second", "first|second"}
    table = hat_table(pairs, "reference", "first", "second")
    for name, sigma in sigmas.items():
        assert table["ate_m"][name] == pytest.approx(sigma, rel=0.1)
        # Independent position noise at both ends of a span: sqrt(2) times it.
        assert table["rpe10_m"][name] == pytest.approx(math.sqrt(2) * sigma, rel=0.1)


def test_pairwise_differences_need_one_length() -> None:
    rng = np.random.default_rng(0)
    with pytest.raises(ValueError, match="differ in length"):
        pairwise_differences({"a": _walk(20, rng), "b": _walk(21, rng)})

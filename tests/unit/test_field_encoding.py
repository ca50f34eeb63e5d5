"""Positional encoding: widths and values as in the paper."""

from __future__ import annotations

import math

import pytest
import torch

from cpslam.common.field import encoded_dim, positional_encoding


def test_paper_widths() -> None:
    features = torch.randn(5, 32)
    offsets = torch.randn(5, 3)
    assert positional_encoding(features, 1).shape == (5, 96)
    assert positional_encoding(offsets, 7).shape == (5, 45)
    assert encoded_dim(32, 1) + encoded_dim(3, 7) == 96 + 45


def test_values_follow_the_formula() -> None:
    v = torch.tensor([[0.25, -0.5]])
    out = positional_encoding(v, 2)[0]
    expected = [0.25, -0.5]
    for level in range(2):
        f = 2.0**level * math.pi
        expected += [math.sin(f * 0.25), math.sin(f * -0.5), math.cos(f * 0.25), math.cos(f * -0.5)]
    torch.testing.assert_close(out, torch.tensor(expected))


def test_order_zero_is_identity_and_negative_rejected() -> None:
    v = torch.randn(4, 3)
    assert torch.equal(positional_encoding(v, 0), v)
    with pytest.raises(ValueError, match="order"):
        positional_encoding(v, -1)

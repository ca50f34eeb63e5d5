"""Neighbour search: both backends agree with brute force, -1 beyond the radius."""

from __future__ import annotations

import pytest
import torch

from cpslam.common.field import NeighbourIndex


def _brute(points: torch.Tensor, queries: torch.Tensor, k: int, radius: float) -> torch.Tensor:
    d = torch.cdist(queries.double(), points.double())
    d = torch.where(d <= radius, d, torch.inf)
    best, idx = torch.topk(d, k, dim=1, largest=False)
    return torch.where(torch.isfinite(best), idx, -1)


@pytest.mark.parametrize("backend", ["kdtree", "torch"])
def test_matches_brute_force(backend: str) -> None:
    gen = torch.Generator().manual_seed(3)
    points = torch.rand(3000, 3, generator=gen) * torch.tensor([4.0, 3.0, 2.0]) - 1.0
    queries = torch.rand(2000, 3, generator=gen) * 5.0 - 1.5  # some far outside the cloud
    index = NeighbourIndex(points, backend=backend)
    got = index.query(queries, k=8, radius=0.2)
    want = _brute(points, queries, 8, 0.2)
    assert got.shape == (2000, 8) and got.dtype == torch.int64
    assert torch.equal(got, want)
    assert bool((got == -1).any()) and bool((got >= 0).any())


@pytest.mark.parametrize("backend", ["kdtree", "torch"])
def test_minus_one_beyond_radius(backend: str) -> None:
    points = torch.tensor([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.5, 0.0, 0.0]])
    index = NeighbourIndex(points, backend=backend)
    got = index.query(torch.tensor([[0.0, 0.0, 0.0], [3.0, 3.0, 3.0]]), k=4, radius=0.15)
    assert got.tolist() == [[0, 1, -1, -1], [-1, -1, -1, -1]]


@pytest.mark.parametrize("backend", ["kdtree", "torch"])
def test_far_from_origin_and_empty(backend: str) -> None:
    points = torch.tensor([[1.0e4, -1.0e4, 5.0], [1.0e4 + 0.05, -1.0e4, 5.0]])
    index = NeighbourIndex(points, backend=backend)
    got = index.query(torch.tensor([[1.0e4, -1.0e4, 5.0]]), k=2, radius=0.1)
    assert got.tolist() == [[0, 1]]
    empty = NeighbourIndex(torch.zeros(0, 3), backend=backend)
    assert empty.query(torch.zeros(2, 3), k=3, radius=1.0).tolist() == [[-1] * 3] * 2


def test_bad_arguments() -> None:
    with pytest.raises(ValueError, match="backend"):
        NeighbourIndex(torch.zeros(1, 3), backend="faiss")
    with pytest.raises(ValueError, match=r"\[N, 3\]"):
        NeighbourIndex(torch.zeros(4, 2))

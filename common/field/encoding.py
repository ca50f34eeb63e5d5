"""Positional encoding as in the paper (NeRF style, including the raw input)."""

from __future__ import annotations

import math

import torch


def encoded_dim(dim: int, order: int) -> int:
    """Width of `positional_encoding` for a `dim`-vector at `order` frequencies."""
    if dim < 1 or order < 0:
        raise ValueError(f"positional encoding needs dim >= 1 and order >= 0, got {dim}, {order}")
    return dim * (1 + 2 * order)


def positional_encoding(v: torch.Tensor, order: int) -> torch.Tensor:
    """PE_L(v) = [v, sin(2^0 pi v), cos(2^0 pi v), ..., sin(2^(L-1) pi v), cos(2^(L-1) pi v)].

    v: [..., D]; returns [..., D (1 + 2L)]. Each sin/cos block spans all D components, blocks
    in order of increasing frequency. Order 0 returns v unchanged.
    """
    if order < 0:
        raise ValueError(f"positional encoding order must be >= 0, got {order}")
    if order == 0:
        return v
    freqs = math.pi * torch.pow(
        2.0, torch.arange(order, device=v.device, dtype=v.dtype)
    )  # [L]
    scaled = v[..., None, :] * freqs[:, None]  # [..., L, D]
    # Interleave sin and cos per frequency: [..., L, 2, D] -> [..., 2 L D].
    sincos = torch.stack((torch.sin(scaled), torch.cos(scaled)), dim=-2)
    return torch.cat((v, sincos.flatten(-3)), dim=-1)

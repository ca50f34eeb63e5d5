"""Decoders C, G, U of the paper and the untrained feature CNN for new points.

C maps [PE(f_k), PE(x - p_k)] of each (sample, neighbour) pair to a per-neighbour feature,
G decodes an occupancy per neighbour, U decodes a colour from the inverse-distance weighted
per-neighbour feature. Only pairs that exist are evaluated: the inputs are flat lists of
(sample, point) pairs, so samples without neighbours cost nothing.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from cpslam.common.field.encoding import encoded_dim, positional_encoding

# Inverse-distance weights use sqrt(d^2 + EPS^2): finite weight and gradient at d = 0.
_DIST_EPS = 1e-6


class Decoders(nn.Module):
    """C, G and U with explicit widths (build them with `FieldSpec.decoders`).

    Args:
        feature_dim: point feature width F (32 in the paper).
        pe_feature: positional-encoding order on features (1 in the paper).
        pe_offset: positional-encoding order on offsets x - p_k (7 in the paper).
        c_hidden: width of C's hidden layers (256 in the paper).
        c_out: width of C's output, the per-neighbour feature (128 in the paper).
        g_hidden: width of G's hidden layers (256 in the paper).
        u_hidden: width of U's hidden layers (128 in the paper).
        u_layers: number of hidden layers of U (2 in the paper).
        seed: seed of the weight initialisation (the global RNG is left untouched).
        c_layers: number of hidden layers of C (1 in the paper).
        g_layers: number of hidden layers of G (1 in the paper).
        leaky_slope: negative slope of every LeakyReLU (0.01 in the paper, torch's default).
    """

    def __init__(
        self,
        *,
        feature_dim: int,
        pe_feature: int,
        pe_offset: int,
        c_hidden: int,
        c_out: int,
        g_hidden: int,
        u_hidden: int,
        u_layers: int,
        seed: int,
        c_layers: int,
        g_layers: int,
        leaky_slope: float,
    ) -> None:
        super().__init__()
        if min(u_layers, c_layers, g_layers) < 1:
            raise ValueError(f"Decoders: c_layers, g_layers and u_layers must be >= 1, got "
                             f"{c_layers}, {g_layers}, {u_layers}")
        self.feature_dim = feature_dim
        self.pe_feature = pe_feature
        self.pe_offset = pe_offset
        # Counters for tests and benchmarks: how many pair rows / samples went through the MLPs.
        self.rows_evaluated = 0
        self.samples_decoded = 0
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)
            # C's first layer is split into its feature and offset halves: the feature half is
            # evaluated once per distinct point instead of once per (sample, neighbour) pair,
            # which is the same function at a fraction of the cost.
            self.c_feature = nn.Linear(encoded_dim(feature_dim, pe_feature), c_hidden, bias=False)
            self.c_offset = nn.Linear(encoded_dim(3, pe_offset), c_hidden)
            # Extra hidden layers of C (none in the paper, so its state-dict keys stay put).
            self.c_mid = nn.ModuleList(
                nn.Linear(c_hidden, c_hidden) for _ in range(c_layers - 1)
            )
            self.c_out = nn.Linear(c_hidden, c_out)
            self.g = _mlp(c_out, g_hidden, g_layers, 1, leaky_slope)
            self.u = _mlp(c_out, u_hidden, u_layers, 3, leaky_slope)
        self.act = nn.LeakyReLU(leaky_slope)

    def forward(
        self, features_k: torch.Tensor, offsets: torch.Tensor, valid: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Decode samples from their gathered neighbours.

        features_k: [S, K, F]; offsets: [S, K, 3] (x - p_k); valid: [S, K] bool.
        Returns occupancy [S] in [0, 1] (0 where no neighbour is valid) and colour [S, 3].
        """
        if features_k.shape[:2] != valid.shape or offsets.shape[:2] != valid.shape:
            raise ValueError(
                f"Decoders.forward: features_k {tuple(features_k.shape)}, offsets "
                f"{tuple(offsets.shape)} and valid {tuple(valid.shape)} must share [S, K]"
            )
        sample, slot = valid.nonzero(as_tuple=True)
        pair_point = torch.arange(sample.numel(), device=sample.device)
        return self.forward_pairs(
            features_k[sample, slot], pair_point, offsets[sample, slot], sample, valid.shape[0]
        )

    def point_hidden(self, point_features: torch.Tensor) -> torch.Tensor:
        """C's first layer on the feature half: [P, F] -> [P, c_hidden] (no bias).

        A caller that decodes several times from the same points with frozen features and
        decoders (tracking) computes this once and passes it to `forward_pairs`.
        """
        return self.c_feature(positional_encoding(point_features, self.pe_feature))

    def forward_pairs(
        self,
        point_features: torch.Tensor | None,
        pair_point: torch.Tensor,
        pair_offset: torch.Tensor,
        pair_sample: torch.Tensor,
        n_samples: int,
        color: bool = True,
        point_hidden: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Decode from a flat list of (sample, point) pairs.

        point_features: [P, F] features of the points involved; pair_point: [V] int64 rows of
        point_features; pair_offset: [V, 3] x_sample - p_point; pair_sample: [V] int64 sample
        of each pair in [0, n_samples). Returns occupancy [n_samples], colour [n_samples, 3].
        With color=False, U is skipped and the colour is all zeros (depth-only tracking).
        point_hidden: `point_hidden(point_features)` computed beforehand (point_features is
        then not read and may be None).
        """
        device = pair_offset.device
        n_pairs = int(pair_sample.numel())
        self.rows_evaluated += n_pairs
        occupancy = torch.zeros(n_samples, device=device, dtype=pair_offset.dtype)
        if n_pairs == 0:
            return occupancy, torch.zeros(n_samples, 3, device=device, dtype=pair_offset.dtype)

        if point_hidden is None:
            point_hidden = self.point_hidden(point_features)
        # The gathered per-point half is added in place (the [V, H] per-pair tensors are the
        # largest of the pass; a Linear's backward does not read its output; the same sum, so
        # the same bits). The activations stay out of place: LeakyReLU's backward from its
        # output (the in-place form) ran at half the speed of the one from its input.
        # Row gathers use index_select: on CPU it copies [V, H] rows about five times faster
        # than indexing with a tensor (the same values; the same gradient bits in
        # deterministic mode).
        act = self.act
        h = self.c_offset(positional_encoding(pair_offset, self.pe_offset))
        h = act(h.add_(point_hidden.index_select(0, pair_point)))
        for layer in self.c_mid:
            h = act(layer(h))
        f_pair = act(self.c_out(h))  # [V, c_out]

        dist = torch.sqrt((pair_offset * pair_offset).sum(-1) + _DIST_EPS**2)
        w = 1.0 / dist
        w_sum = torch.zeros(n_samples, device=device, dtype=w.dtype).index_add(0, pair_sample, w)
        w = w / w_sum.index_select(0, pair_sample)

        occ_pair = torch.sigmoid(self.g(f_pair)).squeeze(-1)
        occupancy = occupancy.index_add(0, pair_sample, w * occ_pair)
        if not color:
            return occupancy, torch.zeros(n_samples, 3, device=device, dtype=pair_offset.dtype)

        decoded = (w_sum > 0).nonzero(as_tuple=True)[0]
        self.samples_decoded += int(decoded.numel())
        f_sample = torch.zeros(
            n_samples, f_pair.shape[1], device=device, dtype=f_pair.dtype
        ).index_add(0, pair_sample, w[:, None] * f_pair)
        rgb = torch.sigmoid(self.u(f_sample.index_select(0, decoded)))
        colors = torch.zeros(n_samples, 3, device=device, dtype=rgb.dtype)
        return occupancy, colors.index_copy(0, decoded, rgb)


def _mlp(n_in: int, hidden: int, layers: int, n_out: int, slope: float) -> nn.Sequential:
    """`layers` hidden Linear + LeakyReLU blocks of width `hidden`, then a Linear to n_out."""
    blocks: list[nn.Module] = [nn.Linear(n_in, hidden), nn.LeakyReLU(slope)]
    for _ in range(layers - 1):
        blocks += [nn.Linear(hidden, hidden), nn.LeakyReLU(slope)]
    blocks.append(nn.Linear(hidden, n_out))
    return nn.Sequential(*blocks)


class FeatureCNN(nn.Module):
    """One untrained convolution from RGB to F-d per-pixel features (initial point features).

    The weights come from `seed` and are never trained; the map then optimises the features
    of the points themselves.
    """

    def __init__(self, feature_dim: int, kernel_size: int = 3, seed: int = 0) -> None:
        super().__init__()
        if kernel_size % 2 != 1:
            raise ValueError(f"FeatureCNN: kernel_size must be odd, got {kernel_size}")
        self.feature_dim = feature_dim
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)
            self.conv = nn.Conv2d(3, feature_dim, kernel_size, padding=kernel_size // 2)
        self.requires_grad_(False)

    @torch.no_grad()
    def forward(self, rgb: np.ndarray | torch.Tensor) -> torch.Tensor:
        """rgb: uint8 [H, W, 3]. Returns features float32 [H, W, F] on this module's device."""
        if rgb.ndim != 3 or rgb.shape[2] != 3:
            raise ValueError(f"FeatureCNN: expected RGB [H, W, 3], got shape {tuple(rgb.shape)}")
        device = self.conv.weight.device
        image = torch.as_tensor(np.asarray(rgb) if not torch.is_tensor(rgb) else rgb)
        image = image.to(device=device, dtype=torch.float32) / 255.0
        out = self.conv(image.permute(2, 0, 1)[None])  # [1, F, H, W]
        return out[0].permute(1, 2, 0).contiguous()

    @torch.no_grad()
    def at_pixels(
        self, rgb: np.ndarray | torch.Tensor, u: torch.Tensor, v: torch.Tensor
    ) -> torch.Tensor:
        """Features [M, F] at integer pixel columns u [M] and rows v [M]."""
        features = self.forward(rgb)
        return features[v.long().to(features.device), u.long().to(features.device)]

"""Pooling a local feature map [B, C, h, w] into one global descriptor: NetVLAD and GeM.

NetVLAD (Arandjelovic et al., CVPR 2016) soft-assigns each L2-normalised local feature to K
cluster centres and sums the residuals per centre; intra-normalisation then a global L2 norm.
Untrained, the soft assignment is the one NetVLAD is initialised with: a 1x1 convolution with
weight 2·alpha·c_k and bias -alpha·|c_k|², i.e. a softmax over -alpha·|x - c_k|² (the |x|² term
cancels). GeM (Radenovic et al., TPAMI 2018) is the generalised mean (mean x^p)^(1/p) per channel.
Untrained centres come from `kmeans` over local features of `procedural_images`.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

__all__ = ["GeM", "NetVLAD", "assignment_alpha", "kmeans", "procedural_images"]


class NetVLAD(nn.Module):
    """NetVLAD layer: [B, C, h, w] -> [B, K * C], L2-normalised.

    `centroids` [K, C]; the assignment convolution is either given (`conv_weight` [K, C],
    `conv_bias` [K], as a trained layer has them) or derived from the centroids with `alpha`.
    """

    def __init__(
        self,
        centroids: torch.Tensor,
        alpha: float | None = None,
        conv_weight: torch.Tensor | None = None,
        conv_bias: torch.Tensor | None = None,
    ) -> None:
        super().__init__()
        centroids = centroids.detach().float()
        if centroids.ndim != 2:
            raise ValueError(f"centroids: expected [K, C], got shape {tuple(centroids.shape)}")
        if conv_weight is None:
            if alpha is None:
                raise ValueError("NetVLAD needs either conv_weight/conv_bias or alpha")
            conv_weight = 2.0 * alpha * centroids
            conv_bias = -alpha * (centroids**2).sum(dim=1)
        elif conv_bias is None:
            conv_bias = torch.zeros(centroids.shape[0], device=centroids.device)
        conv_weight = conv_weight.detach().float().reshape(centroids.shape)
        self.register_buffer("centroids", centroids)
        self.register_buffer("conv_weight", conv_weight)
        self.register_buffer("conv_bias", conv_bias.detach().float().reshape(-1))

    @property
    def clusters(self) -> int:
        return int(self.centroids.shape[0])

    @property
    def dim(self) -> int:
        return int(self.centroids.numel())

    def forward(self, feat: torch.Tensor) -> torch.Tensor:
        x = F.normalize(feat.flatten(2), dim=1)  # [B, C, N]
        logits = torch.einsum("kc,bcn->bkn", self.conv_weight, x) + self.conv_bias[None, :, None]
        soft = logits.softmax(dim=1)  # [B, K, N]
        # sum_n a_kn (x_n - c_k) = sum_n a_kn x_n - c_k sum_n a_kn
        vlad = torch.einsum("bkn,bcn->bkc", soft, x) - soft.sum(dim=2)[..., None] * self.centroids
        vlad = F.normalize(vlad, dim=2)  # intra-normalisation
        return F.normalize(vlad.flatten(1), dim=1)


class GeM(nn.Module):
    """Generalised-mean pooling: [B, C, h, w] -> [B, C], L2-normalised."""

    def __init__(self, p: float = 3.0, eps: float = 1e-6) -> None:
        super().__init__()
        if p <= 0:
            raise ValueError(f"GeM p must be positive, got {p}")
        self.p = float(p)
        self.eps = eps

    def forward(self, feat: torch.Tensor) -> torch.Tensor:
        pooled = feat.clamp_min(self.eps).pow(self.p).mean(dim=(2, 3)).pow(1.0 / self.p)
        return F.normalize(pooled, dim=1)


def kmeans(x: torch.Tensor, k: int, seed: int = 0, iters: int = 30) -> torch.Tensor:
    """Centres [k, C] of points x [N, C] by k-means++ seeding and Lloyd iterations (float64).

    Deterministic for a given input and seed; float64 so that tiny backbone differences between
    machines rarely change an assignment.
    """
    if x.ndim != 2 or x.shape[0] < k:
        raise ValueError(f"kmeans: need at least k={k} points [N, C], got {tuple(x.shape)}")
    x = x.double()
    gen = torch.Generator().manual_seed(seed)
    # The draws happen on the CPU generator's device: the same centres on CPU and CUDA.
    centres = [x[torch.randint(x.shape[0], (1,), generator=gen, device=gen.device)].squeeze(0)]
    d2 = ((x - centres[0]) ** 2).sum(dim=1)
    for _ in range(1, k):
        pick = torch.multinomial((d2 / d2.sum()).cpu(), 1, generator=gen).to(x.device)
        centres.append(x[pick].squeeze(0))
        d2 = torch.minimum(d2, ((x - centres[-1]) ** 2).sum(dim=1))
    c = torch.stack(centres)
    for _ in range(iters):
        assign = torch.cdist(x, c).argmin(dim=1)
        counts = torch.bincount(assign, minlength=k).double()
        sums = torch.zeros_like(c).index_add_(0, assign, x)
        # An emptied cluster keeps its previous centre rather than collapsing to zero.
        c_new = torch.where(counts[:, None] > 0, sums / counts.clamp_min(1)[:, None], c)
        if torch.allclose(c_new, c, atol=1e-9):
            break
        c = c_new
    return c.float()


def assignment_alpha(x: torch.Tensor, centroids: torch.Tensor, ratio: float = 0.01) -> float:
    """NetVLAD's initial softness: the mean gap between the nearest and second-nearest squared
    distance makes the second centre's weight `ratio` times the first's, on average."""
    d2 = torch.cdist(x.double(), centroids.double()) ** 2
    two = d2.topk(2, dim=1, largest=False).values
    gap = (two[:, 1] - two[:, 0]).mean().item()
    return -math.log(ratio) / max(gap, 1e-12)


def procedural_images(count: int, size: int, seed: int = 0) -> np.ndarray:
    """Deterministic indoor-like RGB uint8 images [count, size, size, 3]: shaded walls, boxes,
    lines, discs and value noise, so the local features span edges, corners, flat and textured
    regions in many colours."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float32) / size
    out = np.empty((count, size, size, 3), np.uint8)
    for i in range(count):
        base = rng.uniform(40, 220, 3)
        grad = rng.uniform(-60, 60, 2)
        img = base + (grad[0] * (xx - 0.5) + grad[1] * (yy - 0.5))[..., None]
        noise = cv2.resize(
            rng.normal(0, 1, (8, 8)).astype(np.float32), (size, size), interpolation=cv2.INTER_CUBIC
        )
        img = img + rng.uniform(0, 25) * noise[..., None]
        img = np.clip(img, 0, 255).astype(np.uint8).copy()
        for _ in range(rng.integers(3, 12)):
            colour = tuple(int(v) for v in rng.integers(0, 256, 3))
            shape = rng.integers(0, 3)
            p0 = rng.integers(0, size, 2)
            if shape == 0:
                p1 = np.clip(p0 + rng.integers(size // 16, size // 2, 2), 0, size - 1)
                cv2.rectangle(
                    img,
                    tuple(int(v) for v in p0),
                    tuple(int(v) for v in p1),
                    colour,
                    -1 if rng.random() < 0.7 else int(rng.integers(1, 4)),
                )
            elif shape == 1:
                p1 = rng.integers(0, size, 2)
                cv2.line(
                    img,
                    tuple(int(v) for v in p0),
                    tuple(int(v) for v in p1),
                    colour,
                    int(rng.integers(1, 5)),
                )
            else:
                cv2.circle(
                    img, tuple(int(v) for v in p0), int(rng.integers(3, size // 6)), colour, -1
                )
        fine = rng.normal(0, rng.uniform(0, 12), (size, size, 1))
        img = np.clip(cv2.GaussianBlur(img, (3, 3), 0) + fine, 0, 255)
        out[i] = img.astype(np.uint8)
    return out

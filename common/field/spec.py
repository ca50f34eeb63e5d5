"""`FieldSpec`: the neural point field's shape, one frozen value shared by every part.

The map, the decoders, the ray sampler and the renderer must agree on the feature width, the
grid cell, the neighbours per sample and their radius, the decoder widths and the samples per
ray; the tracker, the mapper, the back end and the federation all render the same field. The
spec is built once from the `field` config section (`cpslam.common.field_config.field_spec`)
and handed to each of them, so no part holds a default that copies a preset's value and a
caller cannot forget one. Its field names are the `field` section's. Plain dataclass: the
field package stays free of pydantic.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from cpslam.common.field.decoders import Decoders, FeatureCNN
from cpslam.common.field.points import NeuralPointMap
from cpslam.common.field.prior import apply_prior, resolve_prior
from cpslam.common.field.sampler import RaySampler

__all__ = ["FieldSpec"]


@dataclass(frozen=True)
class FieldSpec:
    """Every number of the `field` config section (see docs/configuration.md, `field`)."""

    feature_dim: int
    patch_size: int
    grid_size: float
    k_neighbors: int
    radius: float
    pe_feature_order: int
    pe_offset_order: int
    c_hidden: int
    c_layers: int
    c_out: int | None
    u_hidden: int
    u_layers: int
    g_hidden: int
    g_layers: int
    leaky_slope: float
    neighbour_backend: str
    n_near: int
    n_uniform: int
    near_lo: float
    near_hi: float
    far_hi: float
    no_depth_near: float
    chunk_rays: int
    prior: str | None = None

    def decoders(self, seed: int) -> Decoders:
        """Decoders C, G, U with these widths (C's output: c_out, else its hidden width),
        with the prior's weights if there is one, else random weights from `seed`."""
        decoders = Decoders(
            feature_dim=self.feature_dim, pe_feature=self.pe_feature_order,
            pe_offset=self.pe_offset_order, c_hidden=self.c_hidden,
            c_out=self.c_out or self.c_hidden, g_hidden=self.g_hidden, u_hidden=self.u_hidden,
            u_layers=self.u_layers, seed=seed, c_layers=self.c_layers, g_layers=self.g_layers,
            leaky_slope=self.leaky_slope,
        )
        if self.prior is not None:
            apply_prior(decoders, resolve_prior(self.prior), "decoders")
        return decoders

    def sampler(self, perturb: bool = True, n_near: int | None = None,
                n_uniform: int | None = None) -> RaySampler:
        """The paper's ray sampler with these depth bands and sample counts (n_near,
        n_uniform: other counts than the spec's, e.g. the tracker's)."""
        return RaySampler(
            n_near=self.n_near if n_near is None else n_near,
            n_uniform=self.n_uniform if n_uniform is None else n_uniform,
            min_depth=self.no_depth_near, perturb=perturb, near_lo=self.near_lo,
            near_hi=self.near_hi, far_hi=self.far_hi,
        )

    def point_map(self, agent_id: int, device: str | torch.device) -> NeuralPointMap:
        """An empty point map with this feature width and grid cell."""
        return NeuralPointMap(feature_dim=self.feature_dim, cell_size=self.grid_size,
                              default_agent=agent_id, device=device)

    def cnn(self, seed: int) -> FeatureCNN:
        """The untrained feature CNN that gives new points their initial features (the
        prior's, whose features its decoders were fitted to, if there is one)."""
        cnn = FeatureCNN(feature_dim=self.feature_dim, seed=seed)
        if self.prior is not None:
            apply_prior(cnn, resolve_prior(self.prior), "cnn")
        return cnn

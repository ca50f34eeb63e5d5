"""Build the neural point field's parts from the `field` config section.

Kept outside `cpslam.common.field` so that the field package stays free of pydantic; the agent
(odometry), the server and `cpslam render` all rebuild the model through these functions, so
a run's `config.yaml` plus its saved state dicts always give back the same model.
"""

from __future__ import annotations

from typing import Any

import torch

from cpslam.common.config import FieldConfig, TrackingConfig
from cpslam.common.field import Decoders, FeatureCNN, NeuralPointMap, RaySampler

__all__ = ["cnn_from_config", "decoders_from_config", "point_map_from_config",
           "sampler_from_config", "tracker_args_from_config"]


def decoders_from_config(field_cfg: FieldConfig, seed: int) -> Decoders:
    """Decoders C, G, U with the section's widths (C's output: c_out, else its hidden width)."""
    return Decoders(
        feature_dim=field_cfg.feature_dim,
        pe_feature=field_cfg.pe_feature_order,
        pe_offset=field_cfg.pe_offset_order,
        c_hidden=field_cfg.c_hidden,
        c_out=field_cfg.c_out or field_cfg.c_hidden,
        g_hidden=field_cfg.g_hidden,
        u_hidden=field_cfg.u_hidden,
        u_layers=field_cfg.u_layers,
        seed=seed,
        c_layers=field_cfg.c_layers,
        g_layers=field_cfg.g_layers,
        leaky_slope=field_cfg.leaky_slope,
    )


def point_map_from_config(
    field_cfg: FieldConfig, agent_id: int, device: str | torch.device
) -> NeuralPointMap:
    """An empty point map with the section's feature width and grid cell."""
    return NeuralPointMap(
        feature_dim=field_cfg.feature_dim,
        cell_size=field_cfg.grid_size,
        default_agent=agent_id,
        device=device,
    )


def sampler_from_config(field_cfg: FieldConfig, perturb: bool = True) -> RaySampler:
    """The paper's ray sampler with the section's sample counts and depth bands."""
    return RaySampler(
        n_near=field_cfg.n_near,
        n_uniform=field_cfg.n_uniform,
        min_depth=field_cfg.no_depth_near,
        perturb=perturb,
        near_lo=field_cfg.near_lo,
        near_hi=field_cfg.near_hi,
        far_hi=field_cfg.far_hi,
    )


def cnn_from_config(field_cfg: FieldConfig, seed: int) -> FeatureCNN:
    """The untrained feature CNN that gives new points their initial features."""
    return FeatureCNN(feature_dim=field_cfg.feature_dim, seed=seed)


def tracker_args_from_config(
    field_cfg: FieldConfig, tracking_cfg: TrackingConfig
) -> dict[str, Any]:
    """Keyword arguments of `Tracker` (all but intrinsics and sampler) from the `tracking`
    and `field` sections: the agent's tracker and the server's loop refinement share them."""
    tr = tracking_cfg
    return dict(
        iters=tr.iters, n_pixels=tr.n_pixels, lr=tr.lr, lr_end_factor=tr.lr_end_factor,
        color_weight=tr.color_weight, err_lo=tr.outlier_err_lo, err_hi=tr.outlier_err_hi,
        var_factor=tr.outlier_var_factor, keep_best=tr.keep_best,
        early_stop_tol=tr.early_stop_tol, k=field_cfg.k_neighbors, radius=field_cfg.radius,
        backend=field_cfg.neighbour_backend, chunk=field_cfg.chunk_rays,
        pixel_sampling=tr.pixel_sampling, method=tr.method, prior_sigma_t=tr.prior_sigma_t,
        prior_sigma_r=tr.prior_sigma_r, reference_weight=tr.reference_weight,
        reference_pixels=tr.reference_pixels,
    )

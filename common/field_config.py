"""The neural point field's spec and the tracker's and mapper's settings from the config.

Kept outside `cpslam.common.field` so that the field package stays free of pydantic; the agent
(odometry), the server and `cpslam render` all rebuild the model from `field_spec`, so a run's
`config.yaml` plus its saved state dicts always give back the same model.
"""

from __future__ import annotations

from typing import Any

from cpslam.common.config import FieldConfig, MappingConfig, TrackingConfig
from cpslam.common.field.spec import FieldSpec

__all__ = ["field_spec", "mapper_args_from_config", "tracker_args_from_config"]


def field_spec(field_cfg: FieldConfig) -> FieldSpec:
    """The `field` section as the frozen spec every part of the field is built from."""
    return FieldSpec(**field_cfg.model_dump())


def tracker_args_from_config(tracking_cfg: TrackingConfig) -> dict[str, Any]:
    """Keyword arguments of `Tracker` (all but intrinsics and the field spec) from the
    `tracking` section: the agent's tracker and the server's loop refinement share them."""
    tr = tracking_cfg
    return dict(
        iters=tr.iters, n_pixels=tr.n_pixels, lr=tr.lr, lr_end_factor=tr.lr_end_factor,
        color_weight=tr.color_weight, err_lo=tr.outlier_err_lo, err_hi=tr.outlier_err_hi,
        var_factor=tr.outlier_var_factor, keep_best=tr.keep_best,
        early_stop_tol=tr.early_stop_tol, pixel_sampling=tr.pixel_sampling, method=tr.method,
        prior_sigma_t=tr.prior_sigma_t, prior_sigma_r=tr.prior_sigma_r,
        reference_weight=tr.reference_weight, reference_pixels=tr.reference_pixels,
        n_near=tr.n_near, n_uniform=tr.n_uniform, relinearise_steps=tr.relinearise_steps,
        depth_iters=tr.depth_iters, step_stretch=tr.step_stretch,
    )


def mapper_args_from_config(mapping_cfg: MappingConfig) -> dict[str, Any]:
    """Keyword arguments of `Mapper` (all but the field spec) from the `mapping` section."""
    mp = mapping_cfg
    return dict(
        lr_decoders=mp.lr_decoders, lr_features=mp.lr_features,
        feature_lr_decay=mp.feature_lr_decay, feature_lr_decay_steps=mp.feature_lr_decay_steps,
        color_weight=mp.color_weight, add_points_depth_err=mp.add_points_depth_err,
        pose_average=mp.pose_average,
    )

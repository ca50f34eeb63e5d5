"""Sections of the collaborative back end: place recognition, loops, federation, pose graph,
refinement."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import (
    Field,
    NonNegativeInt,
    PositiveFloat,
    PositiveInt,
    model_validator,
)

from cpslam.common.config.base import Section

__all__ = [
    "FederationConfig",
    "LoopConfig",
    "PlaceRecognitionConfig",
    "PoseGraphConfig",
    "RefinementConfig",
]


class PlaceRecognitionConfig(Section):
    """Global image descriptors for loop detection."""

    backbone: Literal["efficientnet_lite0"] = "efficientnet_lite0"
    """Image backbone producing the local feature map."""
    aggregation: Literal["netvlad", "gem"] = "netvlad"
    """Pooling of the feature map into one descriptor: NetVLAD (the paper) or GeM."""
    layer: Literal["stage4", "stage5", "stage6", "stage7", "head"] | None = None
    """Backbone feature map aggregated; null = the one named in `weights`, else stage6."""
    clusters: PositiveInt = 8
    """Number of NetVLAD clusters (8 measured best untrained; docs/place_recognition.md)."""
    gem_p: PositiveFloat = 1.0
    """Exponent p of GeM pooling (1 = average pooling, measured best untrained)."""
    image_size: int = Field(default=224, ge=32)
    """Images are resized to image_size x image_size before the backbone."""
    weights: Path | None = None
    """Trained aggregation weights file supplied by the user; null = untrained/initialised."""


class LoopConfig(Section):
    """Loop detection, verification and relative pose estimation."""

    lambda_fine: float = Field(default=0.8, ge=-1.0, le=1.0)
    """Descriptor cosine above which a pair may align sub-maps (calibrated: docs/loops.md)."""
    lambda_coarse: float = Field(default=0.65, ge=-1.0, le=1.0)
    """Descriptor cosine above which a pair may add a pose-graph loop edge (docs/loops.md)."""
    min_keyframe_gap: NonNegativeInt = 3
    """Within one agent, keyframes fewer than this many keyframes apart are not loop candidates."""
    max_candidates: PositiveInt = 3
    """At most this many candidates per query keyframe are verified."""
    max_attempts: PositiveInt = 3
    """Tries of a candidate whose keyframe images could not be pulled before it is rejected."""
    spacing: PositiveInt = 1
    """Skip a candidate nearer (keyframes) than this to an accepted or queued pair; 1 skips none."""
    image_scale: float = Field(default=1.0, ge=0.1, le=1.0)
    """Pull keyframe images at this fraction of the agents' processed width and height."""
    coarse_method: Literal["icp", "none"] = "icp"
    """Coarse loop pose before refinement: icp = RANSAC + ICP on RGB-D; none = identity (paper)."""
    icp_max_distance: PositiveFloat = 0.2
    """Largest correspondence distance (m) in the coarse ICP."""
    icp_voxel_size: PositiveFloat = 0.05
    """Voxel size (m) the clouds are reduced to before the coarse ICP."""
    refine: bool = True
    """Track the loop keyframe against the other sub-map from the coarse pose (docs/loops.md)."""
    register_iters: PositiveInt = 200
    """Tracking steps refining a loop's relative pose against the other sub-map (our choice)."""
    verify: bool = True
    """Check a loop's overlap, residual, colour and free space before it becomes an edge."""
    verify_max_residual: PositiveFloat = 0.05
    """Largest accepted RMS point-to-plane residual of a loop after alignment (m)."""
    verify_min_overlap: float = Field(default=0.3, ge=0.0, le=1.0)
    """A loop is accepted when at least this fraction of the smaller view's points overlaps."""
    # The ICP Hessian treats every point's error as independent, which neighbouring points'
    # are not; 0.09 puts the median chi2 of ground-truth errors at its expected value on the
    # training scenes (bench/loop_edges.py --calibrate).
    information_scale: PositiveFloat = 0.09
    """Factor on a loop's registration information (ICP Hessian; not in the paper)."""

    @model_validator(mode="after")
    def _check(self) -> LoopConfig:
        if self.lambda_fine < self.lambda_coarse:
            raise ValueError(
                f"lambda_fine ({self.lambda_fine}) must be at least "
                f"lambda_coarse ({self.lambda_coarse})"
            )
        return self


class FederationConfig(Section):
    """Federated averaging of the decoders of a group of agents."""

    enabled: bool = True
    """Average decoders across the agents of a group."""
    round_every_mappings: PositiveInt = 5
    """Start a federated round every this many mapping calls of an agent."""
    round_timeout_s: PositiveFloat = 30.0
    """A round closes with the weights that arrived within this time (s)."""
    finetune_iters: NonNegativeInt = 100
    """Steps fine-tuning the averaged decoders on keyframe images after a merge."""
    finetune_views: PositiveInt | None = 8
    """Keyframe images a fine-tune trains on, spread over the group's keyframes; null = all."""
    weighting: Literal["samples", "uniform"] = "samples"
    """Average weighted by each agent's sample count, or uniformly."""


class PoseGraphConfig(Section):
    """Pose-graph optimisation over sequential and loop edges."""

    robust_kernel: Literal["cauchy", "huber", "gnc", "none"] = "cauchy"
    """Robust loss on loop edges (gnc = graduated non-convexity)."""
    kernel_scale: PositiveFloat = 1.0
    """Scale of the robust kernel, in units of the whitened residual."""
    seq_sigma_t: PositiveFloat = 0.01
    """Translation standard deviation (m) of sequential edges."""
    seq_sigma_r: PositiveFloat = 0.01
    """Rotation standard deviation (rad) of sequential edges."""
    loop_sigma_t: PositiveFloat = 0.05
    """Translation standard deviation (m) of loop edges."""
    loop_sigma_r: PositiveFloat = 0.05
    """Rotation standard deviation (rad) of loop edges."""
    max_iters: PositiveInt = 100
    """Largest number of Levenberg-Marquardt iterations."""
    rel_tol: PositiveFloat = 1e-5
    """Stop when the relative error decrease falls below this."""
    all_frames: bool = True
    """Optimise every frame's pose (the paper) rather than keyframes only."""


class RefinementConfig(Section):
    """Map refinement after a pose-graph correction."""

    finetune_iters: NonNegativeInt = 100
    """Steps of the short map fine-tune after points moved with their keyframes."""
    grid_filter: bool = True
    """Grid filter the moved points before the fine-tune."""

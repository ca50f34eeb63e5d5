"""Sections of one agent's SLAM front end: camera, neural field, tracking, mapping, keyframes."""

from __future__ import annotations

from typing import Literal

from pydantic import (
    Field,
    NonNegativeFloat,
    NonNegativeInt,
    PositiveFloat,
    PositiveInt,
    model_validator,
)

from cpslam.common.config.base import Section

__all__ = ["CameraConfig", "FieldConfig", "KeyframesConfig", "MappingConfig", "RecoveryConfig",
           "TrackingConfig"]


class CameraConfig(Section):
    """Camera intrinsics override and depth handling."""

    fx: PositiveFloat | None = None
    """Focal length in x (pixels, images as stored); null = from the dataset."""
    fy: PositiveFloat | None = None
    """Focal length in y (pixels, images as stored); null = from the dataset."""
    cx: float | None = None
    """Principal point x (pixels, images as stored); null = from the dataset."""
    cy: float | None = None
    """Principal point y (pixels, images as stored); null = from the dataset."""
    width: PositiveInt | None = None
    """Image width in pixels as stored; null = from the dataset."""
    height: PositiveInt | None = None
    """Image height in pixels as stored; null = from the dataset."""
    depth_scale: PositiveFloat | None = None
    """Raw depth units per metre (metres = raw / depth_scale); null = the format's default."""
    depth_min: NonNegativeFloat = 0.01
    """Depths below this (m) are treated as invalid."""
    depth_max: PositiveFloat = 10.0
    """Depths above this (m) are treated as invalid."""
    downscale: float = Field(default=1.0, gt=0.0, le=1.0)
    """Resize factor applied to every image before processing (0.5 runs 640x480 at 320x240)."""

    @model_validator(mode="after")
    def _check(self) -> CameraConfig:
        given = [getattr(self, k) is not None for k in ("fx", "fy", "cx", "cy", "width", "height")]
        if any(given) and not all(given):
            raise ValueError(
                "the intrinsics override needs all of fx, fy, cx, cy, width, height or none"
            )
        if self.depth_min >= self.depth_max:
            raise ValueError(
                f"depth_min ({self.depth_min}) must be below depth_max ({self.depth_max})"
            )
        return self

    @property
    def has_intrinsics(self) -> bool:
        """True when the config overrides the dataset's intrinsics."""
        return self.fx is not None


class FieldConfig(Section):
    """The neural point field: points, features, decoders and ray sampling."""

    feature_dim: PositiveInt = 32
    """Length of the learnable feature carried by every neural point."""
    patch_size: PositiveInt = 4
    """New points come from the centre pixel of each patch_size x patch_size image patch."""
    grid_size: PositiveFloat = 0.14
    """Grid-filter cell size rho (m): at most one point per cell."""
    k_neighbors: PositiveInt = 8
    """Neighbouring points K gathered for every ray sample."""
    radius: PositiveFloat = 0.15
    """Neighbour search radius r (m); a sample with no point this close has occupancy 0."""
    pe_feature_order: NonNegativeInt = 1
    """Positional-encoding frequencies applied to point features (0 = raw feature only)."""
    pe_offset_order: NonNegativeInt = 7
    """Positional-encoding frequencies applied to sample-to-point offsets."""
    c_hidden: PositiveInt = 256
    """Width of the hidden layers of MLP C (per-neighbour feature)."""
    c_layers: PositiveInt = 1
    """Number of hidden layers of MLP C."""
    c_out: PositiveInt | None = None
    """Width of C's output, the per-neighbour feature fed to G and U; null = c_hidden."""
    u_hidden: PositiveInt = 128
    """Width of the hidden layers of MLP U (colour decoder)."""
    u_layers: PositiveInt = 2
    """Number of hidden layers of MLP U."""
    g_hidden: PositiveInt = 256
    """Width of the hidden layers of MLP G (occupancy decoder)."""
    g_layers: PositiveInt = 1
    """Number of hidden layers of MLP G."""
    leaky_slope: float = Field(default=0.01, ge=0.0, lt=1.0)
    """Negative slope of the LeakyReLU activations."""
    neighbour_backend: Literal["auto", "kdtree", "torch"] = "auto"
    """Neighbour search: scipy k-d tree (CPU), pure torch grid (any device), or auto by device."""
    n_near: PositiveInt = 16
    """Samples per ray drawn uniformly in [near_lo * D, near_hi * D] around the measured depth D."""
    n_uniform: NonNegativeInt = 4
    """Samples per ray drawn uniformly in [near_lo * D_min, far_hi * D_max] of the batch."""
    near_lo: PositiveFloat = 0.95
    """Lower factor of the near band and of the uniform range."""
    near_hi: PositiveFloat = 1.05
    """Upper factor of the near band around the measured depth."""
    far_hi: PositiveFloat = 1.05
    """Upper factor on the batch's largest depth for the uniform samples."""
    no_depth_near: PositiveFloat = 0.001
    """Near bound D_l (m) for pixels without depth, sampled uniformly in [D_l, far_hi * D_max]."""
    chunk_rays: PositiveInt = 4096
    """Rays rendered per chunk; bounds peak memory of rendering."""
    prior: str | None = None
    """Start weights of decoders and feature CNN (.npz; bare name: bundled); null: from run.seed."""

    @model_validator(mode="after")
    def _check(self) -> FieldConfig:
        if self.near_lo >= self.near_hi:
            raise ValueError(f"near_lo ({self.near_lo}) must be below near_hi ({self.near_hi})")
        if self.far_hi < self.near_lo:
            raise ValueError(f"far_hi ({self.far_hi}) must not be below near_lo ({self.near_lo})")
        if self.prior is not None and not self.prior.endswith(".npz"):
            raise ValueError(f"prior must name an .npz file (or be null), got {self.prior!r}")
        return self

    @property
    def samples_per_ray(self) -> int:
        """Samples on every ray (N_near + N_uniform; all uniform for pixels without depth)."""
        return self.n_near + self.n_uniform


class TrackingConfig(Section):
    """Camera tracking against the rendered map."""

    method: Literal["adam", "lm"] = "adam"
    """Pose optimiser: Adam on the loss (the paper) or Levenberg-Marquardt (robust, converges)."""
    iters: PositiveInt = 100
    """Optimisation steps per frame, at most ("lm": solves; the paper does not state it)."""
    n_pixels: PositiveInt = 1500
    """Pixels sampled per step (M2)."""
    lr: PositiveFloat = 0.0015
    """Adam learning rate of the se(3) pose increment xi (T = T_init @ exp(xi), camera frame)."""
    lr_end_factor: float = Field(default=1.0, gt=0.0, le=1.0)
    """Exponential decay of the rate over a frame's steps to lr * this at the last (1 = none)."""
    pixel_sampling: Literal["uniform", "stratified"] = "uniform"
    """How a frame's pixels are drawn: independently (the paper) or one per cell of a grid."""
    init: Literal["zero_motion", "constant_velocity"] = "zero_motion"
    """Initial pose of a new frame: the previous pose (the paper) or a constant-velocity guess."""
    color_weight: NonNegativeFloat = 0.0
    """Weight of the colour term (adam: L1 of RGB; lm: normalised luminance) (0 = the paper)."""
    prior_sigma_t: PositiveFloat = 0.05
    """lm: sigma (m) of the prior holding the pose at its initial guess where data is silent."""
    prior_sigma_r: PositiveFloat = 0.05
    """lm: sigma (rad) of the prior holding the rotation at its initial guess."""
    reference_weight: NonNegativeFloat = 0.0
    """lm: weight of luminance and depth residuals against the latest keyframe (0 = off)."""
    reference_pixels: PositiveInt = 2000
    """lm: pixels of the frame compared with the latest keyframe."""
    previous_reference: float = Field(default=0.0, ge=0.0, le=1.0)
    """lm: weight of the previous frame's view (at its tracked pose) against the keyframe's."""
    relinearise_steps: NonNegativeInt | None = None
    """lm: accepted steps that get new Jacobians; later ones reuse them (null: every step)."""
    step_stretch: float = Field(default=1.0, ge=1.0, le=4.0)
    """lm: after a step that beat its model 1.5x, try the next this much longer first (1 = off)."""
    depth_iters: PositiveInt | None = None
    """lm with colour: solves of the depth-only phase before the luminance one (null: iters)."""
    n_near: PositiveInt | None = None
    """Samples per tracking ray around the measured depth (null: field.n_near)."""
    n_uniform: NonNegativeInt | None = None
    """Uniform samples per tracking ray (null: field.n_uniform)."""
    outlier_err_lo: NonNegativeFloat = 0.1
    """Pixels with depth error below this multiple of the median error are masked."""
    outlier_err_hi: PositiveFloat = 10.0
    """Pixels with depth error above this multiple of the median error are masked."""
    outlier_var_factor: PositiveFloat = 2.0
    """Pixels with depth variance above this multiple of the median variance are masked."""
    keep_best: bool = True
    """Keep the pose of the lowest-loss step rather than the last one."""
    early_stop_tol: NonNegativeFloat = 0.0
    """Stop when the relative loss change falls below this (0 disables early stopping)."""

    @model_validator(mode="after")
    def _check(self) -> TrackingConfig:
        if self.outlier_err_lo >= self.outlier_err_hi:
            raise ValueError(
                f"outlier_err_lo ({self.outlier_err_lo}) must be below "
                f"outlier_err_hi ({self.outlier_err_hi})"
            )
        return self


class RecoveryConfig(Section):
    """Tracking failure detection and recovery (the paper has none)."""

    enabled: bool = False
    """Check every tracked frame and re-track a suspect one from other initial guesses."""
    residual_jump: PositiveFloat = 3.0
    """Suspect when the median depth error exceeds this multiple of the recent frames' median."""
    min_inliers: float = Field(default=0.5, ge=0.0, le=1.0)
    """Suspect when the tracking loss kept less than this share of the frame's pixels."""
    max_jump_t: PositiveFloat = 0.05
    """Suspect when the pose is this far (m) from the motion model's prediction."""
    max_jump_r: PositiveFloat = 0.05
    """Suspect when the pose is rotated this much (rad) from the motion model's prediction."""
    window: PositiveInt = 20
    """Healthy frames whose median depth error sets the reference for residual_jump."""
    iters_factor: PositiveFloat = 2.0
    """Re-tracking runs this many times tracking.iters steps from each other guess."""
    geometric_guess: bool = True
    """Also re-track from a frame-to-frame RGB-D odometry estimate (Open3D, multi-scale)."""
    relocalise: bool = True
    """When every guess fails, register the frame against recent keyframes and track from there."""


class MappingConfig(Section):
    """Map optimisation: features and decoders.

    Every mapping call first adds points: the patch-centre pixels of the frame are back-projected
    and kept where the map does not explain them (no existing point within field.radius, or, when
    add_points_depth_err is set, a rendered depth error above it); the grid filter then keeps at
    most one point per field.grid_size cell.
    """

    every: PositiveInt = 10
    """Run mapping every this many frames."""
    n_pixels: PositiveInt = 3000
    """Pixels sampled per step over the current frame and co-visible keyframes (M1)."""
    n_pixels_first: PositiveInt = 3136
    """Pixels sampled per step when mapping the first frame (M3)."""
    iters_first: PositiveInt = 3000
    """Optimisation steps for the first frame."""
    lr_scale_first: PositiveFloat = 1.0
    """The first frame's call runs at this times lr_decoders and lr_features."""
    iters: PositiveInt = 200
    """Optimisation steps for every later mapping call."""
    iters_after_fusion: PositiveInt = 150
    """Steps re-fitting the map before the next track when the server changed map or decoders."""
    covisible_keyframes: NonNegativeInt = 5
    """Co-visible keyframes whose pixels join the current frame's in every mapping call."""
    lr_decoders: PositiveFloat = 0.003
    """Adam learning rate of the decoder MLPs."""
    lr_features: PositiveFloat = 0.005
    """Adam learning rate of the point features (before decay)."""
    feature_lr_decay: float = Field(default=0.1, gt=0.0, le=1.0)
    """Feature lr is lr_features * feature_lr_decay ** (step / feature_lr_decay_steps)."""
    feature_lr_decay_steps: PositiveInt = 10000
    """Steps over which the feature lr decays by feature_lr_decay; reset every mapping call."""
    color_weight: NonNegativeFloat = 0.2
    """Weight of the colour L1 term in the mapping loss (depth L1 has weight 1)."""
    add_points_depth_err: PositiveFloat | None = None
    """Add points where rendered depth errs by more than this (m); null = no point within radius."""
    pose_lr: NonNegativeFloat = 0.0
    """Adam rate refining a non-keyframe mapping frame's pose with the map (0 = keep tracked)."""
    pose_average: float = Field(default=0.5, ge=0.0, lt=1.0)
    """Refined pose: mean of the pose increments over this last share of steps (0 = last step's)."""
    max_pending_keyframes: PositiveInt = 2
    """Concurrent schedule: keyframes waiting for the mapping thread before tracking waits too."""
    first_publish_every: NonNegativeInt = 0
    """Concurrent schedule: publish the first call's map every this many steps (0 = at its end)."""


class KeyframesConfig(Section):
    """Keyframe selection and the stored keyframe images."""

    every: PositiveInt = 50
    """Make a keyframe every this many frames."""
    image_downscale: PositiveInt = 2
    """Stored keyframe RGB-D copies are this many times smaller per side."""
    jpeg_quality: int = Field(default=90, ge=1, le=100)
    """JPEG quality of the stored keyframe colour images."""

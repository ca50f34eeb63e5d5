"""The server's constructor arguments from a config: `registry_args` (the ``limits`` section,
for `Registry`) and `backend_args` (the whole config, for `Backend.from_config`).

Kept apart from the classes they configure: their signatures stay plain keyword arguments
(tests build them without a config), and which config field feeds which argument is read in
one place.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from cpslam.common.config import CpslamConfig, LimitsConfig
    from cpslam.common.field import FieldSpec

__all__ = ["backend_args", "registry_args"]


def registry_args(limits: LimitsConfig, descriptor_dim: int) -> dict[str, Any]:
    """`Registry`'s keyword arguments from the ``limits`` section (`descriptor_dim`: the
    length the place_recognition section gives, unless the section overrides it)."""
    return dict(
        descriptor_dim=limits.descriptor_dim or descriptor_dim,
        max_agents=limits.max_agents,
        max_pending_points=limits.max_pending_points,
        max_pending_frames=limits.max_pending_frames,
        max_seq_ahead=limits.max_seq_ahead,
        max_removed_per_message=limits.max_removed_per_message,
        max_tombstones=limits.max_tombstones,
        max_translation_m=limits.max_translation_m,
        max_federated_samples=limits.max_federated_samples,
        max_counter_keys=limits.max_counter_keys,
        max_keyframes_per_agent=limits.max_keyframes_per_agent,
        max_points_per_agent=limits.max_points_per_agent,
    )


def backend_args(cfg: CpslamConfig) -> tuple[FieldSpec, dict[str, Any]]:
    """The neural field's spec and `Backend`'s keyword arguments from a whole config (all but
    the config sections it takes whole and ``fetch_image``)."""
    from cpslam.common.field_config import field_spec
    from cpslam.common.place_recognition import descriptor_dim

    spec = field_spec(cfg.field)
    dim = cfg.limits.descriptor_dim or descriptor_dim(cfg.place_recognition)
    return spec, {
        "registry_args": registry_args(cfg.limits, dim),
        "image_cache_bytes": int(cfg.limits.image_cache_mb * 2**20),
        "seed": cfg.run.seed,
        "decoders_factory": lambda: spec.decoders(cfg.run.seed),
        "finetune_lr": cfg.mapping.lr_decoders,
        "finetune_lr_features": cfg.mapping.lr_features,
        "color_weight": cfg.mapping.color_weight,
        "update_resend_after_s": cfg.transport.resend_after_s,
        "update_max_points": cfg.transport.update_max_points,
    }

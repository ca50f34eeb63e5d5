"""Field specs and settings for unit tests: a preset's sections with a test's own values."""

from __future__ import annotations

from dataclasses import replace
from functools import cache

from cpslam.common.config import CpslamConfig, load_config
from cpslam.common.field import FieldSpec
from cpslam.common.field_config import field_spec, mapper_args_from_config, tracker_args_from_config


@cache
def _config(preset: str) -> CpslamConfig:
    return load_config(preset, env={})  # frozen: safe to share between tests


def spec(preset: str = "gpu", **changes: object) -> FieldSpec:
    """The preset's field spec (default `gpu`: the schema defaults) with `changes`."""
    return replace(field_spec(_config(preset).field), **changes)


def tracker_args(preset: str = "gpu", **changes: object) -> dict:
    """`Tracker` keywords from the preset's `tracking` section, with `changes`."""
    return {**tracker_args_from_config(_config(preset).tracking), **changes}


def mapper_args(preset: str = "gpu", **changes: object) -> dict:
    """`Mapper` keywords from the preset's `mapping` section, with `changes`."""
    return {**mapper_args_from_config(_config(preset).mapping), **changes}


def finetune_args(preset: str = "gpu", **changes: object) -> dict:
    """`Backend`'s fine-tune keywords (the `mapping` section's rates, the run's seed)."""
    cfg = _config(preset)
    return {"finetune_lr": cfg.mapping.lr_decoders, "finetune_lr_features": cfg.mapping.lr_features,
            "color_weight": cfg.mapping.color_weight, "seed": cfg.run.seed, **changes}

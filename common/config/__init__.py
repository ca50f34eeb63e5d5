"""The configuration tree of cpslam and how it is loaded.

`load_config(preset, config_file, overrides, env)` merges preset -> YAML file -> environment
(`CPSLAM_<SECTION>__<FIELD>`) -> `--set section.field=value` and validates once into a frozen
`CpslamConfig`. See docs/configuration.md for every field.
"""

from cpslam.common.config.loader import (
    ConfigError,
    available_presets,
    config_from_cli,
    config_to_dict,
    load_config,
    load_config_file,
    override_config,
    preset_text,
    save_config,
)
from cpslam.common.config.reference import config_reference_markdown
from cpslam.common.config.schema import (
    CameraConfig,
    CpslamConfig,
    FederationConfig,
    FieldConfig,
    KeyframesConfig,
    LimitsConfig,
    LinkConfig,
    LoopConfig,
    MappingConfig,
    PlaceRecognitionConfig,
    PoseGraphConfig,
    RecoveryConfig,
    RefinementConfig,
    RunConfig,
    TrackingConfig,
    TransportConfig,
)

__all__ = [
    "CameraConfig",
    "ConfigError",
    "CpslamConfig",
    "FederationConfig",
    "FieldConfig",
    "KeyframesConfig",
    "LimitsConfig",
    "LoopConfig",
    "MappingConfig",
    "PlaceRecognitionConfig",
    "PoseGraphConfig",
    "RecoveryConfig",
    "RefinementConfig",
    "RunConfig",
    "TrackingConfig",
    "LinkConfig",
    "TransportConfig",
    "available_presets",
    "config_from_cli",
    "config_reference_markdown",
    "config_to_dict",
    "load_config",
    "load_config_file",
    "override_config",
    "preset_text",
    "save_config",
]

"""The configuration tree: one frozen pydantic model per part of the system.

Defaults: the paper's model with this project's choices (docs/configuration.md, Paper vs
default; the `paper` preset is the paper as written). Every field's attribute docstring is its
description; `config_reference_markdown()` turns them into docs/configuration.md, so the dotted
field names here are the public `--set section.field=value` surface — rename with care.
"""

from __future__ import annotations

from cpslam.common.config.base import Section
from cpslam.common.config.collab import (
    FederationConfig,
    LoopConfig,
    PlaceRecognitionConfig,
    PoseGraphConfig,
    RefinementConfig,
)
from cpslam.common.config.limits import LimitsConfig
from cpslam.common.config.runtime import LinkConfig, RunConfig, TransportConfig
from cpslam.common.config.slam import (
    CameraConfig,
    FieldConfig,
    KeyframesConfig,
    MappingConfig,
    RecoveryConfig,
    TrackingConfig,
)

__all__ = [
    "CameraConfig",
    "CpslamConfig",
    "FederationConfig",
    "FieldConfig",
    "KeyframesConfig",
    "LimitsConfig",
    "LinkConfig",
    "LoopConfig",
    "MappingConfig",
    "PlaceRecognitionConfig",
    "PoseGraphConfig",
    "RecoveryConfig",
    "RefinementConfig",
    "RunConfig",
    "TrackingConfig",
    "TransportConfig",
]


class CpslamConfig(Section):
    """Everything a cpslam agent or server reads, one section per part of the system."""

    camera: CameraConfig = CameraConfig()
    """Camera intrinsics override and depth handling."""
    field: FieldConfig = FieldConfig()
    """The neural point field: points, features, decoders and ray sampling."""
    tracking: TrackingConfig = TrackingConfig()
    """Camera tracking against the rendered map."""
    recovery: RecoveryConfig = RecoveryConfig()
    """Tracking failure detection and recovery (the paper has none)."""
    mapping: MappingConfig = MappingConfig()
    """Map optimisation: features and decoders."""
    keyframes: KeyframesConfig = KeyframesConfig()
    """Keyframe selection and the stored keyframe images."""
    place_recognition: PlaceRecognitionConfig = PlaceRecognitionConfig()
    """Global image descriptors for loop detection."""
    loop: LoopConfig = LoopConfig()
    """Loop detection, verification and relative pose estimation."""
    federation: FederationConfig = FederationConfig()
    """Federated averaging of the decoders of a group of agents."""
    pose_graph: PoseGraphConfig = PoseGraphConfig()
    """Pose-graph optimisation over sequential and loop edges."""
    refinement: RefinementConfig = RefinementConfig()
    """Map refinement after a pose-graph correction."""
    transport: TransportConfig = TransportConfig()
    """The message bus between agents and server."""
    limits: LimitsConfig = LimitsConfig()
    """Caps on peer-keyed state and plausibility bounds of agents' messages."""
    link: LinkConfig = LinkConfig()
    """What agents send the server and how compactly: sub-map deltas, decoders, compression."""
    run: RunConfig = RunConfig()
    """Process-level settings: output, device, seeds, logging."""

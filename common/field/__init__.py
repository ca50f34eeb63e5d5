"""The neural point field: points with learnable features, decoders, sampler and renderer.

Shared by agents (tracking, mapping) and the server (relative pose by rendering, fine-tuning
after fusion). Only torch, numpy and scipy are used here, so the package runs unchanged on a
GPU machine that has nothing else installed.
"""

from cpslam.common.field.decoders import Decoders, FeatureCNN
from cpslam.common.field.encoding import encoded_dim, positional_encoding
from cpslam.common.field.patches import patch_points
from cpslam.common.field.points import NeuralPointMap
from cpslam.common.field.renderer import camera_rays, render_image, render_rays, render_samples
from cpslam.common.field.sampler import RaySampler
from cpslam.common.field.search import NeighbourIndex
from cpslam.common.field.spec import FieldSpec

__all__ = [
    "Decoders",
    "FeatureCNN",
    "FieldSpec",
    "NeighbourIndex",
    "NeuralPointMap",
    "RaySampler",
    "camera_rays",
    "encoded_dim",
    "patch_points",
    "positional_encoding",
    "render_image",
    "render_rays",
    "render_samples",
]

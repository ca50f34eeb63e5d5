"""The length of a keyframe descriptor as the `place_recognition` section fixes it.

The server checks every keyframe's descriptor against this length (`limits.descriptor_dim`
overrides it), so it never learns the length from whichever agent speaks first. The agent's
`DescriptorExtractor` computes descriptors of exactly this length (a test holds them equal);
no torch model is built here, so the server pays nothing for it.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from cpslam.common.config.collab import PlaceRecognitionConfig

__all__ = ["DEFAULT_LAYER", "LAYER_CHANNELS", "MAX_DIM", "descriptor_dim"]

DEFAULT_LAYER = "stage6"
"""Backbone feature map used by default (192 channels at stride 32), chosen by measured recall
(docs/place_recognition.md)."""
MAX_DIM = 4096
"""Descriptors longer than this are reduced by a seeded count sketch."""
LAYER_CHANNELS = {"stage4": 80, "stage5": 112, "stage6": 192, "stage7": 320, "head": 1280}
"""Channels of each EfficientNet-Lite0 feature map a descriptor may pool."""


def descriptor_dim(cfg: PlaceRecognitionConfig) -> int:
    """Descriptor length D of the section: with a weights file, what the file sets (a
    projection's rows, a sketch's width, NetVLAD's clusters), else K * C of the layer for
    NetVLAD (count-sketched to MAX_DIM when longer) or C for GeM."""
    layer = cfg.layer
    clusters = cfg.clusters
    if cfg.weights is not None:
        params = _read_weights(Path(cfg.weights))
        if "pca.weight" in params:
            return int(params["pca.weight"].shape[0])
        if "sketch.dim" in params:
            return int(params["sketch.dim"])
        if "layer" in params:
            layer = str(params["layer"])
        if cfg.aggregation == "netvlad" and "centroids" in params:
            clusters = int(params["centroids"].shape[0])
    channels = LAYER_CHANNELS[layer or DEFAULT_LAYER]
    raw = clusters * channels if cfg.aggregation == "netvlad" else channels
    return min(raw, MAX_DIM)


def _read_weights(path: Path) -> dict[str, np.ndarray]:
    try:
        if path.suffix == ".npz":
            with np.load(path, allow_pickle=False) as data:
                return {k: np.asarray(data[k]) for k in data.files}
        import torch

        raw = torch.load(path, map_location="cpu", weights_only=True)
        return {k: np.asarray(v) for k, v in raw.items()}
    except Exception as err:
        raise ValueError(
            f"{path}: cannot read place recognition weights to find the "
            f"descriptor length ({err}); set limits.descriptor_dim"
        ) from err

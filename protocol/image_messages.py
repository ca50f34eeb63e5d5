"""Keyframe image messages: the server's request for a keyframe's RGB-D and the agent's reply.

The images themselves travel as {"codec", "data"} maps (`cpslam.protocol.images`), checked
against the declared width and height before they are decoded.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

import numpy as np
from pydantic import Field, model_serializer, model_validator
from pydantic_core import core_schema

from cpslam.protocol.arrays import ArraySpec
from cpslam.protocol.base import Id, KfId, Message
from cpslam.protocol.images import image_from_wire, image_to_wire

__all__ = ["KeyframeImage", "KeyframeImageRequest"]

MB = 1 << 20
MAX_IMAGE_SIDE = 4096


class KeyframeImageRequest(Message):
    """The server's query for a keyframe's images (payload of a get on the image key)."""

    max_bytes = 4096
    type: Literal["keyframe_image_request"] = "keyframe_image_request"
    agent_id: Id
    """Agent that owns the keyframe."""
    kf_id: KfId
    """Keyframe wanted."""
    want_rgb: bool = True
    """Send the colour image."""
    want_depth: bool = True
    """Send the depth image."""
    scale: float = Field(default=1.0, ge=0.1, le=1.0)
    """Fraction of the processed frame's width and height wanted (1: the processed size)."""

    @model_validator(mode="after")
    def _check(self) -> KeyframeImageRequest:
        if not (self.want_rgb or self.want_depth):
            raise ValueError("want_rgb/want_depth: at least one must be true")
        return self


class _Image:
    """Annotation for an image field: decoded from {"codec", "data"} with the declared size."""

    def __init__(self, kind: Literal["rgb", "depth"]) -> None:
        self.kind = kind
        self.spec = (
            ArraySpec("uint8", ("H", "W", 3)) if kind == "rgb" else ArraySpec("uint16", ("H", "W"))
        )

    def __get_pydantic_core_schema__(self, source: Any, handler: Any) -> core_schema.CoreSchema:
        return core_schema.with_info_plain_validator_function(self.validate)

    def validate(self, value: Any, info: core_schema.ValidationInfo) -> np.ndarray:
        if isinstance(value, dict) and "codec" in value:
            if "width" not in info.data or "height" not in info.data:
                raise ValueError("cannot check the image without a valid width and height")
            field = f"{self.kind}_codec"
            declared = info.data.get(field)
            if value["codec"] != declared:
                raise ValueError(f"codec {value['codec']!r:.20} differs from {field} {declared!r}")
            return image_from_wire(value, self.kind, info.data["width"], info.data["height"])
        if isinstance(value, dict):
            raise ValueError("expected an image map with keys codec/data")
        return self.spec.validate(value)


class KeyframeImage(Message):
    """A keyframe's colour and/or depth image with its intrinsics (reply to the request).

    Colour is RGB in memory and PNG (lossless) or JPEG on the wire; depth is uint16, PNG or
    zstd-delta (both lossless), 0 = invalid, and either linear (value / depth_scale metres)
    or inverse (depth_scale / value metres: steps that grow as depth², and planes whose values
    change linearly across the image, which a predictor stores in few bytes). `from_metres` and
    `depth_metres` convert to and from float32 metres.
    """

    max_bytes = 8 * MB
    type: Literal["keyframe_image"] = "keyframe_image"
    agent_id: Id
    """Agent that owns the keyframe."""
    kf_id: KfId
    """Keyframe id."""
    fx: float = Field(gt=0)
    """Focal length along x (pixels)."""
    fy: float = Field(gt=0)
    """Focal length along y (pixels)."""
    cx: float
    """Principal point x (pixels)."""
    cy: float
    """Principal point y (pixels)."""
    width: int = Field(ge=1, le=MAX_IMAGE_SIDE)
    """Image width W (pixels)."""
    height: int = Field(ge=1, le=MAX_IMAGE_SIDE)
    """Image height H (pixels)."""
    depth_scale: float = Field(default=1000.0, gt=0)
    """Linear depth: units per metre (1000 = millimetres); inverse: value x depth in metres."""
    depth_encoding: Literal["linear", "inverse"] = "linear"
    """How a depth value maps to metres: value / depth_scale, or depth_scale / value."""
    rgb_codec: Literal["png", "jpeg"] = "jpeg"
    """How `rgb` is compressed on the wire."""
    jpeg_quality: int = Field(default=90, ge=1, le=100)
    """JPEG quality used when rgb_codec is jpeg."""
    depth_codec: Literal["png", "zstd-delta"] = "zstd-delta"
    """How `depth` is compressed on the wire (both lossless; zstd-delta a quarter smaller)."""
    rgb: Annotated[np.ndarray, _Image("rgb")] | None = None
    """Colour image, RGB (uint8 [H, W, 3]); None when not requested."""
    depth: Annotated[np.ndarray, _Image("depth")] | None = None
    """Depth image as `depth_encoding` says, 0 = invalid (uint16 [H, W]); None: not requested."""

    @model_validator(mode="after")
    def _check(self) -> KeyframeImage:
        if self.rgb is None and self.depth is None:
            raise ValueError("rgb/depth: at least one image is required")
        for name, image in (("rgb", self.rgb), ("depth", self.depth)):
            if image is not None and image.shape[:2] != (self.height, self.width):
                raise ValueError(
                    f"{name}: shape {list(image.shape)} does not match height x width "
                    f"{self.height} x {self.width}"
                )
        return self

    @model_serializer(mode="wrap")
    def _serialize(self, handler: Any) -> dict[str, Any]:
        wire = handler(self)
        if self.rgb is not None:
            wire["rgb"] = image_to_wire(self.rgb, "rgb", self.rgb_codec, self.jpeg_quality)
        if self.depth is not None:
            wire["depth"] = image_to_wire(self.depth, "depth", self.depth_codec)
        return wire

    @classmethod
    def from_metres(
        cls,
        depth_m: np.ndarray | None,
        depth_scale: float = 1000.0,
        depth_encoding: Literal["linear", "inverse"] = "linear",
        **fields: Any,
    ) -> KeyframeImage:
        """Build from float32 metric depth (0 or non-finite = invalid); other fields as kwargs.

        Depths the uint16 range cannot hold (linear: beyond 65535 / depth_scale m; inverse:
        nearer than depth_scale / 65535 m or beyond 2 x depth_scale m) become 0 (invalid)
        rather than being clipped to a wrong value.
        """
        depth = None
        if depth_m is not None:
            z = np.nan_to_num(np.asarray(depth_m, np.float64), nan=0.0, posinf=0.0, neginf=0.0)
            if depth_encoding == "inverse":
                scaled = np.where(z > 0, depth_scale / np.where(z > 0, z, 1.0), 0.0)
            else:
                scaled = z * depth_scale
            scaled = np.rint(scaled)
            scaled[(scaled < 0) | (scaled > np.iinfo(np.uint16).max)] = 0
            depth = scaled.astype(np.uint16)
        return cls(depth=depth, depth_scale=depth_scale, depth_encoding=depth_encoding, **fields)

    def depth_metres(self) -> np.ndarray | None:
        """Depth as float32 metres [H, W] (0 = invalid, as is any depth float32 cannot hold),
        or None if absent."""
        if self.depth is None:
            return None
        value = self.depth.astype(np.float64)
        if self.depth_encoding == "inverse":
            z = np.where(value > 0, self.depth_scale / np.maximum(value, 1.0), 0.0)
        else:
            z = value / self.depth_scale
        with np.errstate(over="ignore"):
            z = z.astype(np.float32)
        return np.where(np.isfinite(z), z, np.float32(0.0))

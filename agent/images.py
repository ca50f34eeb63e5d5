"""An agent's answer to the server's keyframe image request: the keyframe's RGB-D at the size
the request asks for, in its wire form.

The server verifies loops and fine-tunes decoders on these images; a request's ``scale`` below
1 asks for a smaller copy (colour area-averaged, depth resampled without mixing an edge's two
sides, intrinsics scaled to match), which cuts the image bytes by about the square of it.
"""

from __future__ import annotations

import numpy as np

from cpslam.common.camera import Intrinsics, resize_rgbd
from cpslam.protocol import KeyframeImage, KeyframeImageRequest
from cpslam.protocol.images import depth_coding

__all__ = ["image_reply", "rescale_reply"]


def image_reply(request: KeyframeImageRequest, rgb: np.ndarray, depth_m: np.ndarray,
                intr: Intrinsics, rgb_codec: str = "jpeg", jpeg_quality: int = 90,
                depth_step_mm_per_m2: float = 0.0) -> KeyframeImage:
    """The reply to `request` from a keyframe's RGB uint8 [H, W, 3] and depth float32 [H, W]
    (m) with camera `intr`: resized by ``request.scale``, depth as inverse depth in steps of
    `depth_step_mm_per_m2` x z² mm, or at 0 in millimetres (`depth_coding`), only what it
    wants."""
    if request.scale < 1.0:
        rgb, depth_m = resize_rgbd(rgb, depth_m, request.scale)
        intr = intr.scaled(request.scale)
    depth_scale, depth_encoding = depth_coding(depth_step_mm_per_m2)
    return KeyframeImage.from_metres(
        depth_m if request.want_depth else None, depth_scale, depth_encoding,
        agent_id=request.agent_id, kf_id=request.kf_id, fx=intr.fx, fy=intr.fy, cx=intr.cx,
        cy=intr.cy, width=intr.width, height=intr.height, rgb_codec=rgb_codec,
        jpeg_quality=jpeg_quality, rgb=rgb if request.want_rgb else None)


def rescale_reply(image: KeyframeImage, request: KeyframeImageRequest) -> KeyframeImage:
    """A stored full reply (both images) answered again for `request`, as `image_reply` would
    have answered it from the keyframe's own images (in the stored reply's depth coding)."""
    if image.rgb is None or image.depth is None:
        raise ValueError(f"keyframe image {image.agent_id}/{image.kf_id}: a stored reply needs "
                         "both colour and depth")
    intr = Intrinsics(image.fx, image.fy, image.cx, image.cy, image.width, image.height)
    step = 1000.0 / image.depth_scale if image.depth_encoding == "inverse" else 0.0
    return image_reply(request, image.rgb, image.depth_metres(), intr, image.rgb_codec,
                       image.jpeg_quality, step)

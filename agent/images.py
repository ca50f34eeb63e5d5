"""An agent's answer to the server's keyframe image request: the keyframe's RGB-D at the size
the request asks for, in its wire form.

The server verifies loops and fine-tunes decoders on these images; a request's ``scale`` below
1 asks for a smaller copy (colour area-averaged, depth resampled without mixing an edge's two
sides, intrinsics scaled to match), which cuts the image bytes by about the square of it.
`ImageReplies` answers smaller still when the agent's depth is noisy: registration on noisy
depth is limited by the noise, which resampling averages, not by the pixel count (a reply
states its own size and intrinsics, so the server takes it as it comes). It also coarsens the
depth's steps to a fraction of the measured noise: finer steps only spend bits on the noise,
which no lossless codec can compress; a smaller reply's resampling averages the noise, and
its steps shrink with it.
"""

from __future__ import annotations

from collections import OrderedDict

import numpy as np

from cpslam.common.camera import Intrinsics, depth_noise, resize_rgbd
from cpslam.protocol import KeyframeImage, KeyframeImageRequest
from cpslam.protocol.images import depth_coding

__all__ = ["ImageReplies", "image_reply", "rescale_reply"]

NOISE_WINDOW = 64
"""Keyframes whose depth noise `ImageReplies` keeps (their median decides)."""

MAX_NOISE_STEP = 1.5
"""Coarsest inverse-depth step (mm/m²) the measured noise sets. Quantised inverse depth is
no extra noise but contours: at 3 mm/m² the loop edges of the noisy synthetic apartment
(noise 1.5 mm/m²) were 1.65 times worse at the median and 5.6 times at the 90th percentile
than at 0.5, at 1.5 1.14 and 1.4 times (`loop-edges-synthetic-wire*`)."""


class ImageReplies:
    """How an agent answers the server's keyframe image requests.

    Args:
        rgb_codec, jpeg_quality: how the colour is compressed.
        depth_codec: how the depth is compressed (lossless: png or zstd-delta).
        depth_step_mm_per_m2: depth as inverse depth in steps of this x z² mm; 0: mm.
        noisy_scale: the largest scale of a reply while the agent's depth is noisy and it
            has merged with another agent (1: as asked).
        noisy_depth_mm_per_m2: depth is noisy when the median `depth_noise` of the last
            `NOISE_WINDOW` keyframes answered reaches this.
        step_noise_ratio: the inverse-depth step is at least this x that median noise (at
            most `MAX_NOISE_STEP`); 0 keeps `depth_step_mm_per_m2` (and millimetres stay
            millimetres). Noise is measured only where this or `noisy_scale` needs it.
    """

    def __init__(self, rgb_codec: str = "jpeg", jpeg_quality: int = 90,
                 depth_step_mm_per_m2: float = 0.5, noisy_scale: float = 1.0,
                 noisy_depth_mm_per_m2: float = 0.3, step_noise_ratio: float = 2.0,
                 depth_codec: str = "zstd-delta") -> None:
        if not 0.0 < noisy_scale <= 1.0:
            raise ValueError(f"ImageReplies: noisy_scale must be in (0, 1], got {noisy_scale}")
        if step_noise_ratio < 0.0:
            raise ValueError(f"ImageReplies: step_noise_ratio must be >= 0, got {step_noise_ratio}")
        self.step_noise_ratio = step_noise_ratio if depth_step_mm_per_m2 > 0 else 0.0
        self.rgb_codec, self.jpeg_quality, self.depth_codec = rgb_codec, jpeg_quality, depth_codec
        self.depth_step_mm_per_m2 = depth_step_mm_per_m2
        self.noisy_scale, self.noisy_depth_mm_per_m2 = noisy_scale, noisy_depth_mm_per_m2
        self.noise: OrderedDict[int, float] = OrderedDict()
        """`depth_noise` (mm/m²) of the last `NOISE_WINDOW` keyframes answered, by keyframe id,
        oldest first (a keyframe answered again counts once)."""

    @property
    def noisy(self) -> bool:
        """Whether the depth of the keyframes answered so far is noisy."""
        return bool(self.noise) and self._median() >= self.noisy_depth_mm_per_m2

    def depth_step(self, scale: float = 1.0) -> float:
        """The inverse-depth step (mm/m²) of the next reply at `scale` of the processed size:
        `depth_step_mm_per_m2`, coarser where `step_noise_ratio` x the median noise x `scale`
        is. Resampling to half size averages four pixels, which halves the noise; at other
        scales it averages fewer, so the step is finer than the noise asks (never coarser)."""
        step = self.depth_step_mm_per_m2
        if self.step_noise_ratio > 0 and self.noise:
            noise_step = self.step_noise_ratio * self._median() * min(scale, 1.0)
            step = max(step, min(MAX_NOISE_STEP, noise_step))
        return step

    def _median(self) -> float:
        return float(np.median(list(self.noise.values())))

    def answer(self, request: KeyframeImageRequest, rgb: np.ndarray, depth_m: np.ndarray,
               intr: Intrinsics, merged: bool = True) -> KeyframeImage:
        """`image_reply` to `request`, in the `depth_step` that the noise measured so far (this
        keyframe's included) sets; at most `noisy_scale` of the size while depth is noisy and
        the agent has `merged` with another. Before that its loop candidates with other
        agents have no pose to start from: registering them takes matching features, which
        half-size noisy depth does not give (9 of 45 failed on a noisy apartment)."""
        if self.noisy_scale < 1.0 or self.step_noise_ratio > 0:
            if request.kf_id not in self.noise:
                self.noise[request.kf_id] = depth_noise(depth_m)
                while len(self.noise) > NOISE_WINDOW:
                    self.noise.popitem(last=False)
        if (merged and self.noisy_scale < 1.0 and self.noisy
                and request.scale > self.noisy_scale):
            request = request.model_copy(update={"scale": self.noisy_scale})
        return image_reply(request, rgb, depth_m, intr, self.rgb_codec, self.jpeg_quality,
                           self.depth_step(request.scale), self.depth_codec)


def image_reply(request: KeyframeImageRequest, rgb: np.ndarray, depth_m: np.ndarray,
                intr: Intrinsics, rgb_codec: str = "jpeg", jpeg_quality: int = 90,
                depth_step_mm_per_m2: float = 0.0, depth_codec: str = "zstd-delta"
                ) -> KeyframeImage:
    """The reply to `request` from a keyframe's RGB uint8 [H, W, 3] and depth float32 [H, W]
    (m) with camera `intr`: resized by ``request.scale``, depth as inverse depth in steps of
    `depth_step_mm_per_m2` x z² mm, or at 0 in millimetres (`depth_coding`), compressed by
    `depth_codec`, only what it wants."""
    if request.scale < 1.0:
        rgb, depth_m = resize_rgbd(rgb, depth_m, request.scale)
        intr = intr.scaled(request.scale)
    depth_scale, depth_encoding = depth_coding(depth_step_mm_per_m2)
    return KeyframeImage.from_metres(
        depth_m if request.want_depth else None, depth_scale, depth_encoding,
        agent_id=request.agent_id, kf_id=request.kf_id, fx=intr.fx, fy=intr.fy, cx=intr.cx,
        cy=intr.cy, width=intr.width, height=intr.height, rgb_codec=rgb_codec,
        jpeg_quality=jpeg_quality, depth_codec=depth_codec,
        rgb=rgb if request.want_rgb else None)


def rescale_reply(image: KeyframeImage, request: KeyframeImageRequest) -> KeyframeImage:
    """A stored full reply (both images) answered again for `request`, as `image_reply` would
    have answered it from the keyframe's own images (in the stored reply's depth coding)."""
    if image.rgb is None or image.depth is None:
        raise ValueError(f"keyframe image {image.agent_id}/{image.kf_id}: a stored reply needs "
                         "both colour and depth")
    intr = Intrinsics.of(image)
    step = 1000.0 / image.depth_scale if image.depth_encoding == "inverse" else 0.0
    return image_reply(request, image.rgb, image.depth_metres(), intr, image.rgb_codec,
                       image.jpeg_quality, step, image.depth_codec)

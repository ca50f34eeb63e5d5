"""Geometric registration of a loop candidate's two keyframe images: the coarse stage of the
loop pose (the RANSAC/ICP mathematics is `cpslam.common.registration` and
`cpslam.common.icp`).

With ``loop.coarse_method`` "none" (the paper) there is no coarse stage: keyframe a starts at
b's pose (the identity relative pose), which is verified as it is, and only the rendering
refinement (`cpslam.server.loops.refinement`) moves it.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from cpslam.common.camera import Intrinsics

if TYPE_CHECKING:
    from cpslam.common.config.collab import LoopConfig
    from cpslam.protocol import KeyframeImage

__all__ = ["coarse_register", "keyframe_rgbd"]


def coarse_register(loop: LoopConfig, seed: int) -> Callable[[KeyframeImage, KeyframeImage], Any]:
    """``(src_image_b, dst_image_a) -> Registration`` with the ``loop`` section's settings
    (`register_rgbd`, or the identity verified with ``coarse_method`` "none")."""
    def register(src: KeyframeImage, dst: KeyframeImage) -> Any:
        from cpslam.common.registration import RegistrationParams, register_rgbd, verify

        params = RegistrationParams.from_config(loop, seed)
        if loop.coarse_method == "none":
            # The paper: no coarse stage, the loop keyframe starts at the other keyframe's
            # pose (identity relative pose) and only the rendering refinement moves it.
            result = verify(keyframe_rgbd(src), keyframe_rgbd(dst), Intrinsics.of(src),
                            np.eye(4), params, dst_intrinsics=Intrinsics.of(dst))
            result.method = "identity"
            return result
        return register_rgbd(keyframe_rgbd(src), keyframe_rgbd(dst), Intrinsics.of(src),
                             params, dst_intrinsics=Intrinsics.of(dst))

    return register


def keyframe_rgbd(img: KeyframeImage) -> tuple[np.ndarray, np.ndarray]:
    """RGB uint8 [H, W, 3] (black when the image has none) and depth float32 [H, W] (m)."""
    depth = img.depth_metres()
    if depth is None:
        raise ValueError(f"keyframe image {img.agent_id}/{img.kf_id} has no depth")
    rgb = img.rgb if img.rgb is not None else np.zeros((*depth.shape, 3), np.uint8)
    return rgb, depth

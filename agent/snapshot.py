"""What the odometry keeps across a restart (`Odometry.state_dict`): its map, decoders,
keyframes, frames and counters as plain tensors, numbers, strings, lists and dicts (loadable
with ``torch.load(weights_only=True)``), and their restore. A part of the odometry split out
for size: it reads the odometry whole.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import torch

from cpslam.agent.recovery import Frame
from cpslam.common.camera import Intrinsics

if TYPE_CHECKING:
    from cpslam.agent.odometry import Odometry

__all__ = ["FORMAT_VERSION", "odometry_state", "restore_odometry"]

FORMAT_VERSION = 1


def odometry_state(odo: Odometry) -> dict:
    """Everything needed to render or resume; waits for the mapping thread."""
    odo.drain()
    return {
        "format_version": FORMAT_VERSION,
        "agent_id": odo.agent_id,
        "seed": odo.seed,
        "intrinsics": odo.intrinsics.to_dict(),
        "point_map": odo.maps.work.point_map.state_dict(),
        "decoders": {k: v.detach().cpu().clone() for k, v in
                     odo.maps.work.decoders.state_dict().items()},
        "keyframes": odo.keyframes.state_dict(),
        **odo.frames.state_dict(),
        "n_frames": odo.n_frames,
        "fused": odo.fused,
        "last_keyframe_count": -1 if odo._last_kf_count is None else odo._last_kf_count,
        "last_mapping_count": -1 if odo._last_map_count is None else odo._last_map_count,
        **({"recovery": odo.recovery.state_dict()} if odo.recovery is not None else {}),
        **({"last_tracked": _frame_state(odo._last_tracked)}
           if odo._last_tracked is not None else {}),
    }


def restore_odometry(odo: Odometry, state: dict) -> None:
    """Load an `odometry_state` into `odo` (same config and processing resolution)."""
    if int(state.get("format_version", -1)) != FORMAT_VERSION:
        raise ValueError(f"odometry state: format_version {state.get('format_version')}, "
                         f"expected {FORMAT_VERSION}")
    intrinsics = Intrinsics.from_dict(state["intrinsics"])
    if intrinsics != odo.intrinsics:
        raise ValueError(f"odometry state: saved at {intrinsics}, this odometry works at "
                         f"{odo.intrinsics}")
    odo.drain()
    odo.maps.work.point_map.load_state_dict(state["point_map"],
                                            source="odometry state point_map")
    odo.maps.work.decoders.load_state_dict(state["decoders"])
    odo.maps.republish()
    odo.keyframes.load_state_dict(state["keyframes"], source="odometry state keyframes")
    odo.frames.load_state_dict(state, int(state["n_frames"]))
    odo.seed = int(state["seed"])
    odo.agent_id = int(state["agent_id"])
    odo.fused = bool(state["fused"])
    n = len(odo.frames)
    # States written before the counters existed made both on multiples of the period.
    last_kf = int(state.get("last_keyframe_count", (n - 1) // odo.kf_every * odo.kf_every))
    last_map = int(state.get("last_mapping_count", (n - 1) // odo.map_every * odo.map_every))
    odo._last_kf_count = None if last_kf < 0 or n == 0 else last_kf
    odo._last_map_count = None if last_map < 0 or n == 0 else last_map
    odo._reference = None
    latest = odo.keyframes.latest
    if latest is not None and len(latest.rgb_png):  # the comparison resumes at once
        odo._set_reference(latest.kf_id)
    if odo.recovery is not None and "recovery" in state:
        odo.recovery.load_state_dict(state["recovery"])
    # The view tracking.previous_reference compares the next frame with, and where the
    # recovery's RGB-D odometry starts (states written before it had none: both wait a frame).
    odo._last_tracked = _frame(state["last_tracked"], odo) if "last_tracked" in state else None


def _frame_state(frame: Frame) -> dict:
    return {"index": int(frame.index), "rgb": torch.from_numpy(frame.rgb.copy()),
            "depth": torch.from_numpy(frame.depth.copy())}


def _frame(state: dict, odo: Odometry) -> Frame:
    rgb = state["rgb"].cpu().numpy().astype(np.uint8)
    depth = state["depth"].cpu().numpy().astype(np.float32)
    if rgb.shape != (*odo.intrinsics.shape, 3) or depth.shape != odo.intrinsics.shape:
        raise ValueError(f"odometry state: last_tracked is {rgb.shape} / {depth.shape}, "
                         f"expected {odo.intrinsics.shape} images")
    return Frame.from_arrays(state["index"], rgb, depth, odo.device)

"""RGB-D sequence loaders: Replica (NICE-SLAM / CP-SLAM layout), TUM RGB-D, 7-Scenes, ScanNet,
ROS 1 / ROS 2 bags and MCAP files.

    seq = open_sequence("data/Replica/room0", frames="0:500")
    for frame in seq:  # RGBDFrame: rgb uint8 [H, W, 3], depth float32 metres [H, W]
        ...

Ground truth (`RGBDFrame.gt_pose`, `RGBDSequence.gt_poses()`) is for evaluation only.
See docs/datasets.md for layouts, depth scales and where intrinsics come from.
"""

from cpslam.common.datasets.base import (
    DatasetError,
    RGBDFrame,
    RGBDSequence,
    parse_frames,
)
from cpslam.common.datasets.detect import FORMATS, detect_format, open_sequence
from cpslam.common.datasets.sidecar import SIDECAR_NAME, Sidecar

__all__ = [
    "FORMATS",
    "SIDECAR_NAME",
    "DatasetError",
    "RGBDFrame",
    "RGBDSequence",
    "Sidecar",
    "detect_format",
    "open_sequence",
    "parse_frames",
]

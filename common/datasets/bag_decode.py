"""ROS messages to arrays: images (raw and compressed, incl. compressedDepth), camera info, poses.

Works on the message objects `rosbags` deserialises (ROS 1 and ROS 2 alike: field names
differ only in CameraInfo's K/k). `where` arguments name the bag, topic and message for
error messages.
"""

from __future__ import annotations

import logging
import struct
from typing import Any

import cv2
import numpy as np

from cpslam.common.datasets.base import DatasetError, check_pose
from cpslam.common.geometry import pose_from_tq

logger = logging.getLogger(__name__)

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
POSE_TYPES = (
    "geometry_msgs/msg/PoseStamped",
    "geometry_msgs/msg/PoseWithCovarianceStamped",
    "geometry_msgs/msg/TransformStamped",
    "nav_msgs/msg/Odometry",
)
TF_TYPES = ("tf2_msgs/msg/TFMessage", "tf/msg/tfMessage")  # ROS 2 and ROS 1's /tf

COLOUR_ENCODINGS = ("rgb8", "bgr8", "rgba8", "bgra8", "mono8")
DEPTH_ENCODINGS = ("16UC1", "mono16", "32FC1")
_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
# compressed_depth_image_transport puts a ConfigHeader before the PNG: an int32 format
# followed by two float32 quantisation parameters (used for 32FC1 only).
_DEPTH_HEADER = struct.Struct("<iff")


def stamp_ns(msg: Any) -> int:
    """The message's header stamp in integer nanoseconds (0 when it has none)."""
    header = getattr(msg, "header", None)
    if header is None:
        return 0
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def depth_kind(msgtype: str, msg: Any) -> str | None:
    """"16UC1" or "32FC1" when the message is a depth image it can decode, else None."""
    if msgtype == IMAGE:
        return {"16UC1": "16UC1", "mono16": "16UC1", "32FC1": "32FC1"}.get(msg.encoding)
    if msgtype == COMPRESSED and "compresseddepth" in msg.format.lower():
        return "32FC1" if msg.format.strip().startswith("32FC1") else "16UC1"
    return None


def check_colour(msgtype: str, msg: Any, where: str) -> None:
    """Reject a colour image message the decoder cannot turn into RGB."""
    if msgtype == IMAGE and msg.encoding not in COLOUR_ENCODINGS:
        raise DatasetError(
            f"{where}: colour encoding {msg.encoding!r} is not supported; expected one of "
            + ", ".join(COLOUR_ENCODINGS)
        )
    if msgtype == COMPRESSED and "compresseddepth" in msg.format.lower():
        raise DatasetError(f"{where}: is compressed depth ({msg.format!r}), not a colour image")


def decode_colour(msgtype: str, msg: Any, where: str) -> np.ndarray:
    """uint8 [H, W, 3] RGB from a sensor_msgs Image or CompressedImage."""
    check_colour(msgtype, msg, where)
    if msgtype == COMPRESSED:
        bgr = cv2.imdecode(np.frombuffer(msg.data, np.uint8), cv2.IMREAD_COLOR)
        if bgr is None:
            raise DatasetError(f"{where}: cannot decode compressed image ({msg.format!r})")
        # image_transport converts colour to bgr8 before encoding ("rgb8; jpeg compressed
        # bgr8"); a stream encoded straight from rgb8 says so after "compressed".
        after = msg.format.lower().rpartition("compressed")[2].strip()
        if after.startswith("rgb"):
            return np.ascontiguousarray(bgr)
        return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
    channels = {"rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4, "mono8": 1}[msg.encoding]
    img = _raw_pixels(msg, np.dtype(np.uint8), channels, where)
    if msg.encoding == "mono8":
        return cv2.cvtColor(img, cv2.COLOR_GRAY2RGB)
    if msg.encoding.startswith("bgr"):
        return cv2.cvtColor(img, cv2.COLOR_BGRA2RGB if channels == 4 else cv2.COLOR_BGR2RGB)
    return np.ascontiguousarray(img[:, :, :3])


def decode_depth(msgtype: str, msg: Any, depth_scale: float, where: str) -> np.ndarray:
    """float32 [H, W] metres from a depth Image or CompressedImage; 0 means no reading.

    16UC1 (and mono16) is divided by `depth_scale` (units per metre); 32FC1 is metres, with
    NaN, inf and non-positive values meaning no reading.
    """
    kind = depth_kind(msgtype, msg)
    if msgtype == COMPRESSED:
        raw = _decompress_depth(msg, kind, where)
    elif kind is None:
        raise DatasetError(
            f"{where}: depth encoding {msg.encoding!r} is not supported; expected one of "
            + ", ".join(DEPTH_ENCODINGS)
        )
    else:
        dtype = np.dtype(np.uint16 if kind == "16UC1" else np.float32)
        raw = _raw_pixels(msg, dtype.newbyteorder(">" if msg.is_bigendian else "<"), 1, where)
    if raw.dtype == np.uint16:
        return raw.astype(np.float32) / np.float32(depth_scale)
    depth = raw.astype(np.float32)
    depth[~np.isfinite(depth) | (depth < 0)] = 0.0
    return depth


def intrinsics_values(msg: Any, where: str) -> dict[str, float | int]:
    """fx, fy, cx, cy, width, height of a sensor_msgs CameraInfo."""
    K = np.asarray(getattr(msg, "k", None) if hasattr(msg, "k") else msg.K, dtype=np.float64)
    if K.shape != (9,) or not np.all(np.isfinite(K)) or K[0] <= 0 or K[4] <= 0:
        raise DatasetError(f"{where}: camera info K is not a valid 3x3 camera matrix: {K}")
    D = np.asarray(getattr(msg, "d", None) if hasattr(msg, "d") else msg.D, dtype=np.float64)
    if D.size and np.any(D != 0):
        logger.warning(
            "%s: distortion %s is ignored (images are used as they are, pinhole model)",
            where, np.round(D, 4).tolist(),
        )
    values: dict[str, float | int] = {
        "fx": float(K[0]), "fy": float(K[4]), "cx": float(K[2]), "cy": float(K[5]),
    }
    if msg.width > 0 and msg.height > 0:
        values.update(width=int(msg.width), height=int(msg.height))
    return values


def pose_matrix(msgtype: str, msg: Any, where: str) -> np.ndarray:
    """`T_world_cam` [4, 4] from a PoseStamped, PoseWithCovarianceStamped, TransformStamped
    or Odometry (the frame the message describes is taken as the colour camera's)."""
    if msgtype == "geometry_msgs/msg/TransformStamped":
        t, q = msg.transform.translation, msg.transform.rotation
    else:
        pose = msg.pose if msgtype == "geometry_msgs/msg/PoseStamped" else msg.pose.pose
        t, q = pose.position, pose.orientation
    quat = np.array([q.x, q.y, q.z, q.w], dtype=np.float64)
    xyz = np.array([t.x, t.y, t.z], dtype=np.float64)
    if not (np.all(np.isfinite(quat)) and np.all(np.isfinite(xyz))) or np.linalg.norm(quat) < 1e-6:
        raise DatasetError(f"{where}: non-finite pose or zero quaternion")
    return check_pose(pose_from_tq(xyz, quat / np.linalg.norm(quat)), where)


def _raw_pixels(msg: Any, dtype: np.dtype, channels: int, where: str) -> np.ndarray:
    """The [H, W(, C)] pixels of a raw Image, honouring its row stride (`step`)."""
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    row = width * channels * dtype.itemsize
    data = np.asarray(msg.data, dtype=np.uint8)
    if step < row or data.size < step * height or height == 0 or width == 0:
        raise DatasetError(
            f"{where}: {msg.encoding} image of {width}x{height} needs rows of {row} bytes; "
            f"message has step {step} and {data.size} bytes"
        )
    rows = data[: step * height].reshape(height, step)[:, :row]
    pixels = np.ascontiguousarray(rows).view(dtype).reshape(height, width, channels)
    pixels = pixels.astype(dtype.newbyteorder("="), copy=False)
    return pixels[:, :, 0] if channels == 1 else pixels


def _decompress_depth(msg: Any, kind: str | None, where: str) -> np.ndarray:
    """Raw depth of a compressed depth image: uint16 (16UC1) or float32 metres (32FC1)."""
    data = bytes(msg.data)
    fmt = msg.format.lower()
    if kind is not None and "rvl" in fmt:
        raise DatasetError(
            f"{where}: compressedDepth RVL ({msg.format!r}) is not supported; record depth "
            "raw or as compressedDepth png"
        )
    start = 0 if data.startswith(_PNG_MAGIC) else _DEPTH_HEADER.size
    if data[start : start + 8] != _PNG_MAGIC:
        raise DatasetError(f"{where}: compressed depth ({msg.format!r}) holds no PNG image")
    img = cv2.imdecode(np.frombuffer(data[start:], np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None or img.ndim != 2 or img.dtype != np.uint16:
        raise DatasetError(
            f"{where}: compressed depth ({msg.format!r}) must decode to single-channel 16-bit, "
            f"got {None if img is None else (img.dtype, img.shape)}"
        )
    if kind != "32FC1":
        return img
    if start == 0:
        raise DatasetError(f"{where}: 32FC1 compressedDepth lacks its quantisation header")
    _, quant_a, quant_b = _DEPTH_HEADER.unpack_from(data)
    # compressed_depth_image_transport stores inverse depth: q = A / depth + B.
    depth = np.zeros(img.shape, np.float32)
    valid = img > 0
    with np.errstate(divide="ignore"):
        depth[valid] = quant_a / (img[valid].astype(np.float32) - quant_b)
    return depth

"""Write small ROS 1 / ROS 2 / MCAP bags from an RGBDSequence with `rosbags` itself (tests only).

Messages are built the way ROS drivers and image_transport publish them: raw Image
(rgb8 colour, 16UC1 millimetre or 32FC1 metre depth), CompressedImage ("rgb8; png
compressed bgr8" colour, "16UC1; compressedDepth png" depth with its 12-byte header),
CameraInfo, and PoseStamped ground truth. Header stamps are the frame timestamps in whole
nanoseconds; receive times are the stamps plus a fixed latency.
"""

from __future__ import annotations

import struct
from pathlib import Path

import cv2
import numpy as np

from cpslam.common.datasets import RGBDSequence
from cpslam.common.geometry import pose_to_tq

LATENCY_NS = 5_000_000
STAMP_BASE_NS = 1_700_000_000_000_000_000  # a realistic epoch stamp


def stamp_ns(timestamp: float) -> int:
    return STAMP_BASE_NS + round(timestamp * 1e9)


def write_bag(
    path: Path,
    seq: RGBDSequence,
    kind: str,
    compressed: bool = False,
    depth_encoding: str = "16UC1",
    topics: dict[str, str] | None = None,
    with_info: bool = True,
    with_pose: bool = True,
    depth_offset_ns: int = 0,
    depth_stride: int = 1,
    with_tf: bool = False,
    extra: tuple[tuple[str, str], ...] = (),
) -> Path:
    """Write `seq` to a "ros1" .bag, a "ros2" sqlite3 folder or an "mcap" ROS 2 file.

    `extra` adds (topic, what) pairs, `what` one of `EXTRA` (colour, colour_compressed,
    mono, depth, info, pose), holding another copy of that stream (for topic detection).
    Depth is converted from metres back to the encoding;
    `depth_stride` 2 writes every second depth pixel (a depth image not registered to colour).
    `with_tf` adds /tf with two transforms per frame: world -> camera (the ground truth) and
    camera -> camera_optical (identity).
    Returns the path to open.
    """
    from rosbags.typesys import Stores, get_typestore

    names = {"rgb": "/camera/color/image_raw", "depth": "/camera/depth/image_raw",
             "info": "/camera/color/camera_info", "pose": "/ground_truth/pose"}
    names.update(topics or {})
    if compressed:
        names["rgb"] += "/compressed"
        names["depth"] += "/compressedDepth"
    ros1 = kind == "ros1"
    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    if ros1 and with_tf:  # rosbags' Noetic store has no tf2_msgs
        from rosbags.typesys import get_types_from_msg

        store.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms",
                                          "tf2_msgs/msg/TFMessage"))
    T = store.types

    def header(ns: int, frame: str) -> object:
        time = T["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)
        if ros1:
            return T["std_msgs/msg/Header"](seq=0, stamp=time, frame_id=frame)
        return T["std_msgs/msg/Header"](stamp=time, frame_id=frame)

    image_type = "sensor_msgs/msg/CompressedImage" if compressed else "sensor_msgs/msg/Image"
    streams = [(names["rgb"], image_type), (names["depth"], image_type)]
    if with_info:
        streams.append((names["info"], "sensor_msgs/msg/CameraInfo"))
    if with_pose and seq.has_gt:
        streams.append((names["pose"], "geometry_msgs/msg/PoseStamped"))
    if with_tf:
        streams.append(("/tf", "tf2_msgs/msg/TFMessage"))
    streams.extend((topic, EXTRA[what]) for topic, what in extra)

    writer, serialize = _writer(path, kind, store)
    with writer:
        conns = {topic: writer.add_connection(topic, msgtype, typestore=store)
                 for topic, msgtype in streams}
        k = seq.intrinsics
        for frame in seq:
            ns = stamp_ns(frame.timestamp)
            msgs = {
                names["rgb"]: _colour(T, header(ns, "color"), frame.rgb, compressed),
                names["depth"]: _depth(T, header(ns + depth_offset_ns, "color"),
                                       frame.depth[::depth_stride, ::depth_stride],
                                       seq.depth_scale, depth_encoding, compressed),
            }
            if with_info:
                K = np.array([k.fx, 0, k.cx, 0, k.fy, k.cy, 0, 0, 1], np.float64)
                fields = dict(header=header(ns, "color"), height=k.height, width=k.width,
                              distortion_model="plumb_bob", binning_x=0, binning_y=0,
                              roi=T["sensor_msgs/msg/RegionOfInterest"](
                                  x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))
                mats = dict(D=np.zeros(5), K=K, R=np.eye(3).ravel(),
                            P=np.hstack([K.reshape(3, 3), np.zeros((3, 1))]).ravel())
                fields.update(mats if ros1 else {m.lower(): v for m, v in mats.items()})
                msgs[names["info"]] = T["sensor_msgs/msg/CameraInfo"](**fields)
            if with_pose and frame.gt_pose is not None:
                t, q = pose_to_tq(frame.gt_pose)
                pose = T["geometry_msgs/msg/Pose"](
                    position=T["geometry_msgs/msg/Point"](x=t[0], y=t[1], z=t[2]),
                    orientation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]))
                msgs[names["pose"]] = T["geometry_msgs/msg/PoseStamped"](
                    header=header(ns, "world"), pose=pose)
            if with_tf:
                transforms = [
                    T["geometry_msgs/msg/TransformStamped"](
                        header=header(ns, parent), child_frame_id=child,
                        transform=T["geometry_msgs/msg/Transform"](
                            translation=T["geometry_msgs/msg/Vector3"](x=t[0], y=t[1], z=t[2]),
                            rotation=T["geometry_msgs/msg/Quaternion"](
                                x=q[0], y=q[1], z=q[2], w=q[3])))
                    for parent, child, (t, q) in (
                        ("/world", "camera", pose_to_tq(frame.gt_pose)),
                        ("camera", "camera_optical", pose_to_tq(np.eye(4))))
                ]
                msgs["/tf"] = T["tf2_msgs/msg/TFMessage"](transforms=transforms)
            for topic, what in extra:
                if what in ("info", "pose"):
                    msgs[topic] = msgs[names[what]]
                elif what == "mono":
                    grey = np.ascontiguousarray(frame.rgb[:, :, 1])
                    msgs[topic] = T["sensor_msgs/msg/Image"](
                        header=header(ns, "ir"), height=grey.shape[0], width=grey.shape[1],
                        encoding="mono8", is_bigendian=0, step=grey.shape[1], data=grey.ravel())
                elif what == "depth":
                    msgs[topic] = _depth(T, header(ns, "color"), frame.depth, seq.depth_scale,
                                         "16UC1", False)
                else:
                    msgs[topic] = _colour(T, header(ns, "color"), frame.rgb,
                                          what == "colour_compressed")
            for topic, msg in msgs.items():
                writer.write(conns[topic], ns + LATENCY_NS, serialize(msg, conns[topic].msgtype))
    return path


EXTRA = {
    "colour": "sensor_msgs/msg/Image",
    "colour_compressed": "sensor_msgs/msg/CompressedImage",
    "mono": "sensor_msgs/msg/Image",
    "depth": "sensor_msgs/msg/Image",
    "info": "sensor_msgs/msg/CameraInfo",
    "pose": "geometry_msgs/msg/PoseStamped",
}


def _writer(path: Path, kind: str, store: object) -> tuple[object, object]:
    if kind == "ros1":
        from rosbags.rosbag1 import Writer as Writer1

        return Writer1(path), store.serialize_ros1
    from rosbags.rosbag2 import StoragePlugin, Writer

    plugin = StoragePlugin.MCAP if kind == "mcap" else StoragePlugin.SQLITE3
    return Writer(path, version=9, storage_plugin=plugin), store.serialize_cdr


def _colour(T: dict, head: object, rgb: np.ndarray, compressed: bool) -> object:
    if compressed:
        ok, png = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        assert ok
        return T["sensor_msgs/msg/CompressedImage"](header=head, format="rgb8; png compressed bgr8",
                                                    data=png.ravel())
    h, w = rgb.shape[:2]
    return T["sensor_msgs/msg/Image"](header=head, height=h, width=w, encoding="rgb8",
                                      is_bigendian=0, step=3 * w, data=rgb.ravel().copy())


def _depth(T: dict, head: object, depth_m: np.ndarray, scale: float, encoding: str,
           compressed: bool) -> object:
    h, w = depth_m.shape
    if encoding == "16UC1":
        raw = np.round(depth_m.astype(np.float64) * scale).astype(np.uint16)
    else:
        raw = depth_m.astype(np.float32)
    if compressed:
        assert encoding == "16UC1"
        ok, png = cv2.imencode(".png", raw)
        assert ok
        data = struct.pack("<iff", 0, 0.0, 0.0) + png.tobytes()
        return T["sensor_msgs/msg/CompressedImage"](
            header=head, format="16UC1; compressedDepth png", data=np.frombuffer(data, np.uint8))
    itemsize = raw.dtype.itemsize
    return T["sensor_msgs/msg/Image"](header=head, height=h, width=w, encoding=encoding,
                                      is_bigendian=0, step=itemsize * w,
                                      data=raw.view(np.uint8).ravel().copy())

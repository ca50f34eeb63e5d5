"""ROS 1 bags, ROS 2 bags (sqlite3 or mcap storage) and MCAP files, read with `rosbags`.

    BAG.bag                     ROS 1
    BAG/metadata.yaml + *.db3   ROS 2 (a folder; *.mcap storage too)
    BAG.mcap / BAG.db3          a ROS 2 storage file on its own

Colour and depth come from sensor_msgs/Image or CompressedImage topics, intrinsics from a
sensor_msgs/CameraInfo topic, optional ground truth from a pose topic. Topics are given or
detected when there is exactly one candidate (see `choose_topics`). Colour is paired with
the depth image nearest in header time within `max_dt`, like TUM. Opening reads every
message of the chosen topics once, to index their header stamps; images are decoded when
a frame is accessed, each found again by its receive time in the bag.
"""

from __future__ import annotations

import logging
import os
import threading
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from cpslam.common.camera import Intrinsics
from cpslam.common.datasets import bag_decode as dec
from cpslam.common.datasets.bag_topics import TOPIC_KEYS, choose_topics
from cpslam.common.datasets.base import DatasetError, RGBDSequence, nearest_within
from cpslam.common.datasets.sidecar import Sidecar, resolve_intrinsics
from cpslam.common.datasets.tum import associate

logger = logging.getLogger(__name__)

NAME = "bag"
SUFFIXES = (".bag", ".mcap", ".db3")
DEPTH_SCALE = 1000.0  # 16UC1 depth is millimetres by ROS convention (REP 118)
INSTALL_HINT = "pip install 'cpslam[bags]' (or pip install rosbags)"


def looks_like(root: Path) -> bool:
    """A ROS 1 bag, an MCAP/sqlite3 storage file, or a ROS 2 bag folder (metadata.yaml)."""
    if root.is_file():
        return root.suffix.lower() in SUFFIXES
    return (root / "metadata.yaml").is_file()


def load(
    root: Path,
    sidecar: Sidecar,
    intrinsics: Intrinsics | None = None,
    topics: Mapping[str, str | None] | None = None,
    max_dt: float = 0.02,
) -> RGBDSequence:
    """Index a bag: choose topics, read header stamps, pair colour with depth, read ground truth.

    Args:
        topics: "rgb", "depth", "info", "pose" → topic name; None entries are detected.
            "pose" may be "none" (no ground truth even if the bag has a pose topic).
        max_dt: the largest colour/depth and colour/ground-truth gap in header time (s).
    """
    if max_dt <= 0:
        raise DatasetError(f"max_dt must be positive, got {max_dt}")
    unknown = set(topics or {}) - set(TOPIC_KEYS)
    if unknown:
        raise DatasetError(f"unknown topic keys {sorted(unknown)}; expected {TOPIC_KEYS}")
    access = BagAccess(root)
    reader = access.reader()
    chosen = choose_topics(root, reader, dict(topics or {}))

    rgb = _index(access, chosen["rgb"])
    depth = _index(access, chosen["depth"])
    first_depth = access.read(depth.conn[0], int(depth.log_ns[0]), int(depth.ordinal[0]))
    depth_kind = dec.depth_kind(depth.msgtype, first_depth)
    depth_where = f"{root}: topic {chosen['depth']}"
    if depth.msgtype == dec.IMAGE and depth_kind is None:
        raise DatasetError(
            f"{depth_where}: depth encoding {first_depth.encoding!r} is not supported; "
            "expected one of " + ", ".join(dec.DEPTH_ENCODINGS)
        )
    rgb_where = f"{root}: topic {chosen['rgb']}"
    first_rgb = access.read(rgb.conn[0], int(rgb.log_ns[0]), int(rgb.ordinal[0]))
    rgb_hw = dec.decode_colour(rgb.msgtype, first_rgb, rgb_where).shape[:2]
    depth_scale = 1.0 if depth_kind == "32FC1" else (sidecar.depth_scale or DEPTH_SCALE)
    depth_hw = dec.decode_depth(depth.msgtype, first_depth, depth_scale, depth_where).shape
    if rgb_hw != depth_hw:
        raise DatasetError(
            f"{root}: colour {chosen['rgb']} is {rgb_hw[1]}x{rgb_hw[0]} but depth "
            f"{chosen['depth']} is {depth_hw[1]}x{depth_hw[0]}; they must match, with depth "
            "registered to colour (e.g. a driver's aligned_depth_to_color topic)"
        )

    pairs = associate(rgb.stamps, depth.stamps, max_dt)
    if not pairs:
        raise DatasetError(
            f"{root}: no colour image on {chosen['rgb']} has a depth image on "
            f"{chosen['depth']} within {max_dt} s (header stamps)"
        )
    if len(pairs) < len(rgb.stamps):
        logger.info("%s: %d of %d colour images have no depth within %.3f s and are skipped",
                    root, len(rgb.stamps) - len(pairs), len(rgb.stamps), max_dt)
    rows = np.array([i for i, _ in pairs], dtype=np.int64)
    cols = np.array([j for _, j in pairs], dtype=np.int64)

    camera = resolve_intrinsics(
        root, NAME, sidecar, intrinsics,
        _camera_info(access, chosen["info"]) if chosen["info"] else None,
        (depth_hw[1], depth_hw[0]),
        why_no_defaults="the bag has no sensor_msgs/CameraInfo topic; pass --topic-info if "
        "it has one under another type name, or give fx, fy, cx, cy",
    )
    if (camera.height, camera.width) != depth_hw:
        raise DatasetError(
            f"{root}: the intrinsics (camera info {chosen['info']}, overrides or camera.yaml) "
            f"are for {camera.width}x{camera.height} images but depth {chosen['depth']} is "
            f"{depth_hw[1]}x{depth_hw[0]}; name the depth images' camera info with "
            "--topic-info, or give matching width and height"
        )
    stamps = rgb.stamps[rows]
    poses = _ground_truth(access, chosen["pose"], stamps, rows, max_dt) if chosen["pose"] else {}
    if sidecar.fps is not None:
        fps = sidecar.fps
    else:
        steps = np.diff(stamps)
        fps = 1.0 / float(np.median(steps)) if len(steps) and np.median(steps) > 0 else 30.0
    logger.info("%s: colour %s, depth %s (%s), info %s, pose %s", root, chosen["rgb"],
                chosen["depth"], depth_kind or "compressed", chosen["info"], chosen["pose"])
    return BagSequence(
        access=access,
        topics=chosen,
        refs=(rgb.take(rows), depth.take(cols)),
        path=root,
        format=NAME,
        intrinsics=camera,
        indices=rows,
        timestamps=stamps,
        rgb_paths=[root] * len(rows),
        depth_paths=[root] * len(rows),
        depth_scale=depth_scale,
        fps=fps,
        pose_reader=poses.get if poses else None,
    )


class BagAccess:
    """One open `rosbags` reader per process, shared by a sequence and its selections."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._reader: Any = None
        self._pid = -1
        self._lock = threading.Lock()

    def reader(self) -> Any:
        if self._reader is None or self._pid != os.getpid():
            self._reader = _open_reader(self.path)
            self._pid = os.getpid()
        return self._reader

    def connections(self, topic: str) -> list[Any]:
        return [c for c in self.reader().connections if c.topic == topic]

    def read(self, conn_id: int, log_ns: int, ordinal: int) -> Any:
        """The `ordinal`-th message of connection `conn_id` (its position in the reader's
        connections, the same in every process) received at `log_ns`, deserialised."""
        with self._lock:
            reader = self.reader()
            conn = reader.connections[conn_id]
            found = [raw for _, _, raw in reader.messages([conn], start=log_ns, stop=log_ns + 1)]
            if ordinal >= len(found):
                raise DatasetError(
                    f"{self.path}: topic {conn.topic}: message at {log_ns} ns is gone "
                    "(was the bag changed after it was opened?)"
                )
            return reader.deserialize(found[ordinal], conn.msgtype)

    def __getstate__(self) -> dict[str, Any]:
        # A reader holds open files: a copy in another process opens its own.
        return {"path": self.path}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__init__(state["path"])  # type: ignore[misc]


class _TopicIndex:
    """Every message of one topic: connection (position in the reader's list), receive time
    (ns), position among that connection's messages at that time, header stamp (s)."""

    def __init__(self, topic: str, msgtype: str, conn: np.ndarray, log_ns: np.ndarray,
                 ordinal: np.ndarray, stamps: np.ndarray) -> None:
        self.topic, self.msgtype, self.conn = topic, msgtype, conn
        self.log_ns, self.ordinal, self.stamps = log_ns, ordinal, stamps

    def take(self, positions: np.ndarray) -> _TopicIndex:
        return _TopicIndex(self.topic, self.msgtype, self.conn[positions],
                           self.log_ns[positions], self.ordinal[positions], self.stamps[positions])


class BagSequence(RGBDSequence):
    """An RGBDSequence whose images are messages in a bag (`rgb_paths` all name the bag)."""

    def __init__(self, access: BagAccess, topics: dict[str, str | None],
                 refs: tuple[_TopicIndex, _TopicIndex], **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self.access = access
        self.topics = topics
        self._refs = refs

    def _read_images(self, i: int) -> tuple[np.ndarray, np.ndarray, str, str]:
        rgb_ref, depth_ref = self._refs
        where = []
        msgs = []
        for ref in (rgb_ref, depth_ref):
            log_ns = int(ref.log_ns[i])
            where.append(f"{self.path}: topic {ref.topic} message at {log_ns} ns "
                         f"(header {ref.stamps[i]:.6f} s)")
            msgs.append(self.access.read(int(ref.conn[i]), log_ns, int(ref.ordinal[i])))
        rgb = dec.decode_colour(rgb_ref.msgtype, msgs[0], where[0])
        depth = dec.decode_depth(depth_ref.msgtype, msgs[1], self.depth_scale, where[1])
        return rgb, depth, where[0], where[1]

    def _subset_args(self, positions: np.ndarray) -> dict[str, Any]:
        refs = (self._refs[0].take(positions), self._refs[1].take(positions))
        return {**super()._subset_args(positions), "access": self.access,
                "topics": self.topics, "refs": refs}


def _open_reader(path: Path) -> Any:
    try:
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore
    except ImportError:
        raise DatasetError(
            f"{path}: reading ROS bags and MCAP files needs the rosbags package; "
            f"install it with {INSTALL_HINT}"
        ) from None
    # Bags that do not embed their message definitions (older ROS 2 sqlite3) are read with
    # the standard definitions; sensor_msgs and geometry_msgs have not changed since Humble.
    store = get_typestore(Stores.ROS1_NOETIC if path.suffix == ".bag" else Stores.ROS2_HUMBLE)
    try:
        reader = AnyReader([path], default_typestore=store)
        reader.open()
    except Exception as e:  # rosbags raises several unrelated types for unreadable input
        raise DatasetError(f"{path}: cannot read as a ROS bag or MCAP file ({e})") from e
    return reader


def _index(access: BagAccess, topic: str) -> _TopicIndex:
    """Read every message of `topic` once for its header stamp."""
    reader = access.reader()
    conns = access.connections(topic)
    msgtype = conns[0].msgtype
    conn_ids = {(c.id, c.topic): i for i, c in enumerate(reader.connections)}
    seen: dict[tuple[int, int], int] = {}
    rows = []
    for conn, log_ns, raw in reader.messages(conns):
        key = (conn_ids[conn.id, conn.topic], log_ns)
        seen[key] = seen.get(key, -1) + 1
        header_ns = dec.stamp_ns(reader.deserialize(raw, msgtype))
        rows.append((*key, seen[key], header_ns))
    if not rows:
        raise DatasetError(f"{access.path}: topic {topic} has no messages")
    table = np.array(rows, dtype=np.int64)
    header = table[:, 3]
    if np.all(header == 0):
        logger.warning("%s: topic %s has no header stamps; using the bag's receive times",
                       access.path, topic)
        header = table[:, 1]
    order = np.argsort(header, kind="stable")
    table, header = table[order], header[order]
    return _TopicIndex(topic, msgtype, table[:, 0], table[:, 1],
                       table[:, 2], header.astype(np.float64) * 1e-9)


def _camera_info(access: BagAccess, topic: str) -> dict[str, float | int]:
    """The intrinsics in the topic's first CameraInfo message."""
    reader = access.reader()
    where = f"{access.path}: topic {topic}"
    for conn, _, raw in reader.messages(access.connections(topic)):
        return dec.intrinsics_values(reader.deserialize(raw, conn.msgtype), where)
    raise DatasetError(f"{where}: has no CameraInfo messages")


def _ground_truth(access: BagAccess, spec: str, frame_stamps: np.ndarray, rows: np.ndarray,
                  max_dt: float) -> dict[int, np.ndarray]:
    """Each frame's pose: the pose message nearest in header time, if within max_dt.

    `spec` is a topic, or "TOPIC:PARENT:CHILD" for a tf topic.
    """
    topic, _, frames = spec.partition(":")
    reader = access.reader()
    conns = access.connections(topic)
    if conns[0].msgtype in dec.TF_TYPES:
        stamps, poses = _tf_poses(access, topic, frames)
    else:
        stamps, poses = [], []
        for conn, log_ns, raw in reader.messages(conns):
            msg = reader.deserialize(raw, conn.msgtype)
            where = f"{access.path}: topic {topic} message at {log_ns} ns"
            poses.append(dec.pose_matrix(conn.msgtype, msg, where))
            stamps.append((dec.stamp_ns(msg) or log_ns) * 1e-9)
    nearest = nearest_within(frame_stamps, np.asarray(stamps), max_dt)
    matched = {int(row): poses[k] for row, k in zip(rows, nearest, strict=True) if k >= 0}
    logger.info("%s: ground truth from %s for %d of %d frames", access.path, spec,
                len(matched), len(rows))
    return matched


def _tf_poses(access: BagAccess, topic: str, frames: str) -> tuple[list[float], list[np.ndarray]]:
    """Stamps and poses of one parent/child pair of a tf topic (leading '/' ignored)."""
    reader = access.reader()
    wanted = tuple(f.strip().lstrip("/") for f in frames.split(":")) if frames else None
    if wanted is not None and (len(wanted) != 2 or not all(wanted)):
        raise DatasetError(f"{access.path}: --topic-pose {topic}:{frames}: expected "
                           f"{topic}:PARENT:CHILD")
    pairs: set[tuple[str, str]] = set()
    stamps: list[float] = []
    poses: list[np.ndarray] = []
    for conn, log_ns, raw in reader.messages(access.connections(topic)):
        for tf in reader.deserialize(raw, conn.msgtype).transforms:
            pair = (tf.header.frame_id.lstrip("/"), tf.child_frame_id.lstrip("/"))
            pairs.add(pair)
            if wanted is None and len(pairs) > 1:
                break
            if wanted is not None and pair != wanted:
                continue
            where = f"{access.path}: topic {topic} {pair[0]} -> {pair[1]} at {log_ns} ns"
            poses.append(dec.pose_matrix("geometry_msgs/msg/TransformStamped", tf, where))
            stamps.append((dec.stamp_ns(tf) or log_ns) * 1e-9)
        if wanted is None and len(pairs) > 1:
            break
    if not poses or (wanted is None and len(pairs) > 1):
        found = ", ".join(f"{p}:{c}" for p, c in sorted(pairs)) or "none"
        what = f"no transform {wanted[0]} -> {wanted[1]}" if wanted else "several frame pairs"
        raise DatasetError(f"{access.path}: topic {topic} has {what} (seen: {found}); "
                           f"choose one with --topic-pose {topic}:PARENT:CHILD")
    return stamps, poses

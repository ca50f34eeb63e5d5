"""Which topics of a bag hold colour, depth, camera info and ground-truth poses.

A topic given by the user is checked (it exists, its type fits). A topic not given is
detected, and must be the only candidate:

- depth: an Image whose first message is 16UC1, mono16 or 32FC1, or a CompressedImage in
  compressedDepth format;
- colour: any other Image or CompressedImage; mono8 images are dropped when a colour one
  exists (infrared streams), and `T/compressed` when the raw `T` is also recorded;
- camera info: the only CameraInfo topic, else the one beside the depth topic (same
  namespace), else the one beside the colour topic; none means intrinsics must be given;
- pose: the only PoseStamped, PoseWithCovarianceStamped, TransformStamped or Odometry topic;
  none means no ground truth; "none" turns it off. A tf topic (tf2_msgs/TFMessage, ROS 1's
  tf/tfMessage) is used only when named, as "TOPIC" (it must hold one parent/child pair)
  or "TOPIC:PARENT:CHILD".
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from cpslam.common.datasets import bag_decode as dec
from cpslam.common.datasets.base import DatasetError

TOPIC_KEYS = ("rgb", "depth", "info", "pose")
_IMAGE_TYPES = (dec.IMAGE, dec.COMPRESSED)
_EXPECTED = {
    "rgb": _IMAGE_TYPES,
    "depth": _IMAGE_TYPES,
    "info": (dec.CAMERA_INFO,),
    "pose": (*dec.POSE_TYPES, *dec.TF_TYPES),
}
_FLAG = {"rgb": "--topic-rgb", "depth": "--topic-depth", "info": "--topic-info",
         "pose": "--topic-pose"}


def choose_topics(root: Path, reader: Any, given: dict[str, str | None]) -> dict[str, str | None]:
    """Topic names for "rgb", "depth", "info", "pose" (info and pose may be None)."""
    types = {topic: info.msgtype for topic, info in reader.topics.items()}
    chosen: dict[str, str | None] = {}
    for key in TOPIC_KEYS:
        topic = given.get(key)
        if key == "pose" and topic is not None and topic.lower() == "none":
            chosen[key] = None
            continue
        if key == "pose" and topic is not None and ":" in topic:
            name = topic.split(":", 1)[0]
            if _check_given(root, types, key, name) and types[name] not in dec.TF_TYPES:
                raise DatasetError(f"{root}: --topic-pose {topic}: PARENT:CHILD frames apply "
                                   f"to tf topics ({', '.join(dec.TF_TYPES)}), {name} is "
                                   f"{types[name]}")
            chosen[key] = topic
        elif topic is not None:
            chosen[key] = _check_given(root, types, key, topic)

    if chosen.get("rgb") is None or chosen.get("depth") is None:
        colour, depth = _image_candidates(root, reader, types, chosen)
        for key, found in (("rgb", colour), ("depth", depth)):
            if chosen.get(key) is None:
                chosen[key] = _only(root, types, key, found)
    if "info" not in chosen:
        chosen["info"] = _camera_info_topic(root, types, chosen)
    if "pose" not in chosen:
        poses = sorted(t for t, m in types.items() if m in dec.POSE_TYPES)
        chosen["pose"] = _only(root, types, "pose", poses) if poses else None
    if chosen["rgb"] == chosen["depth"]:
        raise DatasetError(f"{root}: colour and depth are both topic {chosen['rgb']}")
    return chosen


def _check_given(root: Path, types: dict[str, str], key: str, topic: str) -> str:
    if topic not in types:
        listing = ", ".join(f"{t} ({m})" for t, m in sorted(types.items())
                            if m in _EXPECTED[key]) or "none"
        raise DatasetError(
            f"{root}: {_FLAG[key]} {topic}: no such topic in the bag; topics of a fitting "
            f"type ({', '.join(_EXPECTED[key])}): {listing}"
        )
    if types[topic] not in _EXPECTED[key]:
        raise DatasetError(
            f"{root}: {_FLAG[key]} {topic} is {types[topic]}; expected "
            + " or ".join(_EXPECTED[key])
        )
    return topic


def _image_candidates(root: Path, reader: Any, types: dict[str, str],
                      chosen: dict[str, str | None]) -> tuple[list[str], list[str]]:
    """Colour and depth candidates among the image topics not already chosen."""
    taken = {chosen.get("rgb"), chosen.get("depth")}
    images = sorted(t for t, m in types.items() if m in _IMAGE_TYPES and t not in taken)
    colour, mono, depth = [], [], []
    for topic in images:
        if types[topic] == dec.COMPRESSED and topic.rsplit("/", 1)[0] in images:
            continue  # image_transport's compressed twin of a raw topic that is recorded
        msg = _first_message(reader, topic)
        if msg is None:
            continue
        if dec.depth_kind(types[topic], msg) is not None:
            depth.append(topic)
        elif types[topic] == dec.IMAGE and msg.encoding == "mono8":
            mono.append(topic)
        elif types[topic] == dec.COMPRESSED or msg.encoding in dec.COLOUR_ENCODINGS:
            colour.append(topic)
    return colour or mono, depth


def _camera_info_topic(root: Path, types: dict[str, str],
                       chosen: dict[str, str | None]) -> str | None:
    infos = sorted(t for t, m in types.items() if m == dec.CAMERA_INFO)
    if len(infos) <= 1:
        return infos[0] if infos else None
    for key in ("depth", "rgb"):
        namespace = str(chosen[key]).rsplit("/", 1)[0]
        beside = [t for t in infos if t.rsplit("/", 1)[0] == namespace]
        if len(beside) == 1:
            return beside[0]
    return _only(root, types, "info", infos)


def _only(root: Path, types: dict[str, str], key: str, found: list[str]) -> str:
    what = {"rgb": "colour image", "depth": "depth image", "info": "camera info",
            "pose": "pose"}[key]
    if len(found) == 1:
        return found[0]
    if not found:
        listing = ", ".join(f"{t} ({m})" for t, m in sorted(types.items())) or "none"
        raise DatasetError(
            f"{root}: no {what} topic found (expected {' or '.join(_EXPECTED[key])}"
            + (" with a depth encoding 16UC1, mono16, 32FC1 or compressedDepth" if key == "depth"
               else "")
            + f"); the bag has: {listing}. Name it with {_FLAG[key]}"
        )
    hint = " (or --topic-pose none)" if key == "pose" else ""
    raise DatasetError(
        f"{root}: {len(found)} candidate {what} topics: {', '.join(found)}; choose one with "
        f"{_FLAG[key]} TOPIC{hint}"
    )


def _first_message(reader: Any, topic: str) -> Any:
    conns = [c for c in reader.connections if c.topic == topic]
    for conn, _, raw in reader.messages(conns):
        return reader.deserialize(raw, conn.msgtype)
    return None

"""Decoding ROS image, camera-info and pose messages into arrays (no bag, no data needed)."""

from __future__ import annotations

import logging
import struct
from types import SimpleNamespace as NS

import cv2
import numpy as np
import pytest

from cpslam.common.datasets import DatasetError
from cpslam.common.datasets import bag_decode as dec

rng = np.random.default_rng(0)
RGB = rng.integers(0, 256, (5, 7, 3), dtype=np.uint8)


def _image(pixels: np.ndarray, encoding: str, pad: int = 0, bigendian: bool = False) -> NS:
    h, w = pixels.shape[:2]
    data = pixels.astype(pixels.dtype.newbyteorder(">" if bigendian else "<"))
    rows = data.reshape(h, -1).view(np.uint8)
    rows = np.hstack([rows, np.full((h, pad), 0xAB, np.uint8)])  # stride padding
    return NS(height=h, width=w, encoding=encoding, is_bigendian=int(bigendian),
              step=rows.shape[1], data=rows.ravel())


@pytest.mark.parametrize("encoding", ["rgb8", "bgr8", "rgba8", "bgra8"])
def test_raw_colour_encodings_with_row_padding(encoding: str) -> None:
    pixels = RGB[:, :, ::-1] if encoding.startswith("bgr") else RGB
    if encoding.endswith("a8"):
        pixels = np.dstack([pixels, np.full(RGB.shape[:2], 9, np.uint8)])
    out = dec.decode_colour(dec.IMAGE, _image(pixels, encoding, pad=3), "t")
    assert out.flags.c_contiguous and np.array_equal(out, RGB)


def test_mono8_becomes_grey_rgb() -> None:
    grey = RGB[:, :, 0]
    out = dec.decode_colour(dec.IMAGE, _image(grey, "mono8"), "t")
    assert np.array_equal(out, np.dstack([grey] * 3))


def test_unsupported_colour_encoding_names_it() -> None:
    msg = _image(np.zeros((2, 2), np.uint16), "16UC1")
    with pytest.raises(DatasetError, match=r"bag: topic /c: colour encoding '16UC1' is not "
                       r"supported; expected one of rgb8, bgr8, rgba8, bgra8, mono8"):
        dec.decode_colour(dec.IMAGE, msg, "bag: topic /c")


def test_compressed_depth_is_not_colour() -> None:
    msg = NS(format="16UC1; compressedDepth png", data=np.zeros(30, np.uint8))
    with pytest.raises(DatasetError, match=r"t: is compressed depth .*, not a colour image"):
        dec.decode_colour(dec.COMPRESSED, msg, "t")


@pytest.mark.parametrize("fmt, order", [("rgb8; png compressed bgr8", "bgr"),
                                        ("png", "bgr"), ("rgb8; png compressed rgb8", "rgb")])
def test_compressed_colour_channel_order(fmt: str, order: str) -> None:
    """image_transport encodes bgr8 (cv2's order); "compressed rgb8" was encoded as is."""
    stored = RGB[:, :, ::-1] if order == "bgr" else RGB
    ok, png = cv2.imencode(".png", stored)
    assert ok
    out = dec.decode_colour(dec.COMPRESSED, NS(format=fmt, data=png.ravel()), "t")
    assert np.array_equal(out, RGB)


def test_depth_16uc1_big_endian_and_scale() -> None:
    raw = np.array([[0, 1000, 65535], [1, 2, 3]], np.uint16)
    for bigendian in (False, True):
        out = dec.decode_depth(dec.IMAGE, _image(raw, "16UC1", pad=2, bigendian=bigendian),
                               1000.0, "t")
        assert out.dtype == np.float32
        assert np.array_equal(out, raw.astype(np.float32) / np.float32(1000.0))


def test_depth_32fc1_invalid_values_become_zero() -> None:
    raw = np.array([[1.5, np.nan, np.inf], [-1.0, 0.0, 2.25]], np.float32)
    out = dec.decode_depth(dec.IMAGE, _image(raw, "32FC1"), 1000.0, "t")
    assert np.array_equal(out, np.array([[1.5, 0, 0], [0, 0, 2.25]], np.float32))


def test_unsupported_depth_encoding_names_it() -> None:
    with pytest.raises(DatasetError, match=r"t: depth encoding 'rgb8' is not supported; "
                       r"expected one of 16UC1, mono16, 32FC1"):
        dec.decode_depth(dec.IMAGE, _image(RGB, "rgb8"), 1000.0, "t")


def test_compressed_depth_16uc1_with_and_without_header() -> None:
    raw = rng.integers(0, 5000, (6, 4)).astype(np.uint16)
    png = cv2.imencode(".png", raw)[1].tobytes()
    for data in (struct.pack("<iff", 0, 0.0, 0.0) + png, png):
        msg = NS(format="16UC1; compressedDepth png", data=np.frombuffer(data, np.uint8))
        assert dec.depth_kind(dec.COMPRESSED, msg) == "16UC1"
        out = dec.decode_depth(dec.COMPRESSED, msg, 1000.0, "t")
        assert np.array_equal(out, raw.astype(np.float32) / np.float32(1000.0))


def test_compressed_depth_32fc1_inverse_quantisation() -> None:
    """compressed_depth_image_transport stores q = A / depth + B in 16 bits (0: no reading)."""
    depth_quantization, depth_max = 100.0, 10.0
    A = depth_quantization * (depth_quantization + 1.0)
    B = 1.0 - A / depth_max
    depth = rng.uniform(0.3, 6.0, (5, 5)).astype(np.float32)
    q = (A / depth + B).astype(np.uint16)
    q[0, 0] = 0
    data = struct.pack("<iff", 0, A, B) + cv2.imencode(".png", q)[1].tobytes()
    msg = NS(format="32FC1; compressedDepth png", data=np.frombuffer(data, np.uint8))
    out = dec.decode_depth(dec.COMPRESSED, msg, 1000.0, "t")
    expected = np.float32(A) / (q.astype(np.float32) - np.float32(B))
    expected[0, 0] = 0.0
    assert np.array_equal(out, expected)
    # truncating q loses less than one step of inverse depth: 0 <= out - depth < out^2 / A
    valid = q > 0
    err = out[valid] - depth[valid]
    assert np.all(err >= -1e-6) and np.all(err <= out[valid] ** 2 / A + 1e-6)


def test_compressed_depth_rvl_and_garbage_are_refused() -> None:
    rvl = NS(format="16UC1; compressedDepth rvl", data=np.zeros(20, np.uint8))
    with pytest.raises(DatasetError, match=r"RVL .* is not supported"):
        dec.decode_depth(dec.COMPRESSED, rvl, 1000.0, "t")
    junk = NS(format="16UC1; compressedDepth", data=np.zeros(40, np.uint8))
    with pytest.raises(DatasetError, match=r"t: compressed depth .* holds no PNG image"):
        dec.decode_depth(dec.COMPRESSED, junk, 1000.0, "t")


def test_short_image_data_is_an_error() -> None:
    msg = _image(RGB, "rgb8")
    msg.data = msg.data[:-1]
    with pytest.raises(DatasetError, match=r"t: rgb8 image of 7x5 needs rows of 21 bytes; "
                       r"message has step 21 and 104 bytes"):
        dec.decode_colour(dec.IMAGE, msg, "t")


def test_camera_info_ros1_and_ros2_field_names(caplog: pytest.LogCaptureFixture) -> None:
    K = [500.0, 0, 319.5, 0, 505.0, 239.5, 0, 0, 1]
    ros2 = NS(k=K, d=[0.0] * 5, width=640, height=480)
    assert dec.intrinsics_values(ros2, "t") == {"fx": 500.0, "fy": 505.0, "cx": 319.5,
                                                "cy": 239.5, "width": 640, "height": 480}
    ros1 = NS(K=K, D=[0.1, 0, 0, 0, 0], width=0, height=0)
    with caplog.at_level(logging.WARNING):
        assert dec.intrinsics_values(ros1, "t") == {"fx": 500.0, "fy": 505.0, "cx": 319.5,
                                                    "cy": 239.5}
    assert "distortion [0.1, 0.0, 0.0, 0.0, 0.0] is ignored" in caplog.text
    with pytest.raises(DatasetError, match=r"t: camera info K is not a valid 3x3"):
        dec.intrinsics_values(NS(k=[0.0] * 9, d=[], width=1, height=1), "t")


def test_pose_messages() -> None:
    position, orientation = NS(x=1.0, y=2.0, z=3.0), NS(x=0.0, y=0.0, z=np.sin(0.25),
                                                       w=np.cos(0.25))
    expected = np.eye(4)
    expected[:3, 3] = [1, 2, 3]
    c, s = np.cos(0.5), np.sin(0.5)
    expected[:2, :2] = [[c, -s], [s, c]]
    pose = NS(position=position, orientation=orientation)
    for msgtype, msg in [
        ("geometry_msgs/msg/PoseStamped", NS(pose=pose)),
        ("geometry_msgs/msg/PoseWithCovarianceStamped", NS(pose=NS(pose=pose))),
        ("nav_msgs/msg/Odometry", NS(pose=NS(pose=pose))),
        ("geometry_msgs/msg/TransformStamped",
         NS(transform=NS(translation=position, rotation=orientation))),
    ]:
        np.testing.assert_allclose(dec.pose_matrix(msgtype, msg, "t"), expected, atol=1e-12)
    zero = NS(pose=NS(position=position, orientation=NS(x=0.0, y=0.0, z=0.0, w=0.0)))
    with pytest.raises(DatasetError, match=r"t: non-finite pose or zero quaternion"):
        dec.pose_matrix("geometry_msgs/msg/PoseStamped", zero, "t")

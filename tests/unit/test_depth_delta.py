"""The zstd-delta depth codec: lossless on any uint16 image, smaller than PNG on sensor-like
depth, and every defect of its bytes a ProtocolError that names the codec."""

from __future__ import annotations

import numpy as np
import pytest

from cpslam import protocol as P
from cpslam.protocol.depth_delta import decode_depth_delta, encode_depth_delta
from cpslam.protocol.images import image_to_wire
from cpslam.protocol.quant import compress


def _sensor_depth(rng: np.random.Generator, width: int = 160, height: int = 120) -> np.ndarray:
    """Inverse depth (steps of 1 mm/m²) of a slanted wall with Kinect-like noise, a box in
    front of it and holes, as uint16 [height, width]."""
    u = np.linspace(0.0, 1.0, width)[None, :]
    v = np.linspace(0.0, 1.0, height)[:, None]
    z = 1.0 + 2.0 * u + 0.5 * v
    z[height // 4: height // 2, width // 3: width // 2] = 0.8  # an edge all round
    z = z + rng.normal(0.0, 0.6e-3, z.shape) * z**2
    z[rng.random(z.shape) < 0.03] = 0.0  # scattered holes
    z[:10, :20] = 0.0  # and a block of them
    return np.where(z > 0, np.rint(1000.0 / np.where(z > 0, z, 1.0)), 0).astype(np.uint16)


@pytest.mark.parametrize("case", ["sensor", "random", "zeros", "full", "row", "column", "pixel"])
def test_round_trip_is_exact(case: str) -> None:
    rng = np.random.default_rng(0)
    depth = {
        "sensor": lambda: _sensor_depth(rng),
        "random": lambda: rng.integers(0, 65536, (37, 53)).astype(np.uint16),
        "zeros": lambda: np.zeros((8, 9), np.uint16),
        "full": lambda: np.full((8, 9), 65535, np.uint16),
        "row": lambda: rng.integers(0, 65536, (1, 40)).astype(np.uint16),
        "column": lambda: np.cumsum(rng.integers(0, 300, (40, 1)), axis=0).astype(np.uint16),
        "pixel": lambda: np.array([[65535]], np.uint16),
    }[case]()
    back = decode_depth_delta(encode_depth_delta(depth), depth.shape[1], depth.shape[0])
    assert back.dtype == np.uint16 and np.array_equal(back, depth)


def test_smaller_than_png_on_sensor_depth() -> None:
    sizes = []
    for seed in range(3):
        depth = _sensor_depth(np.random.default_rng(seed))
        sizes.append((len(encode_depth_delta(depth)), len(image_to_wire(depth, "depth")["data"])))
    # a quarter smaller on 7-Scenes depth; the margin is for other zlib and zstd builds
    assert all(delta < 0.9 * png for delta, png in sizes), sizes


def test_keyframe_images_carry_either_codec() -> None:
    depth = _sensor_depth(np.random.default_rng(1))
    fields = dict(agent_id="a", kf_id=1, fx=80.0, fy=80.0, cx=79.5, cy=59.5, width=160,
                  height=120, depth=depth)
    for codec in ("zstd-delta", "png"):
        msg = P.KeyframeImage(depth_codec=codec, **fields)
        back = P.decode(P.encode(msg))
        assert back.depth_codec == codec and np.array_equal(back.depth, depth)
    assert P.KeyframeImage(**fields).depth_codec == "zstd-delta"


def _defect(name: str, depth: np.ndarray) -> bytes:
    n = depth.size
    codes = np.zeros(n, np.uint8)
    if name == "not zstd":
        return b"\x89PNG\r\n\x1a\n" + bytes(40)
    if name == "short":
        return compress(codes[: n - 1].tobytes(), 3)
    if name == "missing raw":
        codes[5] = 255
        return compress(codes.tobytes(), 3)
    if name == "extra bytes":
        return compress(codes.tobytes() + b"\x00\x00", 3)
    if name == "bomb":
        return compress(bytes(3 * n + 1), 3)
    if name == "below zero":
        codes[depth.shape[1]] = 1  # -1 below a 0 in the first row
        return compress(codes.tobytes(), 3)
    if name == "above uint16":
        codes[0] = 255
        codes[depth.shape[1]] = 2  # +1 below a raw 65535
        return compress(codes.tobytes() + np.array([65535], "<u2").tobytes(), 3)
    raise AssertionError(name)


@pytest.mark.parametrize(
    ("name", "needle"),
    [("not zstd", "zstd frame"), ("short", "fewer than"), ("missing raw", "raw values"),
     ("extra bytes", "raw values"), ("bomb", "over the cap"), ("below zero", "uint16 range"),
     ("above uint16", "uint16 range")],
)
def test_defects_are_protocol_errors(name: str, needle: str) -> None:
    depth = np.zeros((6, 7), np.uint16)
    with pytest.raises(P.ProtocolError, match=f"depth delta: .*{needle}"):
        decode_depth_delta(_defect(name, depth), 7, 6)


def test_a_message_checks_the_codec_it_declares() -> None:
    msg = P.KeyframeImage(agent_id="a", kf_id=1, fx=8.0, fy=8.0, cx=3.5, cy=2.5, width=7,
                          height=6, depth=np.zeros((6, 7), np.uint16))
    wire = msg.model_dump(mode="python")
    wire["depth"]["codec"] = "png"
    with pytest.raises(ValueError, match="differs from depth_codec"):
        P.KeyframeImage.model_validate(wire)
    wire["depth"]["codec"] = "jpeg"
    wire["depth_codec"] = "jpeg"
    with pytest.raises(ValueError, match="depth_codec"):
        P.KeyframeImage.model_validate(wire)
    with pytest.raises(P.ProtocolError, match="uint16"):
        encode_depth_delta(np.zeros((6, 7), np.int32))


def test_a_tiny_frame_of_a_huge_image_decodes_in_bounded_memory() -> None:
    """A few hundred bytes may declare a large image: decoding it takes a few bytes per pixel
    (the payload, masks, the uint16 result, column blocks), not int64 arrays of it."""
    import tracemalloc

    width, height = 4096, 1024
    data = compress(bytes(width * height), 3)
    assert len(data) < 1000
    tracemalloc.start()
    try:
        depth = decode_depth_delta(data, width, height)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert depth.shape == (height, width) and not depth.any()
    assert peak < 10 * width * height, peak / (width * height)

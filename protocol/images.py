"""Images on the wire: a msgpack map {"codec": ..., "data": bin}.

Colour is RGB uint8 [H, W, 3] in memory, PNG or JPEG on the wire, and converted to OpenCV's
BGR only here, at the codec edge. Depth is uint16, lossless: a 16-bit grey PNG or
``zstd-delta`` (`cpslam.protocol.depth_delta`, a quarter smaller). Before OpenCV sees PNG or
JPEG bytes the header is parsed and its width, height, bit depth and channel count are
checked against what the message declares, so a tiny file cannot decode into a huge image;
``zstd-delta`` data is decompressed to at most the declared size.
"""

from __future__ import annotations

import math
from typing import Any, Literal

import cv2
import numpy as np

from cpslam.protocol.depth_delta import decode_depth_delta, encode_depth_delta
from cpslam.protocol.errors import ProtocolError

__all__ = [
    "CODECS",
    "DEPTH_CODECS",
    "MAX_PIXELS",
    "WIRE_DEPTH_SCALE",
    "depth_coding",
    "image_from_wire",
    "image_to_wire",
    "read_header",
]

CODECS: tuple[str, ...] = ("png", "jpeg")
"""Colour image codecs allowed on the wire."""

DEPTH_CODECS: tuple[str, ...] = ("png", "zstd-delta")
"""Depth image codecs allowed on the wire (both lossless)."""

MAX_PIXELS = 4096 * 4096
"""Largest image (width x height) accepted."""

WIRE_DEPTH_SCALE = 1000.0
"""Depth units per metre of our agents' image replies: 1 mm steps, coarser than a keyframe
store's 0.2 mm and a third smaller in PNG (`depth_coding` trades them for inverse depth)."""

ImageKind = Literal["rgb", "depth"]

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_GREY, _PNG_RGB = 0, 2  # IHDR colour types
# JPEG start-of-frame markers (baseline, extended, progressive, lossless, ...)
_JPEG_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}
_JPEG_STANDALONE = {0x01, *range(0xD0, 0xD8)}
_PNG_LEVEL = 6  # zlib level: a fifth smaller than 3 on depth for 2x the time; 9 is 15x slower


def depth_coding(step_mm_per_m2: float) -> tuple[float, Literal["linear", "inverse"]]:
    """``(depth_scale, depth_encoding)`` of a keyframe image whose depth goes in steps of
    ``step_mm_per_m2`` x z² mm: inverse depth with ``depth_scale = 1000 / step`` (a value u
    stands for ``depth_scale / u`` m), or at 0 linear millimetres (`WIRE_DEPTH_SCALE`).

    A structured-light or time-of-flight sensor's depth noise grows as the square of the
    depth (about 1.5 mm at 1 m, 6 mm at 2 m for a Kinect), so steps that grow the same way
    keep what a registration can use where it matters; and a plane's inverse depth changes
    linearly across the image, which PNG's predictors store in few bytes."""
    if not (math.isfinite(step_mm_per_m2) and step_mm_per_m2 >= 0):
        raise ValueError(f"depth_coding: step_mm_per_m2 must be >= 0, got {step_mm_per_m2}")
    if step_mm_per_m2 == 0:
        return WIRE_DEPTH_SCALE, "linear"
    return 1000.0 / step_mm_per_m2, "inverse"


def image_to_wire(
    image: np.ndarray, kind: ImageKind, codec: str = "png", jpeg_quality: int = 90
) -> dict[str, Any]:
    """Compress `image` (RGB uint8 [H, W, 3] or depth uint16 [H, W]) to its wire form."""
    allowed = DEPTH_CODECS if kind == "depth" else CODECS
    if codec not in allowed:
        raise ProtocolError(f"{kind} image codec must be one of {allowed}, got {codec!r}")
    if codec == "zstd-delta":
        return {"codec": codec, "data": encode_depth_delta(image)}
    if kind == "depth":
        ok, buf = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, _PNG_LEVEL])
    else:
        bgr = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
        if codec == "jpeg":
            ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)])
        else:
            ok, buf = cv2.imencode(".png", bgr, [cv2.IMWRITE_PNG_COMPRESSION, _PNG_LEVEL])
    if not ok:
        raise ProtocolError(f"OpenCV could not encode the {kind} image as {codec}")
    return {"codec": codec, "data": buf.tobytes()}


def image_from_wire(obj: Any, kind: ImageKind, width: int, height: int) -> np.ndarray:
    """Decode a wire image that must be `width` x `height` of the given kind.

    Returns RGB uint8 [H, W, 3] for ``"rgb"`` or uint16 [H, W] for ``"depth"``.
    Raises `ProtocolError` on any defect (never an OpenCV error).
    """
    if not isinstance(obj, dict) or set(obj) != {"codec", "data"}:
        raise ProtocolError(f"{kind} image: expected a map with keys codec/data")
    codec, data = obj["codec"], obj["data"]
    allowed = DEPTH_CODECS if kind == "depth" else CODECS
    if codec not in allowed:
        raise ProtocolError(f"{kind} image: codec must be one of {allowed}, got {codec!r:.40}")
    if not isinstance(data, bytes):
        raise ProtocolError(f"{kind} image: data must be bin, got {type(data).__name__}")
    if width * height > MAX_PIXELS:
        raise ProtocolError(f"{kind} image: {width}x{height} exceeds {MAX_PIXELS} pixels")
    if codec == "zstd-delta":
        return decode_depth_delta(data, width, height)
    got_codec, got_w, got_h, bits, channels = read_header(data)
    want_bits, want_channels = (16, 1) if kind == "depth" else (8, 3)
    if got_codec != codec:
        raise ProtocolError(f"{kind} image: declared {codec} but the data is {got_codec}")
    if (got_w, got_h) != (width, height):
        raise ProtocolError(f"{kind} image: expected {width}x{height}, header says {got_w}x{got_h}")
    if (bits, channels) != (want_bits, want_channels):
        raise ProtocolError(
            f"{kind} image: expected {want_bits}-bit with {want_channels} channel(s), "
            f"header says {bits}-bit with {channels}"
        )
    try:
        decoded = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    except cv2.error as exc:
        raise ProtocolError(
            f"{kind} image: OpenCV could not decode the {codec} data: {exc}"
        ) from None
    want_shape = (height, width) if kind == "depth" else (height, width, 3)
    want_dtype = np.uint16 if kind == "depth" else np.uint8
    if decoded is None or decoded.shape != want_shape or decoded.dtype != want_dtype:
        raise ProtocolError(f"{kind} image: the {codec} data does not decode to {want_shape}")
    if kind == "rgb":
        decoded = cv2.cvtColor(decoded, cv2.COLOR_BGR2RGB)
    return decoded


def read_header(data: bytes) -> tuple[str, int, int, int, int]:
    """(codec, width, height, bits per sample, channels) from a PNG or JPEG header."""
    if data.startswith(_PNG_SIGNATURE):
        return _png_header(data)
    if data.startswith(b"\xff\xd8"):
        return _jpeg_header(data)
    raise ProtocolError("image data is neither PNG nor JPEG")


def _png_header(data: bytes) -> tuple[str, int, int, int, int]:
    # IHDR must be the first chunk: length 13, then width, height, bit depth, colour type
    if len(data) < 33 or data[8:16] != b"\x00\x00\x00\x0dIHDR":
        raise ProtocolError("PNG image: missing IHDR header")
    width = int.from_bytes(data[16:20], "big")
    height = int.from_bytes(data[20:24], "big")
    bits, colour = data[24], data[25]
    channels = {_PNG_GREY: 1, _PNG_RGB: 3}.get(colour)
    if channels is None:
        raise ProtocolError(f"PNG image: colour type {colour} is not grey or RGB")
    return "png", width, height, bits, channels


def _jpeg_header(data: bytes) -> tuple[str, int, int, int, int]:
    pos = 2
    while pos + 4 <= len(data):
        if data[pos] != 0xFF:
            raise ProtocolError(f"JPEG image: bad marker at byte {pos}")
        marker = data[pos + 1]
        if marker == 0xFF:  # fill byte
            pos += 1
            continue
        if marker in _JPEG_STANDALONE:
            pos += 2
            continue
        length = int.from_bytes(data[pos + 2 : pos + 4], "big")
        if marker in _JPEG_SOF:
            if length < 8 or pos + 10 > len(data):
                raise ProtocolError("JPEG image: truncated frame header")
            bits = data[pos + 4]
            height = int.from_bytes(data[pos + 5 : pos + 7], "big")
            width = int.from_bytes(data[pos + 7 : pos + 9], "big")
            return "jpeg", width, height, bits, data[pos + 9]
        if marker == 0xDA or length < 2:  # scan data before any frame header
            break
        pos += 2 + length
    raise ProtocolError("JPEG image: no frame header found")

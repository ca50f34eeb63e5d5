"""A lossless codec for uint16 depth images: vertical deltas in one byte, zstd-compressed.

Each pixel is predicted by the pixel above it (0 in the first row). A residual of at most
127 either way goes as one zig-zag byte; any other pixel (an edge, a hole's border) goes as
the escape byte 255 and its raw value, in row-major order after all the bytes. The bytes and
the raw values are one zstd frame.

Why not PNG: a sensor's depth noise fills the low bits of every pixel, so the residuals'
entropy is set by the noise whatever the predictor; PNG still spends extra on 16-bit samples
(it filters them byte by byte, so a carry in the low byte leaks into the high one) and on
deflate. On 7-Scenes depth (320 x 240, inverse-depth steps of 0.65-1.3 mm/m²) this codec is
a quarter smaller than PNG at zlib level 6. A predictor that uses the left neighbour too (LOCO-I's
median) saves another 5 % but decodes pixel by pixel; this one decodes with column-wise
cumulative sums.
"""

from __future__ import annotations

import numpy as np

from cpslam.protocol.errors import ProtocolError
from cpslam.protocol.quant import compress, decompress

__all__ = ["DEPTH_DELTA_LEVEL", "decode_depth_delta", "encode_depth_delta"]

DEPTH_DELTA_LEVEL = 19
"""zstd level of the codec: 7 % smaller than level 9 on 7-Scenes depth, for about 30 ms per
320 x 240 image on one core (3 x PNG's time; once per keyframe sent)."""

_ESCAPE = 255


def encode_depth_delta(depth: np.ndarray, level: int = DEPTH_DELTA_LEVEL) -> bytes:
    """The codec's bytes for depth uint16 [H, W]."""
    if depth.ndim != 2 or depth.dtype != np.uint16:
        raise ProtocolError(f"depth delta: expected uint16 [H, W], got {depth.dtype} "
                            f"{list(depth.shape)}")
    value = depth.astype(np.int32)
    above = np.zeros_like(value)
    above[1:] = value[:-1]
    residual = value - above
    zigzag = np.where(residual >= 0, 2 * residual, -2 * residual - 1)
    escape = zigzag >= _ESCAPE
    codes = np.where(escape, _ESCAPE, zigzag).astype(np.uint8)
    raw = depth[escape].astype("<u2")
    return compress(codes.tobytes() + raw.tobytes(), level)


def decode_depth_delta(data: bytes, width: int, height: int) -> np.ndarray:
    """Depth uint16 [height, width] from the codec's bytes; `ProtocolError` on any defect."""
    n = width * height
    try:
        payload = decompress(data, 3 * n)
    except ProtocolError as exc:
        raise ProtocolError(f"depth delta: {exc}") from None
    if len(payload) < n:
        raise ProtocolError(f"depth delta: {len(payload)} bytes, fewer than the {n} pixels")
    codes = np.frombuffer(payload, np.uint8, count=n).reshape(height, width)
    escape = codes == _ESCAPE
    n_raw = int(escape.sum())
    if len(payload) != n + 2 * n_raw:
        raise ProtocolError(f"depth delta: {len(payload)} bytes, expected {n + 2 * n_raw} "
                            f"for {n} pixels with {n_raw} raw values")
    raw = np.frombuffer(payload, "<u2", count=n_raw, offset=n)
    code = codes.astype(np.int64)
    delta = np.where(code & 1, -(code + 1) // 2, code // 2)
    delta[escape] = 0
    base = np.zeros((height, width), np.int64)
    base[escape] = raw
    # a pixel is the raw value of the last escape at or above it in its column (0 above the
    # first row) plus the deltas below that escape down to it
    running = np.cumsum(delta, axis=0)
    rows = np.where(escape, np.arange(height)[:, None], -1)
    last = np.maximum.accumulate(rows, axis=0)
    cols = np.broadcast_to(np.arange(width), (height, width))
    at = np.maximum(last, 0)
    start = np.where(last >= 0, base[at, cols] - running[at, cols], 0)
    value = start + running
    if value.min(initial=0) < 0 or value.max(initial=0) > np.iinfo(np.uint16).max:
        raise ProtocolError("depth delta: the deltas leave the uint16 range")
    return value.astype(np.uint16)

"""int8 quantisation with one scale per row, and zstd framing of whole payloads.

Quantisation: ``q = round(x / scale)`` with ``scale = max|row| / 127`` per row (axis 0; a 0-d
or 1-d array is one row), so every element is off by at most ``scale / 2`` = max|row| / 254
and an all-zero row stays exact (scale 0, q 0).

Compression: a payload is one zstd frame whose header carries the decompressed size; the
reader refuses a frame that declares (or yields) more than the caller's cap before it
allocates the output, so a small hostile frame cannot make us reserve gigabytes.
"""

from __future__ import annotations

import math

import numpy as np
import zstandard

from cpslam.protocol.errors import ProtocolError

__all__ = [
    "ZSTD_MAGIC",
    "add_delta",
    "compress",
    "decompress",
    "dequantise_rows",
    "is_compressed",
    "quantise_rows",
]

ZSTD_MAGIC = b"\x28\xb5\x2f\xfd"
"""First four bytes of a zstd frame (a msgpack message starts with a map byte instead)."""

_QMAX = 127


def quantise_rows(
    x: np.ndarray, levels: int = _QMAX, scale_dtype: type = np.float32
) -> tuple[np.ndarray, np.ndarray]:
    """(q int8 like `x`, scale [rows] of `scale_dtype`) with ``x ~ q * scale`` row by row
    (axis 0) and ``|q| <= levels`` (1-127): fewer levels leave codes that zstd packs into fewer
    bits, each element then off by at most max|row| / (2 levels). A float16 scale is rounded
    up, so no code overflows, and capped at float16's largest (rows beyond it are clipped)."""
    if not 1 <= levels <= _QMAX:
        raise ValueError(f"quantise_rows: levels must be in 1..{_QMAX}, got {levels}")
    x = np.asarray(x, np.float32)
    rows = x.reshape(_rows_shape(x.shape))
    if not np.isfinite(rows).all():
        raise ValueError("quantise_rows: values must be finite")
    peak = np.abs(rows).max(axis=1) if rows.shape[1] else np.zeros(rows.shape[0], np.float32)
    scale = (peak / levels).astype(np.float32)
    if np.dtype(scale_dtype) == np.float16:
        scale = _float16_up(scale)
    safe = np.where(scale > 0, scale, 1.0).astype(np.float32)[:, None]
    q = np.clip(np.rint(rows / safe), -levels, levels).astype(np.int8)
    return q.reshape(x.shape), scale.astype(scale_dtype)


def _float16_up(scale: np.ndarray) -> np.ndarray:
    """The float16 values nearest `scale` (float32, >= 0) from above, as float32 (capped)."""
    capped = np.minimum(scale, np.finfo(np.float16).max)
    half = capped.astype(np.float16)
    low = half.astype(np.float32) < capped
    half[low] = np.nextafter(half[low], np.float16(np.inf))
    return half.astype(np.float32)


def dequantise_rows(q: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """float32 ``q * scale`` (the inverse of `quantise_rows`, up to its rounding)."""
    rows = q.reshape(_rows_shape(q.shape)).astype(np.float32)
    if scale.shape != (rows.shape[0],):
        raise ValueError(
            f"dequantise_rows: {rows.shape[0]} rows need {rows.shape[0]} scales, "
            f"got shape {list(scale.shape)}"
        )
    return (rows * scale.astype(np.float32)[:, None]).reshape(q.shape)


def _rows_shape(shape: tuple[int, ...]) -> tuple[int, int]:
    """(rows, width) of an array quantised row by row: axis 0 for 2-D and up, else one row
    (explicit: reshape cannot infer a width for zero rows)."""
    if len(shape) >= 2:
        return shape[0], math.prod(shape[1:])
    return 1, math.prod(shape)


def add_delta(base: dict[str, np.ndarray], delta: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """float32 ``base + delta`` by name: the one sum both ends of a decoder delta compute, so
    the sender knows bit for bit what the receiver holds."""
    return {
        k: (np.asarray(base[k], np.float32) + np.asarray(v, np.float32)).astype(np.float32)
        for k, v in delta.items()
    }


def is_compressed(data: bytes) -> bool:
    """Whether `data` is a zstd frame (our compressed payloads) rather than plain msgpack."""
    return data[:4] == ZSTD_MAGIC


def compress(data: bytes, level: int) -> bytes:
    """One zstd frame of `data` at `level` (1-22), with its size in the header."""
    return zstandard.ZstdCompressor(level=level, write_content_size=True).compress(data)


def decompress(data: bytes, max_size: int) -> bytes:
    """The payload of a zstd frame of at most `max_size` bytes; ProtocolError otherwise."""
    try:
        params = zstandard.get_frame_parameters(data)
    except zstandard.ZstdError as exc:
        raise ProtocolError(f"decode: bad zstd frame header ({exc})") from None
    size = params.content_size
    if size == zstandard.CONTENTSIZE_UNKNOWN or size == zstandard.CONTENTSIZE_ERROR:
        raise ProtocolError("decode: zstd frame does not declare its decompressed size")
    if size > max_size:
        raise ProtocolError(f"decode: zstd frame declares {size} bytes, over the cap of {max_size}")
    try:
        out = zstandard.ZstdDecompressor().decompress(data, max_output_size=max_size)
    except zstandard.ZstdError as exc:
        raise ProtocolError(f"decode: corrupt zstd frame ({exc})") from None
    if len(out) != size:
        raise ProtocolError(f"decode: zstd frame yields {len(out)} bytes, declares {size}")
    return out

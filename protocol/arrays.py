"""Arrays on the wire: a msgpack map {"dtype": str, "shape": [int, ...], "data": bin} and,
for elements wider than a byte, an optional "filter".

`data` holds the C-order elements in little-endian byte order; `dtype` is one of `DTYPES`.
A filter rearranges those bytes, losslessly and at the same length, so that zstd finds more to
compress: ``planes`` stores byte 0 of every element, then byte 1 of every element, and so on
(sign, exponent and high digits of neighbouring values sit together); ``delta-planes`` does
the same to the first differences of an integer array, wrapping (sorted ids become small
steps). Our encoder writes ``delta-planes`` for 1-d integer arrays (id lists) and ``planes``
for any other array of two or more multi-byte elements. Decoding checks the declared shape
against the byte count *before* anything is allocated, so a hostile header cannot make us
reserve memory it does not pay for.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from pydantic_core import core_schema

from cpslam.protocol.errors import ProtocolError

__all__ = [
    "DTYPES",
    "FILTERS",
    "FIXED_POINT_MAX",
    "MAX_DIM",
    "MAX_NDIM",
    "ArraySpec",
    "array_from_wire",
    "array_to_wire",
    "check_rigid",
]

DTYPES: tuple[str, ...] = (
    "int8",
    "uint8",
    "uint16",
    "int32",
    "int64",
    "float16",
    "float32",
    "float64",
    "bool",
)
"""Element types allowed on the wire (numpy names)."""

MAX_NDIM = 8
"""Most dimensions an array may declare."""

MAX_DIM = 2**31 - 1
"""Largest single dimension an array may declare."""

FILTERS: tuple[str, ...] = ("planes", "delta-planes")
"""Byte rearrangements an array's data may carry (see the module docstring)."""

FIXED_POINT_MAX = 2**22
"""Most grid steps a fixed-point value (`ArraySpec.grid`) may have: float32 values up to this
many steps round-trip exactly through the int32 counts."""

_WIRE_KEYS = frozenset(("dtype", "shape", "data"))
_FILTERED_KEYS = frozenset(("dtype", "shape", "data", "filter"))
_RIGID_TOL = 1e-3  # poses are often optimised in float32, so orthonormality is loose


def array_to_wire(array: np.ndarray) -> dict[str, Any]:
    """Wire form of an array: {"dtype", "shape", "data"} with little-endian C-order bytes, plus
    "filter" (`FILTERS`) for elements wider than a byte: delta-planes for 1-d integer arrays,
    planes for the rest."""
    name = array.dtype.name
    if name not in DTYPES:
        raise ProtocolError(f"array dtype {name!r} is not allowed on the wire (allowed: {DTYPES})")
    little = np.ascontiguousarray(array, dtype=np.dtype(name).newbyteorder("<"))
    wire = {"dtype": name, "shape": list(array.shape)}
    if little.dtype.itemsize == 1 or little.size < 2:
        return {**wire, "data": little.tobytes()}
    flat = little.reshape(-1)
    if little.dtype.kind in "iu" and little.ndim == 1:
        steps = flat.copy()
        steps[1:] = flat[1:] - flat[:-1]  # wraps in the dtype, undone by a wrapping cumsum
        return {**wire, "data": _to_planes(steps), "filter": "delta-planes"}
    return {**wire, "data": _to_planes(flat), "filter": "planes"}


def _to_planes(flat: np.ndarray) -> bytes:
    """Byte k of every element, for k = 0 .. itemsize - 1, one plane after the other."""
    return flat.view(np.uint8).reshape(-1, flat.dtype.itemsize).T.tobytes()


def _from_planes(data: bytes, dtype: np.dtype) -> np.ndarray:
    """The flat array whose byte planes `data` holds (the inverse of `_to_planes`)."""
    planes = np.frombuffer(data, np.uint8).reshape(dtype.itemsize, -1)
    return np.ascontiguousarray(planes.T).view(dtype).reshape(-1)


def array_from_wire(obj: Any, dtype: str | None = None) -> np.ndarray:
    """Array from its wire form, checked; `dtype` (if given) must match exactly.

    Returns a new writable, native-byte-order array. Raises `ProtocolError` on any defect.
    """
    if not isinstance(obj, dict):
        raise ProtocolError(f"array: expected a map with keys dtype/shape/data, got {_kind(obj)}")
    if set(obj) != _WIRE_KEYS and set(obj) != _FILTERED_KEYS:
        raise ProtocolError(
            f"array: expected keys ['data', 'dtype', 'shape'] and optionally 'filter', got "
            f"{sorted(map(str, obj))[:8]}"
        )
    name, shape, data = obj["dtype"], obj["shape"], obj["data"]
    if not isinstance(name, str) or name not in DTYPES:
        raise ProtocolError(f"array: dtype must be one of {DTYPES}, got {name!r:.40}")
    if dtype is not None and name != dtype:
        raise ProtocolError(f"array: expected dtype {dtype}, got {name}")
    if not isinstance(shape, list) or len(shape) > MAX_NDIM:
        raise ProtocolError(f"array: shape must be a list of at most {MAX_NDIM} ints")
    for dim in shape:
        # bool is an int subclass; reject it so a shape cannot be [True, 3]
        if type(dim) is not int or not 0 <= dim <= MAX_DIM:
            raise ProtocolError(f"array: shape entries must be ints in [0, {MAX_DIM}], got {shape}")
    if not isinstance(data, bytes):
        raise ProtocolError(f"array: data must be bin, got {_kind(data)}")
    wire_dtype = np.dtype(name).newbyteorder("<")
    expected = math.prod(shape) * wire_dtype.itemsize
    if expected != len(data):
        raise ProtocolError(
            f"array: shape {shape} of {name} needs {expected} bytes, data has {len(data)}"
        )
    if name == "bool" and data.translate(None, b"\x00\x01"):
        raise ProtocolError("array: bool data must hold only bytes 0 and 1")
    filt = obj.get("filter")
    if filt is None:
        flat = np.frombuffer(data, dtype=wire_dtype)
    elif filt not in FILTERS:
        raise ProtocolError(f"array: filter must be one of {FILTERS}, got {filt!r:.40}")
    elif wire_dtype.itemsize == 1:
        raise ProtocolError(f"array: filter {filt} needs elements wider than a byte, not {name}")
    elif filt == "delta-planes" and wire_dtype.kind not in "iu":
        raise ProtocolError(f"array: filter delta-planes is for integer arrays, not {name}")
    else:
        flat = _from_planes(data, wire_dtype)
        if filt == "delta-planes":
            flat = np.cumsum(flat, dtype=wire_dtype)  # wraps as the encoder's differences did
    return flat.reshape(shape).astype(np.dtype(name))


def check_rigid(T: np.ndarray, what: str) -> None:
    """Raise `ValueError` unless every [..., 4, 4] matrix in `T` is a rigid transform."""
    if T.size == 0:
        return
    bottom = T[..., 3, :]
    if np.abs(bottom - np.array([0.0, 0.0, 0.0, 1.0])).max() > 1e-6:
        raise ValueError(f"{what}: last row of a pose must be [0, 0, 0, 1]")
    R = T[..., :3, :3]
    with np.errstate(all="ignore"):  # huge finite entries overflow to inf, which fails below
        err = np.abs(np.swapaxes(R, -1, -2) @ R - np.eye(3)).max()
        flipped = (np.linalg.det(R) <= 0).any()
    if not err <= _RIGID_TOL or flipped:
        raise ValueError(f"{what}: rotation is not orthonormal (max |R^T R - I| = {err:.2e})")


@dataclass(frozen=True)
class ArraySpec:
    """Pydantic annotation for an array field: `Annotated[np.ndarray, ArraySpec(...)]`.

    From the wire (a dict) the dtype must match exactly. From Python any array-like is
    accepted and cast when the cast keeps values (ints must fit; floats may lose precision,
    e.g. float32 features become float16, but must stay finite where `finite` is set).

    Attributes:
        dtype: numpy name of the element type, one of `DTYPES`.
        shape: per dimension an int (fixed size) or a str (free size, named for the docs);
            None allows any shape with up to `MAX_NDIM` dimensions.
        finite: reject NaN and infinities.
        rigid: every trailing [4, 4] block must be a rigid transform (implies finite).
        grid: fixed point: a float field whose values travel as int32 multiples of `grid`
            (at most `FIXED_POINT_MAX` grid steps); from Python they are rounded to the
            grid, so a message holds what its receiver will decode.
        wire_dtype: a narrower float type the values travel as (e.g. float32 for a float64
            field); from Python they are rounded through it, as with `grid`.
    """

    dtype: str
    shape: tuple[int | str, ...] | None = None
    finite: bool = False
    rigid: bool = False
    grid: float | None = None
    wire_dtype: str | None = None

    def __get_pydantic_core_schema__(self, source: Any, handler: Any) -> core_schema.CoreSchema:
        return core_schema.no_info_plain_validator_function(
            self.validate,
            serialization=core_schema.plain_serializer_function_ser_schema(self.to_wire),
        )

    def describe(self) -> str:
        """Human form, e.g. ``float32 [N, 3]``."""
        dims = "any shape" if self.shape is None else "[" + ", ".join(map(str, self.shape)) + "]"
        return f"{self.dtype} {dims}"

    def to_wire(self, array: np.ndarray) -> dict[str, Any]:
        """Wire form of a field value (`array_to_wire` of it, of its grid counts for fixed
        point, or of it in the wire dtype)."""
        if self.grid is not None:
            return array_to_wire(self._counts(array).astype(np.int32))
        if self.wire_dtype is not None:
            return array_to_wire(np.asarray(array).astype(self.wire_dtype))
        return array_to_wire(array)

    def validate(self, value: Any) -> np.ndarray:
        """Checked array from a wire dict or an array-like; raises ValueError on defects."""
        if isinstance(value, dict):
            array = self._from_wire(value)
        else:
            array = self._narrow(self._coerce(value))
        self._check(array)
        return array

    def _from_wire(self, value: dict) -> np.ndarray:
        """The field's array from its wire form (the grid counts or the wire dtype's values)."""
        if self.grid is not None:
            counts = array_from_wire(value, "int32").astype(np.float64)
            if counts.size and np.abs(counts).max() > FIXED_POINT_MAX:
                raise ValueError(f"{self.describe()} in steps of {self.grid}: counts must be "
                                 f"within +-{FIXED_POINT_MAX}")
            return (counts * self.grid).astype(self.dtype)
        if self.wire_dtype is not None:
            return array_from_wire(value, self.wire_dtype).astype(self.dtype)
        return array_from_wire(value, self.dtype)

    def _narrow(self, array: np.ndarray) -> np.ndarray:
        """A Python-side array rounded as the wire will carry it (grid or wire dtype); ValueError
        beyond the fixed-point range."""
        if self.wire_dtype is not None:
            with np.errstate(over="ignore"):  # beyond the wire type: inf, refused if finite
                return array.astype(self.wire_dtype).astype(self.dtype)
        if self.grid is None:
            return array
        with np.errstate(all="ignore"):
            counts = self._counts(array)
        if not (np.abs(counts) <= FIXED_POINT_MAX).all():  # also catches NaN
            raise ValueError(
                f"{self.describe()} in steps of {self.grid}: values must be finite and within "
                f"+-{FIXED_POINT_MAX * self.grid:.6g}"
            )
        return (counts * self.grid + 0.0).astype(self.dtype)  # + 0.0: no -0.0, as decoded

    def _counts(self, array: np.ndarray) -> np.ndarray:
        """The nearest grid counts of `array` (float64, as many as its values)."""
        return np.rint(np.asarray(array, np.float64) / self.grid)

    def _coerce(self, value: Any) -> np.ndarray:
        try:
            array = np.asarray(value)
        except Exception as exc:  # noqa: BLE001 - any conversion failure is a bad input
            raise ValueError(f"expected an array, got {_kind(value)} ({exc})") from None
        src, dst = array.dtype, np.dtype(self.dtype)
        if src.kind not in "biuf":
            raise ValueError(f"expected a numeric array ({self.dtype}), got dtype {src}")
        if src != dst:
            if dst.kind == "b" and src.kind != "b":
                raise ValueError(f"expected dtype bool, got {src}")
            if dst.kind in "iu" and src.kind not in "biu":
                raise ValueError(f"expected integer dtype {dst}, got {src}")
            with np.errstate(all="ignore"):
                cast = array.astype(dst)
            if dst.kind in "iu" and not np.array_equal(cast, array):
                raise ValueError(f"values do not fit in {dst}")
            array = cast
        # not np.ascontiguousarray: it turns 0-d arrays into 1-d ones
        return array if array.flags.c_contiguous else array.copy(order="C")

    def _check(self, array: np.ndarray) -> None:
        if self.shape is None:
            if array.ndim > MAX_NDIM:
                raise ValueError(f"expected at most {MAX_NDIM} dimensions, got {array.ndim}")
        else:
            fixed_ok = all(
                isinstance(want, str) or want == got
                for want, got in zip(self.shape, array.shape, strict=False)
            )
            if array.ndim != len(self.shape) or not fixed_ok:
                raise ValueError(f"expected shape {self.describe()}, got {list(array.shape)}")
        if (self.finite or self.rigid) and array.dtype.kind == "f":
            if not np.isfinite(array).all():
                raise ValueError(f"{self.describe()} must be finite (found NaN or inf)")
        if self.rigid:
            check_rigid(array, "pose")


def _kind(value: Any) -> str:
    return type(value).__name__

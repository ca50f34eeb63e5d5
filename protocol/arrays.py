"""Arrays on the wire: a msgpack map {"dtype": str, "shape": [int, ...], "data": bin}.

`data` holds the C-order elements in little-endian byte order; `dtype` is one of `DTYPES`.
Decoding checks the declared shape against the byte count *before* anything is allocated, so
a hostile header cannot make us reserve memory it does not pay for in bytes.
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

_WIRE_KEYS = frozenset(("dtype", "shape", "data"))
_RIGID_TOL = 1e-3  # poses are often optimised in float32, so orthonormality is loose


def array_to_wire(array: np.ndarray) -> dict[str, Any]:
    """Wire form of an array: {"dtype", "shape", "data"} with little-endian C-order bytes."""
    name = array.dtype.name
    if name not in DTYPES:
        raise ProtocolError(f"array dtype {name!r} is not allowed on the wire (allowed: {DTYPES})")
    little = array.astype(np.dtype(name).newbyteorder("<"), copy=False)
    return {"dtype": name, "shape": list(array.shape), "data": little.tobytes(order="C")}


def array_from_wire(obj: Any, dtype: str | None = None) -> np.ndarray:
    """Array from its wire form, checked; `dtype` (if given) must match exactly.

    Returns a new writable, native-byte-order array. Raises `ProtocolError` on any defect.
    """
    if not isinstance(obj, dict):
        raise ProtocolError(f"array: expected a map with keys dtype/shape/data, got {_kind(obj)}")
    if set(obj) != _WIRE_KEYS:
        raise ProtocolError(f"array: expected keys ['data', 'dtype', 'shape'], got {sorted(obj)}")
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
    return np.frombuffer(data, dtype=wire_dtype).reshape(shape).astype(np.dtype(name))


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
    """

    dtype: str
    shape: tuple[int | str, ...] | None = None
    finite: bool = False
    rigid: bool = False

    def __get_pydantic_core_schema__(self, source: Any, handler: Any) -> core_schema.CoreSchema:
        return core_schema.no_info_plain_validator_function(
            self.validate,
            serialization=core_schema.plain_serializer_function_ser_schema(array_to_wire),
        )

    def describe(self) -> str:
        """Human form, e.g. ``float32 [N, 3]``."""
        dims = "any shape" if self.shape is None else "[" + ", ".join(map(str, self.shape)) + "]"
        return f"{self.dtype} {dims}"

    def validate(self, value: Any) -> np.ndarray:
        """Checked array from a wire dict or an array-like; raises ValueError on defects."""
        if isinstance(value, dict):
            array = array_from_wire(value, self.dtype)
        else:
            array = self._coerce(value)
        self._check(array)
        return array

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

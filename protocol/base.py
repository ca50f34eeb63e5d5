"""Base classes and shared field types of the wire messages."""

from __future__ import annotations

from typing import Annotated, Any, ClassVar

import numpy as np
from pydantic import AfterValidator, BaseModel, ConfigDict, Field, field_validator

from cpslam.protocol.arrays import ArraySpec
from cpslam.protocol.keys import check_id

__all__ = [
    "PROTOCOL_VERSION",
    "Id",
    "Seq",
    "KfId",
    "Count",
    "Pose",
    "Poses",
    "Tensors",
    "Float16Tensors",
    "Int8Tensors",
    "Scales",
    "Message",
    "WireModel",
]

PROTOCOL_VERSION = 9
"""Version every message carries; a decoder rejects any other. 2: zstd-framed payloads,
int8 sub-map features, decoder weights as deltas against a group round. 3: a group's decoder
goes to each member on its own key (``server/agent/<a>/group_decoder``). 4: keyframe
descriptors travel as float16, decoder weights may travel as float16 (``tensors_f16``). 5: an
image request names the fraction of the processed size it wants (``scale``); a sub-map delta
sends held points' features alone (``feature_ids``). 6: a keyframe image's depth may be
inverse depth (``depth_encoding``). 7: keyframe descriptors travel as int8 codes. 8: keyframe
depth may travel as vertical deltas in zstd (``depth_codec``). 9: arrays of multi-byte elements
may carry a byte-plane filter (``filter``); map point positions travel in fixed point (int32
counts of 0.5 mm), sub-map feature scales as float16, frame poses as float32."""

Id = Annotated[str, AfterValidator(lambda v: check_id(v, "id"))]
"""Agent, group or session id: 1-64 chars of [A-Za-z0-9_-] (usable as a key chunk)."""
Seq = Annotated[int, Field(ge=0, lt=2**63)]
Count = Annotated[int, Field(ge=0, lt=2**63)]
KfId = Annotated[int, Field(ge=0, lt=2**31)]  # keyframe ids also travel in int32 arrays

Pose = Annotated[np.ndarray, ArraySpec("float64", (4, 4), rigid=True)]
Poses = Annotated[np.ndarray, ArraySpec("float64", ("N", 4, 4), rigid=True)]

MAX_TENSORS = 256
MAX_TENSOR_NAME = 128
TensorName = Annotated[str, Field(min_length=1, max_length=MAX_TENSOR_NAME, pattern=r"^[\w.\-]+$")]
Tensors = Annotated[
    dict[TensorName, Annotated[np.ndarray, ArraySpec("float32", None, finite=True)]],
    Field(min_length=1, max_length=MAX_TENSORS),
]
"""Named float32 tensors (a torch state_dict flattened to numpy), at most 256 names."""
Float16Tensors = Annotated[
    dict[TensorName, Annotated[np.ndarray, ArraySpec("float16", None, finite=True)]],
    Field(min_length=1, max_length=MAX_TENSORS),
]
"""Named float16 tensors (parameters rounded to half precision)."""
Int8Tensors = Annotated[
    dict[TensorName, Annotated[np.ndarray, ArraySpec("int8", None)]],
    Field(min_length=1, max_length=MAX_TENSORS),
]
"""Named int8 tensors (quantised parameters, see `cpslam.protocol.quant`)."""
Scales = Annotated[
    dict[TensorName, Annotated[np.ndarray, ArraySpec("float32", ("R",), finite=True)]],
    Field(min_length=1, max_length=MAX_TENSORS),
]
"""Per name the float32 scale of each row (axis 0; one for a 0-d or 1-d tensor)."""


class WireModel(BaseModel):
    """Frozen, strict-keyed model whose equality compares arrays bit for bit."""

    model_config = ConfigDict(
        frozen=True,
        extra="forbid",
        allow_inf_nan=False,
        use_attribute_docstrings=True,
        arbitrary_types_allowed=True,
    )

    def __eq__(self, other: object) -> bool:
        if type(self) is not type(other):
            return NotImplemented
        return all(
            _same(getattr(self, name), getattr(other, name)) for name in type(self).model_fields
        )

    def __hash__(self) -> int:
        return hash(tuple(_hashable(getattr(self, name)) for name in type(self).model_fields))


class Message(WireModel):
    """A top-level wire message: a `type` literal (in each subclass) and a `version`."""

    max_bytes: ClassVar[int]
    """Largest encoded size accepted for this message type (bytes)."""

    version: int = PROTOCOL_VERSION
    """Protocol version; must equal `PROTOCOL_VERSION`."""

    @field_validator("version")
    @classmethod
    def _check_version(cls, value: int) -> int:
        if value != PROTOCOL_VERSION:
            raise ValueError(f"protocol version {value} is not {PROTOCOL_VERSION}")
        return value

    @classmethod
    def type_name(cls) -> str:
        """The wire name in the `type` field, e.g. ``"keyframe"``."""
        return cls.model_fields["type"].default


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return (
            isinstance(a, np.ndarray)
            and isinstance(b, np.ndarray)
            and a.dtype == b.dtype
            and a.shape == b.shape
            and a.tobytes() == b.tobytes()
        )
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, list | tuple) and isinstance(b, list | tuple):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b, strict=True))
    return a == b


def _hashable(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return (value.dtype.str, value.shape, value.tobytes())
    if isinstance(value, dict):
        return tuple((k, _hashable(v)) for k, v in value.items())
    if isinstance(value, list | tuple):
        return tuple(_hashable(v) for v in value)
    return value

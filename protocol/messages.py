"""Messages an agent sends: keyframes, sub-map deltas, decoder weights, frame poses (and,
re-exported, the keyframe image messages of `cpslam.protocol.image_messages`).

Every array field names its dtype and shape in its `Annotated` type (see `ArraySpec`);
every field's docstring gives units and frames and is what docs/protocol.md documents.
"""

from __future__ import annotations

from typing import Annotated, Literal

import numpy as np
from pydantic import Field, field_validator, model_validator

from cpslam.protocol.arrays import ArraySpec
from cpslam.protocol.base import (
    Count,
    Float16Tensors,
    Id,
    Int8Tensors,
    KfId,
    Message,
    Pose,
    Scales,
    Seq,
    Tensors,
)
from cpslam.protocol.image_messages import KeyframeImage, KeyframeImageRequest
from cpslam.protocol.quant import dequantise_rows

__all__ = [
    "KeyframeMsg",
    "SubmapDelta",
    "DecoderWeights",
    "FramePoses",
    "KeyframeImageRequest",
    "KeyframeImage",
    "XYZ_STEP_M",
    "check_points",
    "descriptor_codes",
]

MB = 1 << 20
MAX_DESCRIPTOR = 65536
DESCRIPTOR_PEAK = 127
"""A descriptor's largest magnitude as an int8 code (`descriptor_codes`)."""
MAX_FEATURE_DIM = 1024

Ids = Annotated[np.ndarray, ArraySpec("int64", ("N",))]
KfIds = Annotated[np.ndarray, ArraySpec("int32", ("N",))]
XYZ_STEP_M = 0.0005
"""Map point positions travel as int32 counts of this many metres (fixed point, so each is
off by at most a quarter millimetre, far below depth noise and point spacing)."""

Xyz = Annotated[np.ndarray, ArraySpec("float32", ("N", 3), finite=True, grid=XYZ_STEP_M)]
Features = Annotated[np.ndarray, ArraySpec("float16", ("N", "F"), finite=True)]
Int8Features = Annotated[np.ndarray, ArraySpec("int8", ("N", "F"))]
RowScales = Annotated[np.ndarray, ArraySpec("float16", ("N",), finite=True)]
Colors = Annotated[np.ndarray, ArraySpec("uint8", ("N", 3))]
RemovedIds = Annotated[np.ndarray, ArraySpec("int64", ("M",))]
UpdatedIds = Annotated[np.ndarray, ArraySpec("int64", ("U",))]


class KeyframeMsg(Message):
    """A new keyframe: pose, global image descriptor and link to the previous keyframe."""

    max_bytes = 1 * MB
    type: Literal["keyframe"] = "keyframe"
    agent_id: Id
    """Sending agent."""
    seq: Seq
    """Agent's message sequence number (one counter for all its agent -> server messages)."""
    incarnation: Seq = 0
    """Random id the agent drew at its start (kept by a resumed agent); see docs/protocol.md."""
    kf_id: KfId
    """Keyframe id, unique per agent, increasing."""
    frame_index: Count
    """Index of the keyframe's frame in the agent's RGB-D stream."""
    stamp: float
    """Timestamp of the frame (s, the dataset's clock)."""
    world_epoch: Count = 0
    """Epoch of the last `ServerUpdate` the agent applied; 0 = its own world (first camera)."""
    T_world_cam: Pose
    """Camera-to-world pose in the agent's current world frame (float64 [4, 4], m)."""
    T_prev_kf_kf: Pose | None = None
    """Pose of this keyframe in the previous keyframe's camera frame; None for the first."""
    descriptor: Annotated[np.ndarray, ArraySpec("int8", ("D",))]
    """Global image descriptor's direction as int8 codes [D], 1 <= D <= 65536, not all zero
    (`unit_descriptor` normalises it; `descriptor_codes` scales the largest magnitude to 127,
    which moves cosines between descriptors by less than 1e-3 on real frames).
    From Python a float descriptor is turned into its codes."""
    n_points: Count = 0
    """Number of map points anchored to this keyframe when it was published."""

    @field_validator("descriptor", mode="before")
    @classmethod
    def _codes(cls, value: object) -> object:
        if isinstance(value, np.ndarray) and value.dtype.kind == "f":
            return descriptor_codes(value)
        return value

    @model_validator(mode="after")
    def _check(self) -> KeyframeMsg:
        d = self.descriptor.shape[0]
        if not 1 <= d <= MAX_DESCRIPTOR:
            raise ValueError(f"descriptor: length must be in [1, {MAX_DESCRIPTOR}], got {d}")
        if not self.descriptor.any():
            raise ValueError("descriptor: must not be all zero (it gives a direction)")
        return self

    def unit_descriptor(self) -> np.ndarray:
        """The descriptor as float32 [D] of unit L2 norm."""
        d = self.descriptor.astype(np.float32)
        return d / np.linalg.norm(d)


def descriptor_codes(descriptor: np.ndarray) -> np.ndarray:
    """int8 codes [D] of a descriptor's direction: its largest magnitude becomes
    `DESCRIPTOR_PEAK` (ValueError for a descriptor that is empty, not finite or all zero)."""
    d = np.asarray(descriptor, np.float64)
    if d.ndim != 1 or not d.size:
        raise ValueError(f"descriptor: expected a vector [D], got shape {d.shape}")
    if not np.isfinite(d).all() or not d.any():
        raise ValueError("descriptor: must be finite and not all zero")
    return np.round(d * (DESCRIPTOR_PEAK / np.abs(d).max())).astype(np.int8)


def check_points(
    point_ids: np.ndarray,
    anchor_kf_ids: np.ndarray,
    xyz_local: np.ndarray,
    features: np.ndarray,
    colors: np.ndarray,
    removed_ids: np.ndarray,
) -> None:
    """Cross-field checks of a point set; raises ValueError naming the field."""
    n = point_ids.shape[0]
    for name, array in (
        ("anchor_kf_ids", anchor_kf_ids),
        ("xyz_local", xyz_local),
        ("features", features),
        ("colors", colors),
    ):
        if array.shape[0] != n:
            raise ValueError(f"{name}: has {array.shape[0]} rows, point_ids has {n}")
    if features.shape[1] > MAX_FEATURE_DIM:
        raise ValueError(f"features: F must be <= {MAX_FEATURE_DIM}, got {features.shape[1]}")
    ordered = _sorted_unique(point_ids, "point_ids")
    for name, ids in (("removed_ids", removed_ids), ("anchor_kf_ids", anchor_kf_ids)):
        if ids.size and ids.min() < 0:
            raise ValueError(f"{name}: ids must be >= 0")
    if _any_in(ordered, removed_ids):
        raise ValueError("removed_ids: an id cannot be both updated and removed")


def _sorted_unique(ids: np.ndarray, name: str) -> np.ndarray:
    """`ids` sorted, once checked to be >= 0 and unique (ValueError naming `name`)."""
    if ids.size and ids.min() < 0:
        raise ValueError(f"{name}: ids must be >= 0")
    # sort-based: numpy's hash-based unique is several times slower on 1e5+ ids
    ordered = np.sort(ids)
    if (ordered[1:] == ordered[:-1]).any():
        raise ValueError(f"{name}: ids must be unique")
    return ordered


def _any_in(ordered: np.ndarray, ids: np.ndarray) -> bool:
    """Whether any of `ids` is among the sorted ids `ordered`."""
    if not (ids.size and ordered.size):
        return False
    pos = np.minimum(np.searchsorted(ordered, ids), ordered.size - 1)
    return bool((ordered[pos] == ids).any())


class SubmapDelta(Message):
    """New or changed map points of one agent, and removed ones.

    A point is identified by (agent_id, point id); a later delta carrying the same id replaces
    it. Positions are local to the anchor keyframe, so a keyframe pose correction moves its
    points without resending them. A point the server already holds, whose features alone
    changed, goes in `feature_ids` with only its features: the feature rows are those of
    `point_ids`, then those of `feature_ids`. Features travel either as float16 (`features`)
    or as int8 with one scale per row (`features_int8` times `feature_scales`);
    `feature_values` and `updated_feature_values` give them as float32 either way.
    """

    max_bytes = 64 * MB
    type: Literal["submap_delta"] = "submap_delta"
    agent_id: Id
    """Sending agent."""
    seq: Seq
    """Agent's message sequence number."""
    incarnation: Seq = 0
    """The sending agent's incarnation (as in `KeyframeMsg`)."""
    point_ids: Ids
    """Agent-unique point ids, >= 0, no repeats (int64 [N])."""
    anchor_kf_ids: KfIds
    """Keyframe each point is anchored to (int32 [N])."""
    xyz_local: Xyz
    """Point positions in the anchor keyframe's camera frame (float32 [N, 3], m; on the wire
    int32 counts of `XYZ_STEP_M`)."""
    features: Features | None = None
    """Learned point features (float16 [N + U, F], F <= 1024); None when sent as int8."""
    features_int8: Int8Features | None = None
    """Quantised features (int8 [N + U, F], |q| <= 127); None when sent as float16."""
    feature_scales: RowScales | None = None
    """Scale of each row of features_int8 (float16 [N + U], >= 0): feature = q * scale."""
    colors: Colors
    """Point colours, RGB (uint8 [N, 3])."""
    removed_ids: RemovedIds
    """Ids of points the agent deleted (int64 [M]); disjoint from point_ids."""
    feature_ids: UpdatedIds = Field(default_factory=lambda: np.zeros(0, np.int64))
    """Held points whose features alone are sent (int64 [U]); disjoint from the other ids."""

    @model_validator(mode="after")
    def _check(self) -> SubmapDelta:
        if (self.features is None) == (self.features_int8 is None):
            raise ValueError("features/features_int8: exactly one must be given")
        if (self.features_int8 is None) != (self.feature_scales is None):
            raise ValueError("feature_scales: required with features_int8, and only with it")
        n, u = self.point_ids.shape[0], self.feature_ids.shape[0]
        feats = self.features if self.features is not None else self.features_int8
        if feats.shape[0] != n + u:
            name = "features" if self.features is not None else "features_int8"
            raise ValueError(f"{name}: has {feats.shape[0]} rows, expected {n + u} (point_ids "
                             f"then feature_ids)")
        if self.feature_scales is not None:
            if self.feature_scales.shape[0] != n + u:
                raise ValueError(f"feature_scales: has {self.feature_scales.shape[0]} rows, "
                                 f"expected {n + u}")
            if (self.feature_scales < 0).any():
                raise ValueError("feature_scales: must be >= 0")
        check_points(
            self.point_ids,
            self.anchor_kf_ids,
            self.xyz_local,
            feats[:n],
            self.colors,
            self.removed_ids,
        )
        if u:
            ordered = _sorted_unique(self.feature_ids, "feature_ids")
            if _any_in(ordered, self.point_ids) or _any_in(ordered, self.removed_ids):
                raise ValueError("feature_ids: an id cannot also be in point_ids or removed_ids")
        return self

    @property
    def feature_dim(self) -> int:
        """Width F of the features."""
        feats = self.features if self.features is not None else self.features_int8
        return int(feats.shape[1])

    def feature_values(self) -> np.ndarray:
        """The features of `point_ids` as float32 [N, F], dequantised when they travelled as
        int8."""
        return self._values(slice(0, self.point_ids.shape[0]))

    def updated_feature_values(self) -> np.ndarray:
        """The features of `feature_ids` as float32 [U, F]."""
        return self._values(slice(self.point_ids.shape[0], None))

    def _values(self, rows: slice) -> np.ndarray:
        if self.features is not None:
            return self.features[rows].astype(np.float32)
        return dequantise_rows(self.features_int8[rows], self.feature_scales[rows])


class DecoderWeights(Message):
    """An agent's local decoder weights for one federated round.

    With `base_round` set the tensors are the difference to the group's shared decoder of that
    round (group_id's `GroupDecoder`), which the agent had loaded; with `base_seq` the
    difference to the weights the server holds from this agent's acknowledged
    `DecoderWeights` of that seq (while no shared decoder exists); without either, the
    weights themselves. They travel as float32 (`tensors`), float16 (`tensors_f16`) or as int8
    with one scale per row (`tensors_int8`, `tensor_scales`); `values` gives float32 each way.
    """

    max_bytes = 16 * MB
    type: Literal["decoder_weights"] = "decoder_weights"
    agent_id: Id
    """Sending agent."""
    seq: Seq
    """Agent's message sequence number."""
    incarnation: Seq = 0
    """The sending agent's incarnation (as in `KeyframeMsg`)."""
    group_id: Id
    """Group the agent belongs to (its own id until merged)."""
    round: Count
    """Federated round these weights answer (0 before any shared decoder arrived)."""
    n_samples: Count
    """Number of training rays behind these weights (the averaging weight)."""
    base_round: Count | None = None
    """Round of group_id's shared decoder the tensors are a delta against; None: not that."""
    base_seq: Seq | None = None
    """Seq of this agent's earlier decoder_weights the tensors are a delta against (the
    weights the server holds from it); None: not that. At most one of base_round, base_seq."""
    tensors: Tensors | None = None
    """Parameters (or deltas) by name (torch state_dict keys), each float32 of any shape."""
    tensors_f16: Float16Tensors | None = None
    """The same rounded to float16."""
    tensors_int8: Int8Tensors | None = None
    """The same quantised: int8 of any shape, row i (axis 0) times tensor_scales[name][i]."""
    tensor_scales: Scales | None = None
    """Per name of tensors_int8 the scale of each row (float32 [R], >= 0; R = 1 for 0-d/1-d)."""

    @model_validator(mode="after")
    def _check(self) -> DecoderWeights:
        forms = (self.tensors, self.tensors_f16, self.tensors_int8)
        if sum(form is not None for form in forms) != 1:
            raise ValueError("tensors/tensors_f16/tensors_int8: exactly one must be given")
        if (self.tensors_int8 is None) != (self.tensor_scales is None):
            raise ValueError("tensor_scales: required with tensors_int8, and only with it")
        if self.tensors_int8 is not None:
            if set(self.tensor_scales) != set(self.tensors_int8):
                raise ValueError("tensor_scales: must name the same tensors as tensors_int8")
            for name, q in self.tensors_int8.items():
                rows = q.shape[0] if q.ndim >= 2 else 1
                scale = self.tensor_scales[name]
                if scale.shape[0] != rows:
                    raise ValueError(f"tensor_scales.{name}: has {scale.shape[0]} rows, "
                                     f"expected {rows}")
                if (scale < 0).any():
                    raise ValueError(f"tensor_scales.{name}: must be >= 0")
        if self.base_round is not None and self.base_seq is not None:
            raise ValueError("base_round/base_seq: at most one base")
        if self.base_seq is not None and self.base_seq >= self.seq:
            raise ValueError(f"base_seq: must be an earlier message than seq {self.seq}")
        if self.base_round is not None and self.base_round < 1:
            raise ValueError("base_round: shared decoders start at round 1")
        return self

    def values(self) -> dict[str, np.ndarray]:
        """The tensors (or deltas) as float32 by name, dequantised when sent as int8."""
        for plain in (self.tensors, self.tensors_f16):
            if plain is not None:
                return {k: np.asarray(v, np.float32) for k, v in plain.items()}
        return {k: dequantise_rows(q, self.tensor_scales[k])
                for k, q in self.tensors_int8.items()}


class FramePoses(Message):
    """Poses of ordinary frames relative to their keyframes (a batch)."""

    max_bytes = 4 * MB
    type: Literal["frame_poses"] = "frame_poses"
    agent_id: Id
    """Sending agent."""
    seq: Seq
    """Agent's message sequence number."""
    incarnation: Seq = 0
    """The sending agent's incarnation (as in `KeyframeMsg`)."""
    frame_indices: Annotated[np.ndarray, ArraySpec("int64", ("N",))]
    """Indices of the frames in the agent's stream (int64 [N], >= 0)."""
    stamps: Annotated[np.ndarray, ArraySpec("float64", ("N",), finite=True)]
    """Frame timestamps (float64 [N], s)."""
    kf_ids: KfIds
    """Keyframe each frame is expressed against (int32 [N], >= 0)."""
    T_kf_frame: Annotated[
        np.ndarray, ArraySpec("float64", ("N", 4, 4), rigid=True, wire_dtype="float32")
    ]
    """Frame camera pose in its keyframe's camera frame (float64 [N, 4, 4], m; float32 on the
    wire: a relative pose needs no more)."""

    @model_validator(mode="after")
    def _check(self) -> FramePoses:
        n = self.frame_indices.shape[0]
        for name in ("stamps", "kf_ids", "T_kf_frame"):
            if getattr(self, name).shape[0] != n:
                raise ValueError(f"{name}: has {getattr(self, name).shape[0]} rows, expected {n}")
        if n and (self.frame_indices.min() < 0 or self.kf_ids.min() < 0):
            raise ValueError("frame_indices/kf_ids: must be >= 0")
        return self

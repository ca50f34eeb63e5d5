"""Messages the server sends (updates, shared decoders, acks, status) and control messages."""

from __future__ import annotations

from typing import Annotated, Any, Literal

import numpy as np
from pydantic import Field, field_validator, model_validator

from cpslam.protocol.base import Count, Id, Message, Pose, Poses, Seq, Tensors, WireModel
from cpslam.protocol.messages import (
    MB,
    Colors,
    Features,
    Ids,
    KfIds,
    RemovedIds,
    Xyz,
    check_points,
)

__all__ = [
    "ForeignPoints",
    "ServerUpdate",
    "GroupDecoder",
    "Ack",
    "Status",
    "Control",
    "ErrorReply",
    "check_json",
]

MAX_MEMBERS = 1024
MAX_FOREIGN = 1024
MAX_TEXT = 4096
MAX_JSON_DEPTH = 16
MAX_ACK_RANGES = 64
SeqRange = Annotated[list[Seq], Field(min_length=2, max_length=2)]
"""Inclusive [lo, hi] range of seqs."""


class ForeignPoints(WireModel):
    """Points of another agent of the same group, with that agent's keyframe poses.

    The receiver places point i at ``T_group_kf[k] @ xyz_local[i]`` where k is the row of
    ``anchor_kf_ids[i]`` in ``kf_ids`` (of this block or of an earlier update).
    """

    source_agent_id: Id
    """Agent the points belong to."""
    kf_ids: KfIds
    """Keyframes of the source agent whose poses are given (int32 [K])."""
    T_group_kf: Poses
    """Those keyframes' camera poses in the group frame (float64 [K, 4, 4], m)."""
    point_ids: Ids
    """Source-agent-unique point ids (int64 [N])."""
    anchor_kf_ids: KfIds
    """Source keyframe each point is anchored to (int32 [N])."""
    xyz_local: Xyz
    """Positions in the anchor keyframe's camera frame (float32 [N, 3], m; on the wire int32
    counts of `XYZ_STEP_M`)."""
    features: Features
    """Point features (float16 [N, F])."""
    colors: Colors
    """Point colours, RGB (uint8 [N, 3])."""
    removed_ids: RemovedIds
    """Ids of the source agent's points to drop (int64 [M])."""

    @model_validator(mode="after")
    def _check(self) -> ForeignPoints:
        _check_kf_poses(self.kf_ids, self.T_group_kf)
        check_points(
            self.point_ids,
            self.anchor_kf_ids,
            self.xyz_local,
            self.features,
            self.colors,
            self.removed_ids,
        )
        return self


class ServerUpdate(Message):
    """What the server pushes to one agent after alignment, fusion or pose-graph optimisation."""

    max_bytes = 64 * MB
    type: Literal["server_update"] = "server_update"
    agent_id: Id
    """Receiving agent."""
    seq: Seq
    """Server's sequence number for this agent's updates (increasing)."""
    epoch: Count
    """Alignment epoch, +1 whenever T_group_agent changes; agents echo it as world_epoch."""
    group_id: Id
    """Group the agent now belongs to."""
    group_members: list[Id] = Field(min_length=1, max_length=MAX_MEMBERS)
    """Agents of the group, including the receiver."""
    T_group_agent: Pose
    """Maps the agent's own world (its first camera) into the group frame (float64 [4, 4])."""
    kf_ids: KfIds
    """Keyframes of the receiving agent with corrected poses (int32 [K])."""
    T_group_kf: Poses
    """Corrected keyframe camera poses in the group frame (float64 [K, 4, 4], m)."""
    foreign: list[ForeignPoints] = Field(default_factory=list, max_length=MAX_FOREIGN)
    """Points of other agents of the group, one block per source agent."""

    @model_validator(mode="after")
    def _check(self) -> ServerUpdate:
        _check_kf_poses(self.kf_ids, self.T_group_kf)
        _check_unique(self.group_members, "group_members")
        if self.agent_id not in self.group_members:
            raise ValueError("group_members: must include agent_id")
        sources = [block.source_agent_id for block in self.foreign]
        _check_unique(sources, "foreign")
        if self.agent_id in sources:
            raise ValueError("foreign: a block cannot come from the receiving agent")
        return self


class GroupDecoder(Message):
    """Shared decoder weights of a group after a federated round."""

    max_bytes = 16 * MB
    type: Literal["group_decoder"] = "group_decoder"
    group_id: Id
    """Group the decoder belongs to."""
    round: Count
    """Federated round number (increasing)."""
    members: list[Id] = Field(min_length=1, max_length=MAX_MEMBERS)
    """Agents whose weights were averaged."""
    n_samples: Count
    """Total training rays behind the average."""
    tensors: Tensors
    """Parameters by name (torch state_dict keys), each float32 of any shape."""

    @field_validator("members")
    @classmethod
    def _unique(cls, members: list[str]) -> list[str]:
        _check_unique(members, "members")
        return members


class Ack(Message):
    """The server has handled (and persisted) every message of `agent_id` with seq <= `seq`
    (the floor), and those in `received` above it; `dropped` were handled by being dropped."""

    max_bytes = 16384
    type: Literal["ack"] = "ack"
    agent_id: Id
    """Agent whose messages are acknowledged."""
    seq: int = Field(ge=-1, lt=2**63)
    """The floor: every message with seq <= this is handled (-1: none yet)."""
    incarnation: Seq = 0
    """Incarnation of the agent these seqs belong to."""
    received: list[SeqRange] = Field(default_factory=list, max_length=MAX_ACK_RANGES)
    """Inclusive seq ranges above the floor that are handled too (a lost message leaves a gap)."""
    dropped: list[Seq] = Field(default_factory=list, max_length=MAX_ACK_RANGES)
    """Recent seqs the server dropped because handling them raised (handled, never resend)."""

    @model_validator(mode="after")
    def _check(self) -> Ack:
        for lo, hi in self.received:
            if not self.seq < lo <= hi:
                raise ValueError(f"received: range ({lo}, {hi}) must lie above the floor "
                                 f"{self.seq} with lo <= hi")
        return self


def check_json(value: Any, depth: int = 0) -> Any:
    """`value` as plain JSON data (None, bool, int, float, str, list, str-keyed dict).

    Tuples become lists and numpy scalars Python scalars; anything else, non-finite floats,
    ints outside 64 bits or nesting deeper than 16 raise ValueError.
    """
    if depth > MAX_JSON_DEPTH:
        raise ValueError(f"nested deeper than {MAX_JSON_DEPTH}")
    if isinstance(value, np.generic):
        value = value.item()
    if value is None or isinstance(value, bool | str):
        return value
    if isinstance(value, int):
        if not -(2**63) <= value < 2**64:
            raise ValueError(f"int {value} does not fit in 64 bits")
        return value
    if isinstance(value, float):
        if not np.isfinite(value):
            raise ValueError("floats must be finite")
        return value
    if isinstance(value, list | tuple):
        return [check_json(v, depth + 1) for v in value]
    if isinstance(value, dict):
        if not all(isinstance(k, str) for k in value):
            raise ValueError("dict keys must be str")
        return {k: check_json(v, depth + 1) for k, v in value.items()}
    raise ValueError(f"{type(value).__name__} is not JSON data")


class Status(Message):
    """Summary of the session, the reply of the server's status queryable."""

    max_bytes = 1 * MB
    type: Literal["status"] = "status"
    stamp: float
    """Server wall-clock time of the summary (s since the Unix epoch)."""
    summary: dict[str, Any] = Field(default_factory=dict)
    """JSON data: agents, groups, loops, rounds (content defined by the server)."""

    @field_validator("summary")
    @classmethod
    def _json(cls, summary: dict[str, Any]) -> dict[str, Any]:
        return check_json(summary)


class Control(Message):
    """Session control: finalise (optimise and export) or shut down."""

    max_bytes = 16384
    type: Literal["control"] = "control"
    action: Literal["finalise", "shutdown"]
    """finalise: agents flush, server runs the final optimisation and export; shutdown: stop."""
    reason: str = Field(default="", max_length=MAX_TEXT)
    """Free text for the logs."""


class ErrorReply(Message):
    """Answer of a queryable that cannot serve the query (e.g. unknown keyframe)."""

    max_bytes = 16384
    type: Literal["error"] = "error"
    code: Literal["not_found", "bad_request", "internal"]
    """not_found: nothing under that key; bad_request: the query was malformed; internal: bug."""
    reason: str = Field(default="", max_length=MAX_TEXT)
    """Free text for the logs."""


def _check_kf_poses(kf_ids: np.ndarray, T_group_kf: np.ndarray) -> None:
    if kf_ids.shape[0] != T_group_kf.shape[0]:
        raise ValueError(
            f"T_group_kf: has {T_group_kf.shape[0]} poses, kf_ids has {kf_ids.shape[0]}"
        )
    ordered = np.sort(kf_ids)
    if kf_ids.size and (ordered[0] < 0 or (ordered[1:] == ordered[:-1]).any()):
        raise ValueError("kf_ids: must be unique and >= 0")


def _check_unique(ids: list[str], what: str) -> None:
    if len(set(ids)) != len(ids):
        raise ValueError(f"{what}: ids must be unique")

"""Valid example messages with realistic sizes, for tests and transport benchmarks.

`sample("submap_delta", seed=0, n_points=10_000)` builds one message of the named type with
random but valid content; `samples(seed)` gives one small message of every type.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from cpslam.protocol.base import Message
from cpslam.protocol.delivery import Refusal, UpdateAck
from cpslam.protocol.messages import (
    DecoderWeights,
    FramePoses,
    KeyframeImage,
    KeyframeImageRequest,
    KeyframeMsg,
    SubmapDelta,
)
from cpslam.protocol.updates import (
    Ack,
    Control,
    ErrorReply,
    ForeignPoints,
    GroupDecoder,
    ServerUpdate,
    Status,
)

__all__ = ["random_poses", "sample", "samples", "decoder_tensors"]


def random_poses(rng: np.random.Generator, n: int) -> np.ndarray:
    """`n` random rigid transforms (float64 [n, 4, 4]), translations within ±5 m."""
    q = rng.standard_normal((n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    x, y, z, w = q.T
    T = np.zeros((n, 4, 4))
    T[:, 0, :3] = np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], 1)
    T[:, 1, :3] = np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], 1)
    T[:, 2, :3] = np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], 1)
    T[:, :3, 3] = rng.uniform(-5, 5, (n, 3))
    T[:, 3, 3] = 1.0
    return T


def decoder_tensors(rng: np.random.Generator, n_params: int = 100_000) -> dict[str, np.ndarray]:
    """A small MLP's parameters totalling about `n_params` float32 values."""
    # hidden^2 + 143 hidden + 1 parameters for the layer shapes below
    hidden = max(1, int((-143 + np.sqrt(143**2 + 4 * n_params)) / 2))
    shapes = {
        "c.0.weight": (hidden, 141),
        "c.0.bias": (hidden,),
        "g.0.weight": (hidden, hidden),
        "g.0.bias": (hidden,),
        "g.2.weight": (1, hidden),
        "g.2.bias": (1,),
    }
    return {k: rng.standard_normal(s).astype(np.float32) * 0.1 for k, s in shapes.items()}


def _points(rng: np.random.Generator, n: int, feature_dim: int, n_kf: int) -> dict[str, Any]:
    return {
        "point_ids": rng.permutation(4 * n + 8)[:n].astype(np.int64),
        "anchor_kf_ids": rng.integers(0, n_kf, n).astype(np.int32),
        "xyz_local": rng.uniform(-3, 3, (n, 3)).astype(np.float32),
        "features": rng.standard_normal((n, feature_dim)).astype(np.float16),
        "colors": rng.integers(0, 256, (n, 3)).astype(np.uint8),
        "removed_ids": np.arange(4 * n + 8, 4 * n + 8 + n // 10, dtype=np.int64),
    }


def _keyframe(rng: np.random.Generator, descriptor_dim: int = 1024) -> KeyframeMsg:
    d = rng.standard_normal(descriptor_dim).astype(np.float32)
    return KeyframeMsg(
        agent_id="agent-0",
        seq=7,
        kf_id=3,
        frame_index=150,
        stamp=5.0,
        world_epoch=1,
        T_world_cam=random_poses(rng, 1)[0],
        T_prev_kf_kf=random_poses(rng, 1)[0],
        descriptor=d / np.linalg.norm(d),
        n_points=812,
    )


def _submap(rng: np.random.Generator, n_points: int = 10_000, feature_dim: int = 32) -> SubmapDelta:
    return SubmapDelta(agent_id="agent-0", seq=8, **_points(rng, n_points, feature_dim, 4))


def _decoder(rng: np.random.Generator, n_params: int = 100_000) -> DecoderWeights:
    return DecoderWeights(
        agent_id="agent-0",
        seq=9,
        group_id="agent-0",
        round=2,
        n_samples=60_000,
        tensors=decoder_tensors(rng, n_params),
    )


def _frames(rng: np.random.Generator, n_frames: int = 50) -> FramePoses:
    return FramePoses(
        agent_id="agent-0",
        seq=10,
        frame_indices=np.arange(100, 100 + n_frames, dtype=np.int64),
        stamps=np.arange(n_frames) / 30.0,
        kf_ids=np.full(n_frames, 2, np.int32),
        T_kf_frame=random_poses(rng, n_frames),
    )


def _image(
    rng: np.random.Generator, width: int = 64, height: int = 48, rgb_codec: str = "png"
) -> KeyframeImage:
    # smooth content compresses like a camera image, unlike white noise
    yy, xx = np.mgrid[0:height, 0:width]
    base = (xx * 255 // max(width - 1, 1)).astype(np.uint8)
    rgb = np.stack([base, (yy * 255 // max(height - 1, 1)).astype(np.uint8), 255 - base], -1)
    rgb = np.clip(rgb + rng.integers(-4, 5, rgb.shape), 0, 255).astype(np.uint8)
    depth_m = 1.0 + 0.002 * xx + 0.001 * yy
    depth_m[rng.random(depth_m.shape) < 0.05] = 0.0
    return KeyframeImage.from_metres(
        depth_m,
        agent_id="agent-0",
        kf_id=3,
        fx=0.8 * width,
        fy=0.8 * width,
        cx=width / 2 - 0.5,
        cy=height / 2 - 0.5,
        width=width,
        height=height,
        rgb=rgb,
        rgb_codec=rgb_codec,
    )


def _update(rng: np.random.Generator, n_points: int = 1000, feature_dim: int = 32) -> ServerUpdate:
    foreign = ForeignPoints(
        source_agent_id="agent-1",
        kf_ids=np.arange(4, dtype=np.int32),
        T_group_kf=random_poses(rng, 4),
        **_points(rng, n_points, feature_dim, 4),
    )
    return ServerUpdate(
        agent_id="agent-0",
        seq=4,
        epoch=1,
        group_id="g0",
        group_members=["agent-0", "agent-1"],
        T_group_agent=random_poses(rng, 1)[0],
        kf_ids=np.arange(3, dtype=np.int32),
        T_group_kf=random_poses(rng, 3),
        foreign=[foreign],
    )


_BUILDERS: dict[str, Callable[..., Message]] = {
    "keyframe": _keyframe,
    "submap_delta": _submap,
    "decoder_weights": _decoder,
    "frame_poses": _frames,
    "keyframe_image_request": lambda rng: KeyframeImageRequest(
        agent_id="agent-0", kf_id=3, want_depth=False, scale=0.5
    ),
    "keyframe_image": _image,
    "server_update": _update,
    "group_decoder": lambda rng, n_params=100_000: GroupDecoder(
        group_id="g0",
        round=3,
        members=["agent-0", "agent-1"],
        n_samples=120_000,
        tensors=decoder_tensors(rng, n_params),
    ),
    "ack": lambda rng: Ack(agent_id="agent-0", seq=10, incarnation=7, received=[(12, 15)],
                           dropped=[11]),
    "update_ack": lambda rng: UpdateAck(agent_id="agent-0", incarnation=7, update_seq=3),
    "refusal": lambda rng: Refusal(agent_id="agent-0", incarnation=8,
                                   reason="agent id agent-0 already streams"),
    "status": lambda rng: Status(
        stamp=1.7e9,
        summary={"agents": {"agent-0": {"keyframes": 4, "alive": True}}, "groups": [["agent-0"]]},
    ),
    "control": lambda rng: Control(action="finalise", reason="end of sequence"),
    "error": lambda rng: ErrorReply(code="not_found", reason="no keyframe 99"),
}


def sample(msg_type: str, seed: int = 0, **sizes: Any) -> Message:
    """One valid message of the wire type `msg_type`; `sizes` go to its builder.

    Builders take: keyframe ``descriptor_dim``; submap_delta ``n_points, feature_dim``;
    decoder_weights and group_decoder ``n_params``; frame_poses ``n_frames``;
    keyframe_image ``width, height, rgb_codec``; server_update ``n_points, feature_dim``.
    """
    if msg_type not in _BUILDERS:
        raise KeyError(f"no sample for message type {msg_type!r}; known: {sorted(_BUILDERS)}")
    return _BUILDERS[msg_type](np.random.default_rng(seed), **sizes)


def samples(seed: int = 0) -> list[Message]:
    """One small message of every type (sizes kept small for fast tests)."""
    small = {
        "submap_delta": {"n_points": 50, "feature_dim": 8},
        "decoder_weights": {"n_params": 500},
        "group_decoder": {"n_params": 500},
        "server_update": {"n_points": 20, "feature_dim": 8},
        "keyframe": {"descriptor_dim": 64},
    }
    return [sample(name, seed, **small.get(name, {})) for name in _BUILDERS]

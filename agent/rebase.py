"""Streaming afresh to a server that lost what it had acknowledged.

The server's liveliness token names the state it holds (``alive/server/<state>``, see
`cpslam.protocol.keys.alive_server`); a server restarted from its persisted state keeps the
id, one restarted without it draws a new one. An agent that sees the server come back under
another id than the one its stream went to knows that everything acknowledged is gone, and
`restart_stream` starts the stream over:

1. A new incarnation (the old one's messages can never mix with the new stream), seq from 0,
   an empty outbox (what waited in it is part of the state sent again).
2. The frame the agent is in now becomes its own world (a merged agent stays in its group's
   frame: no pose changes); group, epoch, decoder rounds and what the server held of its map
   and decoder are forgotten.
3. Its whole state again, in stream order: every keyframe (current pose, the descriptor it
   was first sent with, the link to the previous keyframe), every own point (messages of at
   most ``max_points``), its decoder weights (in full) and every frame pose.

Points received from other agents stay in the local map; the new server sends them again once
the agents' maps merge again.
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING

import numpy as np

from cpslam.agent.corrections import rigid
from cpslam.agent.deltas import DecoderBase, SubmapMirror
from cpslam.common.geometry import compose, invert
from cpslam.protocol import KeyframeMsg, Message

if TYPE_CHECKING:
    from cpslam.agent.link import AgentLink

__all__ = ["restart_stream"]

logger = logging.getLogger(__name__)

MAX_POINTS = 200_000
"""Own points per sub-map message of a restarted stream."""


def restart_stream(link: AgentLink, incarnation: int, max_points: int = MAX_POINTS) -> list[
        Message]:
    """Reset `link` to a new stream of incarnation `incarnation` and return its messages (the
    whole state, see the module docstring); the caller publishes them."""
    _reset(link, incarnation)
    out: list[Message] = list(_keyframes(link))
    while (delta := link._submap_delta(max_points, held=True)) is not None:
        out.append(delta)
    if link.federation and link.odometry.n_frames:
        out.append(link._decoder_weights())
    link._pending_frames = _frame_poses(link)
    out += link.flush()
    logger.info("agent %s: streaming afresh as incarnation %d: %d messages (%d keyframes, %d "
                "frames)", link.agent_id, link.incarnation, len(out),
                len(link.odometry.keyframes.ids()), len(link._frame_kf))
    return out


def _reset(link: AgentLink, incarnation: int) -> None:
    link.incarnation = int(incarnation)
    link._seq = 0
    link.outbox.clear()
    link.update_seq = 0
    link.epoch = 0
    link.T_group_agent = np.eye(4)
    link.group_id, link.group_members = link.agent_id, [link.agent_id]
    link.round = 0
    link._decoders_waiting = {}
    link.decoder_base = DecoderBase(full_codec=link.decoder_base.full_codec)
    link.mirror = SubmapMirror(link.mirror.features.shape[1], link.mirror.threshold,
                               link.mirror.codec, link.mirror.bits)
    link._submap_mappings = 0


def _keyframes(link: AgentLink) -> list[KeyframeMsg]:
    store = link.odometry.keyframes
    out, prev = [], None
    for kf in store:
        descriptor = link._descriptors.get(kf.kf_id)
        if descriptor is None:  # resumed from a link state without it: describe it again
            try:
                rgb = store.full_rgbd(kf.kf_id)[0]
            except KeyError:
                rgb = kf.rgb_small
            descriptor = np.asarray(link.describe(rgb), np.float32)
            descriptor = link._descriptors[kf.kf_id] = descriptor / np.linalg.norm(descriptor)
        T_prev = None if prev is None else compose(invert(prev.T_world_cam), kf.T_world_cam)
        out.append(link._stamp(KeyframeMsg(
            agent_id=link.agent_id, seq=0, kf_id=kf.kf_id, frame_index=kf.frame_index,
            stamp=kf.timestamp, world_epoch=0, T_world_cam=kf.T_world_cam,
            T_prev_kf_kf=T_prev, descriptor=descriptor, n_points=len(kf.point_ids))))
        prev = kf
    return out


def _frame_poses(link: AgentLink) -> list[tuple[int, float, int, np.ndarray]]:
    """Every frame as (index, stamp, keyframe, T_kf_frame), against its keyframe's pose now."""
    store = link.odometry.keyframes
    stamps, poses = link.odometry.trajectory()
    out = []
    for index, stamp, kf_id, T in zip(link._frame_index, stamps, link._frame_kf, poses,
                                      strict=True):
        if kf_id in store:
            out.append((index, float(stamp), kf_id,
                        rigid(compose(invert(store.get(kf_id).T_world_cam), T))))
    return out

"""Whether an agent message's poses and keyframe ids can be right, before anything is taken.

Checked against bounds from the config (``limits.max_translation_m``), never against what a
first peer sent: every pose finite with its translation below the bound, and keyframe ids
increasing with the message seq (a keyframe id that goes back while seqs go on is a restart
without a new incarnation, or a forgery).
"""

from __future__ import annotations

import numpy as np

from cpslam.protocol import FramePoses, KeyframeMsg, Message

__all__ = ["implausible"]


def implausible(msg: Message, kf_seqs: dict[int, int], max_translation_m: float | None) -> str:
    """Why `msg`'s poses or keyframe id cannot be right ("" if they can). `kf_seqs`: keyframe
    id -> seq of the message it came with, for the agent's keyframes taken so far."""
    if isinstance(msg, KeyframeMsg):
        poses = [("T_world_cam", msg.T_world_cam), ("T_prev_kf_kf", msg.T_prev_kf_kf)]
    elif isinstance(msg, FramePoses):
        poses = [("T_kf_frame", msg.T_kf_frame)]
    else:
        return ""
    for name, T in poses:
        if T is None or T.size == 0:
            continue
        if not np.isfinite(T).all():
            return f"field {name} is not finite"
        t_max = float(np.linalg.norm(T[..., :3, 3], axis=-1).max())
        if max_translation_m is not None and t_max > max_translation_m:
            return (f"field {name} has |t| {t_max:.6g} m, expected at most "
                    f"{max_translation_m:g} m (limits.max_translation_m)")
    if isinstance(msg, KeyframeMsg):
        kf, seq = int(msg.kf_id), int(msg.seq)
        for other, other_seq in kf_seqs.items():
            if other != kf and (other_seq < seq) != (other < kf):
                return (f"field kf_id {kf} (seq {seq}) does not increase with seq: "
                        f"keyframe {other} came with seq {other_seq}")
    return ""

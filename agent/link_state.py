"""Save and restore an `AgentLink`'s side of the protocol, for ``cpslam-agent --resume``.

A resumed agent is the same incarnation: it keeps the incarnation id, its message counter (new
messages continue the seq numbering, so the server takes them and ignores repeats), its outbox
(resent at once: the server may never have had them), what it already sent of its own points,
the last server update applied, its place in the group frame, the server state its stream
went to and the descriptors it sent (to stream afresh to a server that lost them). Written
atomically next to the odometry's state.pt as ``link.pt`` (loadable with
``torch.load(weights_only=True)``).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from cpslam import protocol
from cpslam.common.durable import torch_save_atomic

if TYPE_CHECKING:
    from cpslam.agent.link import AgentLink

__all__ = ["load_link_state", "link_state", "read_link_state", "write_link_state"]

_SCALARS = (
    "incarnation",
    "_seq",
    "update_seq",
    "epoch",
    "round",
    "group_id",
    "_mappings",
    "_submap_mappings",
    "_samples",
)


_FIELDS = ("agent_id", "group_members", "T_group_agent", "foreign_index", "frame_kf",
           "frame_index", "server_state", "descriptor_kfs", "descriptors", "sent_ids",
           "sent_features", "sent_seqs", "outbox", "pending_frames")


def link_state(link: AgentLink) -> dict:
    """Plain data and tensors of everything `load_link_state` needs."""
    state: dict = {name: getattr(link, name) for name in _SCALARS}
    state.update(
        agent_id=link.agent_id,
        group_members=list(link.group_members),
        T_group_agent=torch.from_numpy(np.asarray(link.T_group_agent, np.float64).copy()),
        foreign_index=dict(link.foreign_index),
        frame_kf=torch.tensor(link._frame_kf, dtype=torch.int64),
        frame_index=torch.tensor(link._frame_index, dtype=torch.int64),
        server_state=-1 if link.server_state is None else int(link.server_state),
        descriptor_kfs=torch.tensor(list(link._descriptors), dtype=torch.int64),
        descriptors=[torch.from_numpy(d.copy()) for d in link._descriptors.values()],
        sent_ids=torch.from_numpy(link.mirror.ids.astype(np.int64)),
        sent_features=torch.from_numpy(link.mirror.features.astype(np.float32)),
        sent_seqs=torch.from_numpy(link.mirror.seqs.astype(np.int64)),
        outbox=[
            torch.frombuffer(bytearray(protocol.encode(m)), dtype=torch.uint8)
            for m in link.unacked()
        ],
        pending_frames=[
            [int(i), float(t), int(k), torch.from_numpy(np.asarray(T).copy())]
            for i, t, k, T in link._pending_frames
        ],
    )
    return state


def load_link_state(link: AgentLink, state: dict) -> None:
    """Restore `link_state` into a fresh link of the same agent id."""
    missing = sorted({*_SCALARS, *_FIELDS} - set(state))
    if missing:
        raise ValueError(f"link state lacks {', '.join(missing)} (written by another cpslam "
                         "version?); resume with the version that wrote it")
    if state["agent_id"] != link.agent_id:
        raise ValueError(
            f"link state of agent {state['agent_id']!r} cannot resume agent {link.agent_id!r}"
        )
    for name in _SCALARS:
        setattr(link, name, type(getattr(link, name))(state[name]))
    link.group_members = [str(m) for m in state["group_members"]]
    link.T_group_agent = state["T_group_agent"].cpu().numpy().copy()
    link.foreign_index = {str(k): int(v) for k, v in state["foreign_index"].items()}
    link._frame_kf = [int(k) for k in state["frame_kf"].tolist()]
    link._frame_index = [int(i) for i in state["frame_index"].tolist()]
    link.server_state = None if int(state["server_state"]) < 0 else int(state["server_state"])
    link._descriptors = {
        int(k): d.cpu().numpy().copy()
        for k, d in zip(state["descriptor_kfs"].tolist(), state["descriptors"], strict=True)
    }
    link.mirror.ids = state["sent_ids"].cpu().numpy().copy()
    link.mirror.features = state["sent_features"].cpu().numpy().astype(np.float32)
    link.mirror.seqs = state["sent_seqs"].cpu().numpy().astype(np.int64)
    if not len(link.mirror.ids) == len(link.mirror.features) == len(link.mirror.seqs):
        raise ValueError("link state: sent_ids, sent_features and sent_seqs differ in length")
    link._pending_frames = [
        (int(i), float(t), int(k), T.cpu().numpy().copy()) for i, t, k, T in state["pending_frames"]
    ]
    for raw in state["outbox"]:
        msg = protocol.decode(raw.cpu().numpy().tobytes())
        link.outbox.add(int(msg.seq), msg)


def write_link_state(link: AgentLink, path: Path) -> None:
    """`link_state` to `path`, atomically."""
    torch_save_atomic(link_state(link), path)


def read_link_state(path: Path) -> dict:
    """A `link_state` written by `write_link_state`; a clear error when it cannot be read."""
    try:
        return torch.load(path, weights_only=True)
    except Exception as exc:  # noqa: BLE001 - name the file and what to do
        raise ValueError(
            f"{path}: cannot read the agent's link state ({exc}); it is written "
            "next to state.pt by a networked cpslam-agent"
        ) from exc

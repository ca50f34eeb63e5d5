"""What the back end keeps across a restart: its accepted state as python data and tensors
(``torch.save``-able, loadable with ``weights_only=True``), and its restore.

Open federated rounds are not kept (agents resubmit); loop candidates still queued, retrying
or in the verification worker's hands are, and are verified after the restore. The state id
names what a back end holds: a fresh back end draws a new one, a restore keeps the saved one,
and agents compare it across a server restart to learn whether their acknowledged data
survived (docs/protocol.md).
"""

from __future__ import annotations

import secrets
from typing import TYPE_CHECKING

import torch

if TYPE_CHECKING:
    from cpslam.server.backend import Backend

__all__ = ["backend_state", "new_state_id", "restore_backend"]


def new_state_id() -> int:
    """A random non-zero 63-bit id, from the OS (a fresh back end's state is a new one)."""
    return secrets.randbits(63) or 1


def backend_state(be: Backend) -> dict:
    """Everything `be` accepted (`Backend.state_dict`)."""
    loops = be.pipeline.state_dict()
    return {
        "state_id": be.state_id,
        "registry": be.registry.state_dict(), "groups": be.groups.state_dict(),
        "foreign": be.sharing.foreign.state_dict(),
        "loops": loops["loops"],
        "corrected": [[a, k, torch.from_numpy(T.copy())] for (a, k), T in be.corrected.items()],
        "rounds_closed": be.rounds_closed, "merges": be.merges,
        "pose_graph_runs": be.pose_graph_runs, "update_seq": dict(be.sharing.seq),
        "loop_book": loops["loop_book"], "queued": loops["queued"],
        "loops_skipped": loops["loops_skipped"],
    }


def restore_backend(be: Backend, state: dict) -> None:
    """Load a `backend_state` into `be`; the loop database is refilled from the keyframes."""
    be.state_id = int(state["state_id"])
    be.registry.load_state_dict(state["registry"])
    be.groups.load_state_dict(state["groups"])
    # Agents send their decoders as deltas against the group decoder they last received:
    # each group's current one is the base they refer to after the restart.
    for group in be.groups.groups.values():
        if group.decoder is not None and group.round > 0:
            be.registry.decoder_bases.add(group.group_id, group.round, group.decoder)
    be.sharing.foreign.load_state_dict(state["foreign"])
    be.pipeline.load_state_dict(state)
    be.corrected = {(a, int(k)): T.cpu().numpy().copy() for a, k, T in state["corrected"]}
    be.federator.rounds = {}
    be.federator.rounds_closed = list(state["rounds_closed"])
    be.merges = list(state["merges"])
    be.pose_graph_runs = list(state["pose_graph_runs"])
    be.sharing.seq = {str(a): int(s) for a, s in state["update_seq"].items()}
    new = set(be.registry.new_keyframes)
    for agent, rec in be.registry.agents.items():
        for kf in rec.kf_ids:
            if (agent, kf) not in new:
                be.database.add(agent, kf, rec.keyframes[kf].descriptor,
                                be.groups.group_of(agent).group_id)

"""Delivery messages: the agent's acknowledgement of server updates, the server's refusal.

`UpdateAck` closes the server -> agent direction: the agent puts it on
``agent/<agent>/update_ack`` after it applied (or, for a duplicate, had already applied) a
`ServerUpdate`, so the server marks foreign points delivered only once they are. `Refusal`
answers an agent incarnation the server will not mix into the world it already holds for that
agent id (see docs/protocol.md).
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from cpslam.protocol.base import Id, Message, Seq

__all__ = ["Refusal", "UpdateAck"]


class UpdateAck(Message):
    """The agent has applied the server's update `update_seq` (its latest)."""

    max_bytes = 4096
    type: Literal["update_ack"] = "update_ack"
    agent_id: Id
    """Acknowledging agent."""
    incarnation: Seq = 0
    """The agent's incarnation."""
    update_seq: Seq
    """Seq of the last `ServerUpdate` the agent applied (0: none yet)."""


class Refusal(Message):
    """The server refuses an agent incarnation; the agent stops (exit code REFUSED)."""

    max_bytes = 16384
    type: Literal["refusal"] = "refusal"
    agent_id: Id
    """Refused agent id."""
    incarnation: Seq
    """The refused incarnation (another incarnation of the same id is not concerned)."""
    reason: str = Field(default="", max_length=4096)
    """What to do about it, for the agent's log."""

"""What the back end hands the daemon to publish: `Outgoing`, a message with its addressee.

The back end has no transport; the daemon (`cpslam.server.node`) turns each `Outgoing` into
puts on the keys its ``scope`` names. Split out of `backend` for size (`backend` still
exports `Outgoing`).
"""

from __future__ import annotations

from dataclasses import dataclass

from cpslam.protocol import GroupDecoder, Message

__all__ = ["Outgoing", "to_groups"]


@dataclass(frozen=True)
class Outgoing:
    """A message to publish: to one agent (``scope`` "agent") or to a group's decoder key."""

    target: str
    message: Message
    scope: str = "agent"


def to_groups(decoders: list[GroupDecoder]) -> list[Outgoing]:
    """Each group decoder addressed to its group."""
    return [Outgoing(msg.group_id, msg, scope="group") for msg in decoders]

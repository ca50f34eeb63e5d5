"""What the server acknowledges of each agent's stream (the seq bookkeeping of `AgentRecord`).

Every seq at or below ``seq_floor`` was handled; handled seqs above it wait in ``seqs_above``
until the gap below them closes. An `Ack` carries the floor, the runs of handled seqs above it
(at most `MAX_ACK_RANGES`) and the seqs whose handling raised (``dropped``), so one lost
message stalls nothing and one that raised is never left hanging. A dropped message counts as
handled: the agent must not resend it forever.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from cpslam.protocol import Ack
from cpslam.protocol.updates import MAX_ACK_RANGES

if TYPE_CHECKING:
    from cpslam.server.records import AgentRecord

__all__ = ["ack", "handled", "mark_handled", "mark_raised"]


def handled(rec: AgentRecord, seq: int) -> bool:
    """The agent's message `seq` was handled already (a replay: acknowledge it again)."""
    return seq <= rec.seq_floor or seq in rec.seqs_above


def mark_handled(rec: AgentRecord, seq: int) -> None:
    """Record `seq` as handled and move the floor up over every seq handled without a gap."""
    rec.seqs_above.add(seq)
    while rec.seq_floor + 1 in rec.seqs_above:
        rec.seq_floor += 1
        rec.seqs_above.discard(rec.seq_floor)


def mark_raised(rec: AgentRecord, seq: int) -> None:
    """Record that handling `seq` raised (reported in the next acks; the newest kept)."""
    rec.raised = [*rec.raised, seq][-MAX_ACK_RANGES:]


def ack(rec: AgentRecord) -> list[Ack]:
    """The ack of what the agent's stream has had handled (none before its first message)."""
    if rec.seq_floor < 0 and not rec.seqs_above:
        return []
    return [Ack(agent_id=rec.agent_id, seq=rec.seq_floor, incarnation=rec.incarnation or 0,
                received=_ranges(rec.seqs_above)[:MAX_ACK_RANGES], dropped=list(rec.raised))]


def _ranges(seqs: set[int]) -> list[tuple[int, int]]:
    """Sorted inclusive (lo, hi) runs of `seqs`."""
    out: list[tuple[int, int]] = []
    for s in sorted(seqs):
        if out and out[-1][1] == s - 1:
            out[-1] = (out[-1][0], s)
        else:
            out.append((s, s))
    return out

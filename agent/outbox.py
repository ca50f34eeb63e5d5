"""The agent's outbox: messages sent and not yet acknowledged, with their send times.

An `Ack` covers a message when its seq is at or below the floor, inside one of the ack's
``received`` ranges, or among its ``dropped`` seqs (the server dropped it because handling
raised: resending it would only raise again). An ack claiming more than the agent has sent
(a floor or a range at or above `next_seq`) cannot be genuine and is ignored whole, with a
warning; so is one of another incarnation. A message older than ``resend_after_s`` since it
was last sent is due again (`due`), while streaming, so one lost message does not wait for
the end of the stream. The outbox is bounded (`full`): the daemon stops taking frames until
acks make room, so accepted data is never dropped.
"""

from __future__ import annotations

import logging
import time
from collections import OrderedDict
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np

from cpslam.protocol import Ack, Message

__all__ = ["Outbox", "message_bytes"]

logger = logging.getLogger(__name__)

MB = 1 << 20


def message_bytes(msg: Message) -> int:
    """Rough size of a message: its arrays' bytes plus a small header (for the outbox bound)."""
    total = 256
    for name in type(msg).model_fields:
        value: Any = getattr(msg, name)
        if isinstance(value, np.ndarray):
            total += value.nbytes
        elif isinstance(value, dict):
            total += sum(v.nbytes for v in value.values() if isinstance(v, np.ndarray))
    return total


class Outbox:
    """Unacknowledged messages by seq, oldest first.

    Args:
        max_messages: `full` once this many messages wait.
        max_mb: `full` once their estimated size reaches this (MiB).
        resend_after_s: a message is `due` again this long after it was last sent.
        now: monotonic clock (s).
    """

    def __init__(
        self,
        max_messages: int = 4096,
        max_mb: float = 512.0,
        resend_after_s: float = 5.0,
        now: Callable[[], float] = time.monotonic,
    ) -> None:
        if max_messages < 1 or max_mb <= 0 or resend_after_s <= 0:
            raise ValueError(
                f"Outbox: max_messages >= 1, max_mb > 0 and resend_after_s > 0 "
                f"expected, got {max_messages}, {max_mb}, {resend_after_s}"
            )
        self.max_messages, self.max_bytes = int(max_messages), int(max_mb * MB)
        self.resend_after_s, self.now = float(resend_after_s), now
        self._items: OrderedDict[int, tuple[Message, int, float]] = OrderedDict()
        self.bytes = 0
        self.floor = -1
        """Highest ack floor seen."""
        self.dropped_by_server: list[int] = []
        """Seqs the server reported dropped (handling raised); never resent."""
        self.ignored_acks = 0
        self.resent = 0

    def __len__(self) -> int:
        return len(self._items)

    def __contains__(self, seq: object) -> bool:
        return seq in self._items

    def __iter__(self) -> Iterator[int]:
        return iter(self._items)

    def __bool__(self) -> bool:
        return bool(self._items)

    def add(self, seq: int, msg: Message) -> None:
        size = message_bytes(msg)
        self._items[seq] = (msg, size, self.now())
        self.bytes += size

    def clear(self) -> None:
        """Forget every waiting message and the ack floor (the stream starts over)."""
        self._items.clear()
        self.bytes, self.floor = 0, -1

    def messages(self) -> list[Message]:
        """Every waiting message, oldest first."""
        return [m for m, _, _ in self._items.values()]

    def full(self) -> bool:
        """At the message or byte bound: take no new frame until acks make room."""
        return len(self._items) >= self.max_messages or self.bytes >= self.max_bytes

    def due(self, limit: int = 64) -> list[Message]:
        """Up to `limit` messages last sent ``resend_after_s`` ago or earlier (oldest first);
        their send time restarts (the caller sends them)."""
        t = self.now()
        out = []
        for seq, (msg, size, sent) in self._items.items():
            if len(out) >= limit:
                break
            if t - sent >= self.resend_after_s:
                out.append(msg)
                self._items[seq] = (msg, size, t)
        self.resent += len(out)
        return out

    def mark_sent(self) -> None:
        """Every waiting message was just sent again (a resend after the server came back)."""
        t = self.now()
        for seq, (msg, size, _) in self._items.items():
            self._items[seq] = (msg, size, t)

    def on_ack(self, ack: Ack, next_seq: int, incarnation: int) -> int:
        """Forget what `ack` covers; returns how many left. `next_seq`: the seq the next new
        message gets (an ack at or above it is forged or from another incarnation)."""
        if int(ack.incarnation) != incarnation:
            self._ignore(ack, f"incarnation {ack.incarnation}, this agent is {incarnation}")
            return 0
        top = max([int(ack.seq), *(hi for _, hi in ack.received), *ack.dropped])
        if top >= next_seq:
            self._ignore(ack, f"it covers seq {top}, only seqs < {next_seq} were sent")
            return 0
        self.floor = max(self.floor, int(ack.seq))
        dropped = set(ack.dropped)
        covered = [
            s
            for s in self._items
            if s <= self.floor or s in dropped or any(lo <= s <= hi for lo, hi in ack.received)
        ]
        for s in covered:
            if s in dropped:
                self.dropped_by_server.append(s)
                logger.warning(
                    "agent %s: the server dropped message seq %d (handling it "
                    "failed); not resending it",
                    ack.agent_id,
                    s,
                )
            self.bytes -= self._items.pop(s)[1]
        del self.dropped_by_server[:-1024]  # a log, not a store
        return len(covered)

    def _ignore(self, ack: Ack, why: str) -> None:
        self.ignored_acks += 1
        logger.warning("agent %s: ignoring ack (floor %d): %s", ack.agent_id, ack.seq, why)

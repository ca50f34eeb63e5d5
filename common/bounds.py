"""Bounded bookkeeping for state keyed by what peers send: counters and log lines.

A counter keyed by a remote key (a message key, a drop reason that quotes the message) grows
with every distinct key a peer invents; `CappedCounter` keeps at most ``max_keys`` of them and
counts the rest under ``"other"``. A warning per bad message becomes a flood of log lines;
`LogThrottle` lets one line per subject through per interval and says how many it held back.
`tensor_mismatch` checks named tensors from a peer against the shapes the local config gives.
"""

from __future__ import annotations

import threading
import time
from collections import Counter
from collections.abc import Callable, Iterator, Mapping
from typing import Any

__all__ = ["OTHER", "CappedCounter", "LogThrottle", "tensor_mismatch"]

OTHER = "other"
"""The bucket of a `CappedCounter` that takes every key beyond its cap."""


class CappedCounter(Mapping[str, int]):
    """Counts per key, at most `max_keys` keys (`OTHER` included): once ``max_keys - 1``
    keys are counted, further keys count under `OTHER`.

    Reads like a read-only mapping (``dict(counter)``, ``counter[key]``: 0 when absent).
    """

    def __init__(self, max_keys: int) -> None:
        if max_keys < 1:
            raise ValueError(f"max_keys must be >= 1, got {max_keys}")
        self.max_keys = int(max_keys)
        self._counts: Counter[str] = Counter()

    def add(self, key: str, count: int = 1) -> str:
        """Count `key` (or `OTHER` when the cap is reached); returns the key counted."""
        if key not in self._counts:
            named = len(self._counts) - (OTHER in self._counts)
            if named >= self.max_keys - 1:
                key = OTHER
        self._counts[key] += count
        return key

    def __getitem__(self, key: str) -> int:
        return self._counts.get(key, 0)

    def __iter__(self) -> Iterator[str]:
        return iter(self._counts)

    def __len__(self) -> int:
        return len(self._counts)

    def total(self) -> int:
        return sum(self._counts.values())


class LogThrottle:
    """At most one log line per subject per `interval_s`, plus the count of those held back.

    Args:
        interval_s: seconds between two lines of one subject.
        max_subjects: subjects remembered (oldest forgotten first), so the throttle itself is
            bounded when subjects come from peers.
        now: the clock (monotonic seconds), injectable for tests.
    """

    def __init__(
        self,
        interval_s: float = 5.0,
        max_subjects: int = 256,
        now: Callable[[], float] = time.monotonic,
    ) -> None:
        self.interval_s = float(interval_s)
        self.max_subjects = int(max_subjects)
        self.now = now
        self._last: dict[str, tuple[float, int]] = {}  # subject -> (last line at, held back)
        self._lock = threading.Lock()

    def allow(self, subject: str) -> int | None:
        """None: hold the line back; else the number of lines held back since the last one
        (log this line and mention them)."""
        t = self.now()
        with self._lock:
            last = self._last.get(subject)
            if last is not None and t - last[0] < self.interval_s:
                self._last[subject] = (last[0], last[1] + 1)
                return None
            self._last.pop(subject, None)
            while len(self._last) >= self.max_subjects:
                self._last.pop(next(iter(self._last)))
            self._last[subject] = (t, 0)
            return 0 if last is None else last[1]


def tensor_mismatch(
    tensors: Mapping[str, Any],
    expected: Mapping[str, tuple[int, ...]],
    source: str = "field config",
) -> str:
    """Why named `tensors` (anything with ``.shape``) are not of the `expected` names and
    shapes ("" if they are); the text names the field, what was expected and what came."""
    if set(tensors) != set(expected):
        missing = sorted(set(expected) - set(tensors))[:3]
        extra = sorted(set(tensors) - set(expected))[:3]
        return (
            f"field tensors: names differ from the {source}'s (missing {missing}, unknown {extra})"
        )
    for name, value in tensors.items():
        if tuple(value.shape) != tuple(expected[name]):
            return (
                f"field tensors[{name!r}] has shape {list(value.shape)}, expected "
                f"{list(expected[name])} ({source})"
            )
    return ""

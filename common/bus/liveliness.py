"""Presence: tokens a session declares, and watchers that see them come and go.

A token lives as long as it is declared and its session is alive; a crashed or killed process
loses its tokens when its transport drops (milliseconds for a closed socket, the lease for a
hung peer). Watchers keep the current member set and call `on_join` / `on_leave` exactly once
per change, whatever duplicates the transport produces.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable

logger = logging.getLogger(__name__)

__all__ = ["LivelinessToken", "LivelinessWatcher"]

MemberCallback = Callable[[str], object]


class LivelinessToken:
    """A declared presence on `key`; `undeclare()` (or closing the bus) withdraws it."""

    def __init__(self, key: str, undeclare: Callable[[], None]) -> None:
        self.key = key
        self._undeclare = undeclare
        self._lock = threading.Lock()
        self._alive = True

    @property
    def alive(self) -> bool:
        return self._alive

    def undeclare(self) -> None:
        """Withdraw the token. Idempotent."""
        with self._lock:
            if not self._alive:
                return
            self._alive = False
        self._undeclare()

    def __enter__(self) -> LivelinessToken:
        return self

    def __exit__(self, *exc: object) -> None:
        self.undeclare()


class LivelinessWatcher:
    """Tracks the tokens matching `key_expr`.

    Members already present when the watcher starts are reported through `on_join` as well
    (asynchronously, shortly after the watcher is created). Callbacks run on the bus's thread:
    keep them short; their exceptions are logged and swallowed.
    """

    def __init__(
        self,
        key_expr: str,
        on_join: MemberCallback | None = None,
        on_leave: MemberCallback | None = None,
    ) -> None:
        self.key_expr = key_expr
        self._on_join = on_join
        self._on_leave = on_leave
        self._members: set[str] = set()
        self._lock = threading.Lock()
        self._closed = False
        self._undeclare: Callable[[], None] | None = None

    def members(self) -> set[str]:
        """Keys of the tokens currently alive (a copy)."""
        with self._lock:
            return set(self._members)

    @property
    def closed(self) -> bool:
        return self._closed

    def close(self) -> None:
        """Stop watching. Idempotent."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            undeclare, self._undeclare = self._undeclare, None
        if undeclare is not None:
            undeclare()

    def __enter__(self) -> LivelinessWatcher:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- for bus implementations -------------------------------------------------------------

    def attach(self, undeclare: Callable[[], None]) -> None:
        """Register how to stop the underlying transport subscription."""
        with self._lock:
            if not self._closed:
                self._undeclare = undeclare
                return
        undeclare()

    def joined(self, key: str) -> None:
        """A token on `key` is alive (idempotent)."""
        with self._lock:
            if self._closed or key in self._members:
                return
            self._members.add(key)
        self._notify(self._on_join, "on_join", key)

    def left(self, key: str) -> None:
        """The token on `key` is gone (idempotent)."""
        with self._lock:
            if self._closed or key not in self._members:
                return
            self._members.discard(key)
        self._notify(self._on_leave, "on_leave", key)

    def _notify(self, callback: MemberCallback | None, name: str, key: str) -> None:
        if callback is None:
            return
        try:
            callback(key)
        except Exception:
            logger.exception(
                "liveliness %s callback for %r (watching %r) failed", name, key, self.key_expr
            )

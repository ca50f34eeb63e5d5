"""The one fake clock for tests: code that reads time through an injected callable
(`clock=`, `now=`) is driven by it, so a test asserts exact logic instead of waiting."""

from __future__ import annotations


class FakeClock:
    """A monotonic clock in seconds that only moves when told (`advance`, `sleep`, `now =`)."""

    def __init__(self, start: float = 100.0) -> None:
        self.now = float(start)

    def __call__(self) -> float:
        return self.now

    def advance(self, seconds: float) -> float:
        """Move forward by `seconds` (>= 0); returns the new time."""
        if seconds < 0:
            raise ValueError(f"a monotonic clock cannot go back ({seconds} s)")
        self.now += seconds
        return self.now

    sleep = advance  # for code that takes an injected `sleep` alongside the clock

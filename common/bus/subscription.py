"""The bounded subscription queue both buses hand out.

A bus's network thread only ever *offers* a sample to a subscription: the offer appends to a
bounded deque and returns at once, so a slow consumer can never stall the transport or the
publisher. The deque is bounded in samples (``queue_size``) and in payload bytes
(``max_bytes``). When it is full the **oldest** sample is dropped (the consumer sees the most
recent data, as Zenoh's RingChannel does), the drop is counted on the subscription and logged
at most once every few seconds.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass

logger = logging.getLogger(__name__)

__all__ = ["Sample", "Subscription"]

# One warning per subscription per interval: a flood of drops must not become a flood of logs.
DROP_LOG_INTERVAL_S = 5.0


@dataclass(frozen=True)
class Sample:
    """One received publication.

    `received_at` is `time.time()` when the bus took the sample off the network (before it
    waited in the queue), so `time.time() - received_at` is the queueing delay.
    """

    key: str
    payload: bytes
    received_at: float


class Subscription:
    """Samples matching one key expression, buffered in a bounded drop-oldest queue.

    The queue holds at most `queue_size` samples and, when `max_bytes` is set, at most that
    many payload bytes (the newest sample is always kept, even alone over the budget).

    Without a callback the owner pulls with `get()` or iterates; with a callback a worker
    thread owned by the subscription calls it for each sample (exceptions are logged, never
    propagated), and `get()` is not available. Iteration ends when the subscription closes.
    """

    def __init__(
        self,
        key_expr: str,
        queue_size: int = 64,
        callback: Callable[[Sample], object] | None = None,
        on_close: Callable[[Subscription], None] | None = None,
        max_bytes: int | None = None,
    ) -> None:
        if queue_size < 1:
            raise ValueError(f"queue_size must be >= 1, got {queue_size}")
        if max_bytes is not None and max_bytes < 1:
            raise ValueError(f"max_bytes must be >= 1, got {max_bytes}")
        self.key_expr = key_expr
        self.queue_size = queue_size
        self.max_bytes = max_bytes
        self._bytes = 0
        self._queue: deque[Sample] = deque()
        self._cond = threading.Condition()
        self._closed = False
        self._dropped = 0
        self._delivered = 0
        self._drops_unlogged = 0
        self._last_drop_log = -float("inf")
        self._callback = callback
        self._on_close = on_close
        self._worker: threading.Thread | None = None
        if callback is not None:
            self._worker = threading.Thread(
                target=self._run_callback, name=f"bus-sub[{key_expr}]", daemon=True
            )
            self._worker.start()

    @property
    def dropped(self) -> int:
        """Samples discarded because the queue was full."""
        with self._cond:
            return self._dropped

    @property
    def delivered(self) -> int:
        """Samples offered to this subscription (kept or later dropped)."""
        with self._cond:
            return self._delivered

    @property
    def closed(self) -> bool:
        return self._closed

    def get(self, timeout: float | None = None) -> Sample | None:
        """The oldest queued sample; waits up to `timeout` s (None: until one or close).

        Returns None on timeout or when the subscription is closed and empty.
        """
        if self._callback is not None:
            raise RuntimeError(
                f"subscription on {self.key_expr!r} has a callback; samples go to it, not get()"
            )
        return self._take(timeout)

    def wait(self, timeout: float | None = None) -> bool:
        """Block until a sample is queued (True) or `timeout` s passed or closed (False); the
        sample stays queued. For loops that serve several queues without busy-waiting."""
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._cond:
            while not self._queue and not self._closed:
                remaining = None if deadline is None else deadline - time.monotonic()
                if remaining is not None and remaining <= 0:
                    return False
                self._cond.wait(remaining)
            return bool(self._queue)

    def __iter__(self) -> Iterator[Sample]:
        while True:
            sample = self.get(None)
            if sample is None:
                return
            yield sample

    def __len__(self) -> int:
        with self._cond:
            return len(self._queue)

    def deliver(self, sample: Sample) -> None:
        """Offer a sample (called by the bus on its network thread); never blocks."""
        log_now = 0
        with self._cond:
            if self._closed:
                return
            self._delivered += 1
            self._queue.append(sample)
            self._bytes += len(sample.payload)
            while len(self._queue) > 1 and self._over():
                self._bytes -= len(self._queue.popleft().payload)
                self._dropped += 1
                self._drops_unlogged += 1
                now = time.monotonic()
                if now - self._last_drop_log >= DROP_LOG_INTERVAL_S:
                    log_now, self._drops_unlogged = self._drops_unlogged, 0
                    self._last_drop_log = now
                    total = self._dropped
            self._cond.notify()
        if log_now:
            logger.warning(
                "subscriber on %r is too slow: dropped %d oldest sample(s) (queue_size=%d, "
                "max_bytes=%s, %d dropped in total)",
                self.key_expr,
                log_now,
                self.queue_size,
                self.max_bytes,
                total,
            )

    @property
    def queued_bytes(self) -> int:
        """Payload bytes waiting in the queue."""
        with self._cond:
            return self._bytes

    def _over(self) -> bool:
        # Called with the condition held.
        if len(self._queue) > self.queue_size:
            return True
        return self.max_bytes is not None and self._bytes > self.max_bytes

    def close(self, timeout: float = 5.0) -> None:
        """Stop receiving and discard what is still queued; wakes waiting consumers.

        Idempotent; waits up to `timeout` s for a running callback to finish (0: not at all;
        `Bus.close` signals every subscription first and then joins them against one
        deadline, so N busy callbacks do not cost N timeouts).
        """
        with self._cond:
            if self._closed:
                return
            self._closed = True
            self._queue.clear()
            self._bytes = 0
            self._cond.notify_all()
        if self._on_close is not None:
            self._on_close(self)
        if timeout > 0:
            self.join(time.monotonic() + timeout)

    def join(self, deadline: float) -> bool:
        """Wait until the callback worker has ended or `deadline` (`time.monotonic()`) has
        passed; True when it ended (or there is none). Logs a callback still running."""
        worker = self._worker
        if worker is None or worker is threading.current_thread():
            return True
        worker.join(timeout=max(deadline - time.monotonic(), 0.0))
        if worker.is_alive():
            logger.warning("callback of subscriber on %r still running at close", self.key_expr)
            return False
        return True

    def __enter__(self) -> Subscription:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _take(self, timeout: float | None) -> Sample | None:
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._cond:
            while not self._queue:
                if self._closed:
                    return None
                if deadline is None:
                    self._cond.wait()
                else:
                    remaining = deadline - time.monotonic()
                    if remaining <= 0:
                        return None
                    self._cond.wait(remaining)
            sample = self._queue.popleft()
            self._bytes -= len(sample.payload)
            return sample

    def _run_callback(self) -> None:
        assert self._callback is not None
        while True:
            sample = self._take(None)
            if sample is None:
                return
            try:
                self._callback(sample)
            except Exception:
                logger.exception(
                    "subscriber callback on %r failed for key %r", self.key_expr, sample.key
                )

"""The server's state writer: snapshots of the accepted state made durable off the poll loop.

The poll loop hands a snapshot (the back end's `state_dict`, whose arrays are already copies)
to `StateWriter.submit` and gets a generation number; the writer serialises it with
`torch.save`, seals it and writes it as the newest generation of the state file
(`cpslam.common.durable.save_generation`: fsync of the file and the folder). `durable_gen`
is the newest generation on disk: the node releases the acks a snapshot covers only once its
generation is there.

A write that fails (a full disk, ENOSPC; an I/O error, EIO; anything else) leaves the server
running: the snapshot stays pending and is retried every `retry_s`, the acks it covers stay
held, and the failure is logged once per `log_every_s` (and once when writes succeed again).

`AckGate` holds the node's acks per generation and releases them once it is durable.

``background=False`` writes in the caller's thread (`submit` writes at once, `pump` retries
when due) so tests drive it step by step with an injected clock.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from cpslam.common import durable

__all__ = ["AckGate", "StateWriter", "detach"]

logger = logging.getLogger(__name__)


def detach(state: Any) -> Any:
    """A copy of the containers (dicts, lists, tuples) of `state`, sharing the leaves: the
    loop may append to its lists while the writer thread pickles the snapshot."""
    if isinstance(state, dict):
        return {k: detach(v) for k, v in state.items()}
    if isinstance(state, list | tuple):
        return type(state)(detach(v) for v in state)
    return state


class StateWriter:
    """Writes snapshots as generations of `path`, newest wins.

    Args:
        path: the state file (its previous generation is ``<path>.prev``).
        background: write on a thread of its own (False: in the caller's thread).
        retry_s: seconds between attempts while writes fail.
        log_every_s: at most one failure log line per this many seconds.
        clock: monotonic seconds (injectable for tests).
    """

    def __init__(
        self,
        path: str | Path,
        background: bool = True,
        retry_s: float = 1.0,
        log_every_s: float = 60.0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.path = Path(path)
        self.background = background
        self.retry_s, self.log_every_s = float(retry_s), float(log_every_s)
        self.clock = clock
        self.write: Callable[[Path, bytes], Any] = durable.save_generation
        """The function that stores the sealed bytes (replaceable to simulate a full disk)."""
        self.encode: Callable[[Any], bytes] = durable.torch_bytes
        self.durable_gen = 0
        """Newest generation known to be on disk."""
        self.failures = 0
        """Failed attempts since the last successful write."""
        self.seconds_last = 0.0
        """Seconds the last successful write took (serialise, write, fsync)."""
        self._gen = 0
        self._attempted = 0
        self._next: tuple[int, Any] | None = None
        self._writing = False
        self._retry_at = float("-inf")
        self._logged_at = float("-inf")
        self._closed = False
        self._cond = threading.Condition()
        self._thread: threading.Thread | None = None
        if background:
            self._thread = threading.Thread(target=self._run, name="state-writer", daemon=True)
            self._thread.start()

    @property
    def busy(self) -> bool:
        """A snapshot is waiting, being written or failed and waiting for its retry."""
        with self._cond:
            return self._next is not None or self._writing

    def submit(self, snapshot: Any) -> int:
        """Queue `snapshot` (replacing one not yet started) and return its generation."""
        with self._cond:
            if self._closed:
                raise RuntimeError(f"{self.path}: the state writer is closed")
            self._gen += 1
            gen = self._gen
            self._next = (gen, snapshot)
            self._retry_at = float("-inf")  # a new snapshot is tried at once
            self._cond.notify_all()
        if not self.background:
            self.pump()
        return gen

    def pump(self) -> None:
        """Synchronous mode: write the pending snapshot if its attempt is due."""
        if self.background:
            return
        with self._cond:
            if self._next is None or self.clock() < self._retry_at:
                return
            gen, snapshot = self._next
            self._next, self._writing = None, True
        self._attempt(gen, snapshot)

    def wait(self, gen: int, timeout_s: float | None = None) -> bool:
        """Wait until generation `gen` was attempted at least once; True if it is durable."""
        if not self.background:
            self.pump()
            return self.durable_gen >= gen
        with self._cond:
            self._cond.wait_for(lambda: self._attempted >= gen or self._closed, timeout_s)
            return self.durable_gen >= gen

    def close(self, timeout_s: float = 60.0) -> None:
        """Stop the thread after the write in progress (a pending one is dropped: its acks
        were never sent, so the agents resend)."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()
        if self._thread is not None:
            self._thread.join(timeout_s)

    # ------------------------------------------------------------------------- internals

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._closed and (self._next is None or self.clock() < self._retry_at):
                    wait = None if self._next is None else self._retry_at - self.clock()
                    self._cond.wait(None if wait is None else max(wait, 0.01))
                if self._closed:
                    return
                gen, snapshot = self._next
                self._next, self._writing = None, True
            self._attempt(gen, snapshot)

    def _attempt(self, gen: int, snapshot: Any) -> None:
        t0 = time.perf_counter()
        try:
            self.write(self.path, self.encode(snapshot))
        except Exception as exc:  # noqa: BLE001 - a failed write holds acks, never kills
            self._failed(gen, snapshot, exc)
            return
        with self._cond:
            if self.failures:
                logger.warning(
                    "%s: state written again after %d failed attempts; held acks are released",
                    self.path,
                    self.failures,
                )
            self.failures, self._logged_at = 0, float("-inf")
            self.durable_gen = max(self.durable_gen, gen)
            self._attempted = max(self._attempted, gen)
            self.seconds_last = time.perf_counter() - t0
            self._writing = False
            self._cond.notify_all()

    def _failed(self, gen: int, snapshot: Any, exc: Exception) -> None:
        with self._cond:
            self.failures += 1
            now = self.clock()
            self._retry_at = now + self.retry_s
            if self._next is None:  # keep it for the retry unless a newer one came
                self._next = (gen, snapshot)
            self._attempted = max(self._attempted, gen)
            self._writing = False
            log = now - self._logged_at >= self.log_every_s
            if log:
                self._logged_at = now
            self._cond.notify_all()
        if log:
            what = (
                f"{type(exc).__name__}: {exc}"
                if not isinstance(exc, OSError)
                else f"{exc.strerror or exc} (errno {exc.errno})"
            )
            logger.error(
                "%s: cannot write the server state: %s; the server goes on with "
                "acks held and retries every %.1f s (%d failed attempts so far, "
                "next report in %.0f s)",
                self.path,
                what,
                self.retry_s,
                self.failures,
                self.log_every_s,
            )


class AckGate:
    """Acks held until the state that contains their messages is durable.

    `hold` keeps the newest ack per agent (acks are cumulative: every seq up to this one), so
    a long full disk holds one per agent. `tick` (each poll) publishes the acks whose snapshot
    is on disk and, when `every_s` has passed and the writer is free, hands it a new snapshot
    covering the held ones.

    Args:
        writer: the state writer.
        every_s: at most one snapshot per this many seconds.
        publish: sends released acks.
        clock: monotonic seconds (injectable for tests).
    """

    def __init__(
        self,
        writer: StateWriter,
        every_s: float,
        publish: Callable[[list[Any]], None],
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.writer, self.every_s, self.publish, self.clock = writer, float(every_s), publish, clock
        self.held: dict[str, Any] = {}
        """Agent -> its newest ack not yet in a snapshot."""
        self.covered: list[tuple[int, list[Any]]] = []
        """(generation, the acks it covers), oldest first."""
        self.last_snapshot = float("-inf")

    @property
    def pending(self) -> bool:
        """Some ack is not yet sent."""
        return bool(self.held or self.covered)

    def hold(self, ack: Any) -> None:
        """Keep `ack` (an outgoing message with ``target`` and ``message.seq``)."""
        held = self.held.get(ack.target)
        if held is None or ack.message.seq >= held.message.seq:
            self.held[ack.target] = ack

    def tick(self, snapshot: Callable[[], Any]) -> None:
        """Release what is durable; snapshot again when due and the writer is free."""
        self.writer.pump()
        self.release()
        if self.held and not self.writer.busy and self.clock() - self.last_snapshot >= self.every_s:
            self.submit(snapshot())
            self.release()

    def submit(self, state: Any) -> int:
        """Hand `state` to the writer as covering every held ack; returns its generation."""
        gen = self.writer.submit(state)
        self.covered.append((gen, list(self.held.values())))
        self.held, self.last_snapshot = {}, self.clock()
        return gen

    def release(self) -> None:
        """Publish the acks of every generation on disk."""
        durable_gen = self.writer.durable_gen
        while self.covered and self.covered[0][0] <= durable_gen:
            self.publish(self.covered.pop(0)[1])

"""Child processes of `cpslam demo`: each in its own process group with its output in a log
file, watched for exits it should not make, stopped with one SIGINT (then SIGKILL).

Why one SIGINT only: the server treats a second SIGINT as "exit without finalising", so a
Ctrl-C in the terminal must reach only the supervising process, which forwards it once.
"""

from __future__ import annotations

import logging
import signal
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path
from typing import IO

__all__ = ["Child", "ChildFailed", "Supervisor"]

logger = logging.getLogger(__name__)


class ChildFailed(RuntimeError):
    """A supervised process exited when it should not have."""

    def __init__(self, name: str, code: int | None, log: Path, why: str = "") -> None:
        self.name, self.code, self.log = name, code, log
        what = why or f"exited with code {code}"
        super().__init__(f"{name} {what}; its log: {log}\n{_tail(log)}")


@dataclass
class Child:
    name: str
    proc: subprocess.Popen
    log: Path
    may_exit: bool
    """True: exit 0 is the normal end (agents); False: any exit is a failure (server)."""
    stream: IO[bytes]


class Supervisor:
    """Starts processes with their output in ``log_dir/<name>.log`` and watches them."""

    def __init__(self, log_dir: Path, env: dict[str, str] | None = None) -> None:
        self.log_dir = Path(log_dir)
        self.env = env
        self.children: dict[str, Child] = {}

    def __enter__(self) -> Supervisor:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def start(self, name: str, argv: list[str], may_exit: bool = True) -> Child:
        self.log_dir.mkdir(parents=True, exist_ok=True)
        log = self.log_dir / f"{name}.log"
        stream = log.open("wb")
        # Own process group: a Ctrl-C in the terminal reaches only us, and we forward it once
        # (the server treats a second SIGINT as "exit without finalising").
        proc = subprocess.Popen(argv, stdout=stream, stderr=subprocess.STDOUT, env=self.env,
                                stdin=subprocess.DEVNULL, start_new_session=True)
        child = Child(name, proc, log, may_exit, stream)
        self.children[name] = child
        logger.info("started %s (pid %d): %s", name, proc.pid, " ".join(argv))
        return child

    def running(self, name: str) -> bool:
        return self.children[name].proc.poll() is None

    def check(self) -> None:
        """Raise `ChildFailed` for the first child that exited when it should not have."""
        for child in self.children.values():
            code = child.proc.poll()
            if code is not None and (code != 0 or not child.may_exit):
                raise ChildFailed(child.name, code, child.log)

    def close(self, grace_s: float = 60.0) -> None:
        """SIGINT to every child still running, then SIGKILL after `grace_s`."""
        live = [c for c in self.children.values() if c.proc.poll() is None]
        for child in live:
            child.proc.send_signal(signal.SIGINT)
        deadline = time.monotonic() + grace_s
        try:
            for child in live:
                try:
                    child.proc.wait(max(deadline - time.monotonic(), 0.01))
                except subprocess.TimeoutExpired:
                    logger.warning("%s did not stop within %.0f s; killing it", child.name,
                                   grace_s)
        except KeyboardInterrupt:
            logger.warning("second interrupt: killing the children")
        finally:
            for child in self.children.values():
                if child.proc.poll() is None:
                    child.proc.kill()
                    child.proc.wait()
                child.stream.close()


def _tail(path: Path, lines: int = 15) -> str:
    try:
        text = path.read_text(errors="replace").splitlines()
    except OSError:
        return ""
    return "\n".join(f"  | {line}" for line in text[-lines:])

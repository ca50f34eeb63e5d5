"""Start the real daemons (`cpslam-server`, `cpslam-agent`) as OS processes for tests.

Each process logs to a file in the test's folder; a failed assertion shows its tail.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

# Every daemon of a test gets one torch thread: the machine has few cores and several
# processes share them.
ENV = {**os.environ, "OMP_NUM_THREADS": "1", "CPSLAM_RUN__NUM_THREADS": "1"}


class Daemon:
    """One daemon process with its log file."""

    def __init__(self, name: str, args: list[str], log_dir: Path,
                 prefix: list[str] | None = None) -> None:
        self.name, self.args = name, args
        self.log = log_dir / f"{name}.log"
        self._fh = self.log.open("w")
        self.proc = subprocess.Popen([*(prefix or []), sys.executable, *args],
                                     stdout=self._fh, stderr=subprocess.STDOUT, env=ENV)

    def wait(self, timeout: float) -> int:
        try:
            return self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            raise AssertionError(f"{self.name} still running after {timeout} s\n"
                                 f"{self.tail()}") from None

    def signal(self, sig: int = signal.SIGTERM) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(sig)

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(10)

    def tail(self, n: int = 40) -> str:
        self._fh.flush()
        lines = self.log.read_text(errors="replace").splitlines()
        return f"--- {self.name} (exit {self.proc.poll()}) ---\n" + "\n".join(lines[-n:])

    def text(self) -> str:
        return self.log.read_text(errors="replace")


def server_args(endpoint: str, session: str, out: Path, *extra: str) -> list[str]:
    return ["-m", "cpslam.server.cli", "--listen", endpoint, "--session", session,
            "--preset", "tiny", "--out", str(out), *extra]


def agent_args(seq: Path, agent_id: str, endpoint: str, session: str, out: Path,
               *extra: str) -> list[str]:
    return ["-m", "cpslam.agent_cli", "--seq", str(seq), "--agent-id", agent_id,
            "--connect", endpoint, "--session", session, "--preset", "tiny", "--out", str(out),
            "--no-progress", *extra]


def status(endpoint: str, session: str, timeout: float = 10.0, *extra: str) -> dict | None:
    """The server's status summary through `cpslam status --json` (None if no answer);
    `extra`: more flags, e.g. ("--config", "operator.yaml")."""
    done = subprocess.run([sys.executable, "-m", "cpslam", "status", "--connect", endpoint,
                           "--session", session, "--json", "--timeout", str(timeout), *extra],
                          capture_output=True, text=True, env=ENV, timeout=timeout + 30)
    if done.returncode != 0:
        return None
    return json.loads(done.stdout)


def agent_field(endpoint: str, session: str, agent: str, name: str, default):
    """One field of one agent in the server's status (`default` when there is no answer)."""
    summary = status(endpoint, session) or {}
    return summary.get("agents", {}).get(agent, {}).get(name, default)


def finalise(endpoint: str, session: str, timeout: float = 180.0, *extra: str) -> None:
    done = subprocess.run([sys.executable, "-m", "cpslam", "finalise", "--connect", endpoint,
                           "--session", session, "--timeout", str(timeout), *extra],
                          capture_output=True, text=True, env=ENV, timeout=timeout + 30)
    assert done.returncode == 0, done.stdout + done.stderr


def wait_until(what: str, check: Callable[[], bool], timeout: float,
               *daemons: Daemon, every: float = 1.0) -> None:
    """Poll `check` until it holds; fail naming `what` (with the daemons' logs) if not."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if check():
            return
        for d in daemons:
            if d.proc.poll() not in (None, 0):
                raise AssertionError(f"{d.name} died while waiting for {what}\n{d.tail()}")
        time.sleep(every)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}\n"
                         + "\n".join(d.tail() for d in daemons))


def tum_rows(path: Path) -> int:
    return sum(1 for line in path.read_text().splitlines()
               if line.strip() and not line.startswith("#"))

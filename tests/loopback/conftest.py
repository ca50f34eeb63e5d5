"""Helpers for loopback tests: free ports and peer processes that are always cleaned up."""

from __future__ import annotations

import queue
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from cpslam.demo import free_port

HERE = Path(__file__).resolve().parent




class Peer:
    """A child Python process whose stdout lines are collected by a reader thread."""

    def __init__(self, args: list[str]) -> None:
        self.args = args
        self.proc = subprocess.Popen(
            [sys.executable, *args],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        self._lines: queue.Queue[str] = queue.Queue()
        self._stderr: list[str] = []
        threading.Thread(
            target=self._pump, args=(self.proc.stdout, self._lines.put), daemon=True
        ).start()
        threading.Thread(
            target=self._pump, args=(self.proc.stderr, self._stderr.append), daemon=True
        ).start()

    @staticmethod
    def _pump(stream, sink: Callable[[str], None]) -> None:
        for line in stream:
            sink(line.rstrip("\n"))

    def expect(self, prefix: str, timeout: float = 15.0) -> str:
        """Wait for a stdout line starting with `prefix`; fail with the peer's stderr if not."""
        deadline = time.monotonic() + timeout
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                break
            try:
                line = self._lines.get(timeout=min(remaining, 0.2))
            except queue.Empty:
                if self.proc.poll() is not None and self._lines.empty():
                    break
                continue
            if line.startswith(prefix):
                return line
        stderr = "\n".join(self._stderr[-30:])
        raise AssertionError(
            f"peer {self.args} printed no {prefix!r} in {timeout} s "
            f"(exit code {self.proc.poll()}); stderr:\n{stderr}"
        )

    def stop(self, timeout: float = 5.0) -> int:
        """Ask the peer to exit (close its stdin); kill it if it does not."""
        if self.proc.poll() is None:
            try:
                self.proc.stdin.close()
            except OSError:
                pass
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout)
        return self.proc.returncode

    def kill(self) -> None:
        self.proc.kill()
        self.proc.wait(5.0)


@pytest.fixture(scope="session")
def apartment(tmp_path_factory: pytest.TempPathFactory):
    """Two agents in the synthetic apartment; they meet from about frame 170 of 300 (made
    once per test run: the daemon tests over TCP and over mutual TLS share it)."""
    pytest.importorskip("open3d")  # the synthetic renderer
    from cpslam.tools.synth import generate

    return generate(tmp_path_factory.mktemp("apt") / "apt", scene="apartment", agents=2,
                    frames=300, seed=0)


@pytest.fixture
def endpoint() -> str:
    """A Zenoh TCP endpoint on 127.0.0.1 with a free port."""
    return f"tcp/127.0.0.1:{free_port()}"


@pytest.fixture
def spawn() -> Iterator[Callable[..., Peer]]:
    """`spawn("script.py", *args)` starts tests/loopback/<script> and kills it at teardown."""
    peers: list[Peer] = []

    def start(script: str, *args: str) -> Peer:
        peer = Peer([str(HERE / script), *args])
        peers.append(peer)
        return peer

    yield start
    for peer in peers:
        if peer.proc.poll() is None:
            peer.kill()


@pytest.fixture
def daemons() -> Iterator[list]:
    """Daemons a test starts (`tests/loopback/daemons.Daemon`), killed at teardown."""
    started: list = []
    yield started
    for d in started:
        d.kill()

"""The networked agent's waits for the server: announced at once, interrupted promptly."""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from cpslam.agent.daemon import ServerPresence, run_networked
from cpslam.common.bus import InMemoryBus, InMemoryNetwork, ZenohBus, open_client
from cpslam.common.cli import ExitCode
from cpslam.common.config import load_config, override_config
from cpslam.demo import free_port

SESSION = "waits"
# These waits run over real sockets and threads, so no fake clock: the bounds below only tell
# "prompt" (the code takes well under a second) from "waited out the long timeout", and are
# generous so that a loaded 2-core runner passes.
PROMPT_S = 10.0
# One open attempt towards a port nobody listens on lasts this long, well above PROMPT_S.
OPEN_ATTEMPT_S = 30.0


def _cfg(port: int, open_timeout_s: float = 5.0):
    return override_config(load_config("tiny", env={}), [
        f"transport.connect=tcp/127.0.0.1:{port}", f"transport.session={SESSION}",
        f"transport.open_timeout_s={open_timeout_s}"])


class _StopOn(logging.Handler):
    """Sets `stop` shortly after a log line containing `text` (records when it did)."""

    def __init__(self, text: str, stop: threading.Event, delay_s: float = 0.3) -> None:
        super().__init__(logging.INFO)
        self.text, self.stop, self.delay_s = text, stop, delay_s
        self.stopped_at: float | None = None

    def emit(self, record: logging.LogRecord) -> None:
        if self.text in record.getMessage() and self.stopped_at is None:
            self.stopped_at = time.monotonic() + self.delay_s
            threading.Timer(self.delay_s, self.stop.set).start()


def test_open_client_says_it_waits_before_the_first_attempt_fails_and_stops(caplog) -> None:
    port = free_port()
    stop = threading.Event()
    stopper = _StopOn("waiting for the server at", stop)
    logging.getLogger("cpslam.common.bus.factory").addHandler(stopper)
    t0 = time.monotonic()
    try:
        with caplog.at_level(logging.INFO, logger="cpslam.common.bus.factory"):
            bus = open_client(_cfg(port, OPEN_ATTEMPT_S).transport, 120.0, "agent w", stop)
    finally:
        logging.getLogger("cpslam.common.bus.factory").removeHandler(stopper)
    assert bus is None and stop.is_set()
    # Announced about a second in, while the first open attempt was still under way...
    assert stopper.stopped_at is not None and stopper.stopped_at - t0 < PROMPT_S
    assert f"tcp/127.0.0.1:{port}" in caplog.text
    # ...and the stop request did not wait for that attempt either.
    assert time.monotonic() - stopper.stopped_at < PROMPT_S


def test_presence_wait_honours_stop() -> None:
    with InMemoryBus() as bus:
        presence = ServerPresence(bus, SESSION)
        stop = threading.Event()
        threading.Timer(0.2, stop.set).start()
        t0 = time.monotonic()
        assert presence.wait(120.0, stop) is False
        assert time.monotonic() - t0 < PROMPT_S
        assert presence.wait(0.05) is False  # no stop: plain timeout
        presence.close()


def test_presence_wait_for_wakes_when_the_token_comes_and_goes() -> None:
    from cpslam.protocol import keys

    network = InMemoryNetwork()
    with InMemoryBus(network) as server_bus, InMemoryBus(network) as agent_bus:
        presence = ServerPresence(agent_bus, SESSION)
        token = server_bus.declare_liveliness(keys.alive_server(SESSION, 7))
        # Both changes reach the watcher on the bus's dispatcher thread, not this one.
        assert presence.wait_for(lambda p: p.up and p.state == 7, PROMPT_S)
        t0 = time.monotonic()
        token.undeclare()
        assert presence.wait_for(lambda p: not p.up, 120.0)
        assert time.monotonic() - t0 < PROMPT_S
        assert presence.joins == 1
        assert presence.wait_for(lambda p: p.joins == 2, 0.05) is False  # plain timeout
        presence.close()


def test_connected_without_a_server_is_logged_and_interruptible(tmp_path: Path,
                                                                caplog) -> None:
    port = free_port()
    stop = threading.Event()
    stopper = _StopOn("waiting for a cpslam-server on session", stop)
    logging.getLogger("cpslam.agent.daemon").addHandler(stopper)
    # A bare Zenoh router: the agent connects, but no server token ever appears.
    with ZenohBus(mode="router", listen=[f"tcp/127.0.0.1:{port}"]):
        try:
            with caplog.at_level(logging.INFO, logger="cpslam.agent.daemon"):
                code = run_networked(_cfg(port), None, "w", tmp_path, "cpu",  # type: ignore
                                     wait_timeout_s=120.0, show_progress=False, stop=stop)
        finally:
            logging.getLogger("cpslam.agent.daemon").removeHandler(stopper)
    assert code == ExitCode.INTERRUPTED
    assert stopper.stopped_at is not None and time.monotonic() - stopper.stopped_at < PROMPT_S
    assert "interrupted while waiting for the server" in caplog.text


@pytest.mark.slow
def test_sigint_while_waiting_for_the_server_exits_130(tmp_path: Path) -> None:
    from cpslam.demo import scene_data

    seq = scene_data(tmp_path, "room", 1, 3, 16, 12, seed=0, show_progress=False)[0]
    proc = subprocess.Popen(
        [sys.executable, "-m", "cpslam.agent_cli", "--seq", str(seq), "--preset", "tiny",
         "--connect", f"tcp/127.0.0.1:{free_port()}", "--wait-timeout", "120",
         "--no-progress", "--out", str(tmp_path / "run")],
        env={**os.environ, "CPSLAM_TRANSPORT__OPEN_TIMEOUT_S": str(OPEN_ATTEMPT_S)},
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    lines: list[str] = []
    try:
        assert proc.stdout is not None
        for line in proc.stdout:  # ends when the process closes its output
            lines.append(line)
            if "waiting for the server at" in line:
                break
        t0 = time.monotonic()
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    text = "".join(lines) + out
    assert proc.returncode == 130, text
    # Not the 120 s wait, nor an open attempt (a real process: a generous bound).
    assert time.monotonic() - t0 < PROMPT_S, text
    assert "Traceback" not in text and "interrupted while waiting" in text

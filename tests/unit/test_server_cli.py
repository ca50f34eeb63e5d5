"""`cpslam-server`'s signals: the first finalises, a repeat of it within a second is the same
request (process-group wrappers deliver it twice), a later or different one exits 130."""

from __future__ import annotations

import signal
import threading

import pytest
from fake_clock import FakeClock
from typer.testing import CliRunner

from cpslam.common.cli import signal_handler
from cpslam.server.cli import REPEAT_WINDOW_S, app


def test_the_same_signal_twice_at_once_is_one_request(fake_clock: FakeClock) -> None:
    stop, clock = threading.Event(), fake_clock
    handler = signal_handler(stop, clock=clock, window_s=REPEAT_WINDOW_S, action="finalising")
    handler(signal.SIGTERM, None)
    assert stop.is_set()
    clock.advance(0.05)
    handler(signal.SIGTERM, None)  # e.g. `timeout`: to the process, then to its group
    clock.advance(REPEAT_WINDOW_S)
    with pytest.raises(SystemExit) as exit_info:
        handler(signal.SIGTERM, None)  # a deliberate second request
    assert exit_info.value.code == 130


def test_a_different_second_signal_exits_at_once(fake_clock: FakeClock) -> None:
    stop, clock = threading.Event(), fake_clock
    handler = signal_handler(stop, clock=clock, window_s=REPEAT_WINDOW_S, action="finalising")
    handler(signal.SIGTERM, None)
    clock.advance(0.1)
    with pytest.raises(SystemExit) as exit_info:
        handler(signal.SIGINT, None)
    assert exit_info.value.code == 130


def test_help_documents_the_second_signal() -> None:
    result = CliRunner().invoke(app, ["--help"], terminal_width=200)
    assert result.exit_code == 0
    text = " ".join(result.output.split())
    assert "exits at once with code 130" in text and "within 1 s is ignored" in text

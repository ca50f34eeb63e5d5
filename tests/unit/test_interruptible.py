"""`common.cli.interruptible`: work that a signal must never interrupt from inside (an
end-of-run report in matplotlib or Open3D code) runs on a worker thread; its value and its
errors come back, and a signal exits 130 at once, saying what was cut short."""

from __future__ import annotations

import signal
import subprocess
import sys
import threading

import pytest

from cpslam.common.cli import interruptible


def test_value_and_error_come_back_to_the_caller() -> None:
    # Whatever the caller had (a shell that starts a job in the background ignores SIGINT).
    before = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    threads: list[str] = []

    def work() -> int:
        threads.append(threading.current_thread().name)
        return 42

    assert interruptible(work, "the sum") == 42
    assert threads == ["the sum"]  # ran off the main thread, where no signal is raised

    def broken() -> None:
        raise ValueError("bad run folder")

    with pytest.raises(ValueError, match="bad run folder"):
        interruptible(broken, "the report")
    # The handlers the caller had are back.
    assert (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)) == before


def test_off_the_main_thread_it_just_runs() -> None:
    result: list[int] = []
    t = threading.Thread(target=lambda: result.append(interruptible(lambda: 7, "x")))
    t.start()
    t.join()
    assert result == [7]


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_exits_130_at_once_and_names_the_work(sig: signal.Signals) -> None:
    code = ("import logging, sys, time\n"
            "from cpslam.common.cli import interruptible\n"
            "logging.basicConfig(level=logging.INFO)\n"
            "def work():\n"
            "    print('ready', flush=True)  # the handlers are in place by now\n"
            "    time.sleep(60)\n"
            "interruptible(work, 'the report of runs/x')\n"
            "print('not reached')\n")
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    assert proc.stdout is not None and proc.stdout.readline().strip() == "ready"
    proc.send_signal(sig)
    out, _ = proc.communicate(timeout=30)  # well under the 60 s the work would take
    assert proc.returncode == 130, out
    assert f"{sig.name}: the report of runs/x interrupted" in out
    assert "not reached" not in out and "Traceback" not in out

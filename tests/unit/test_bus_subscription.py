"""The bounded subscription queue on its own: drop-oldest, rate-limited warnings, close."""

from __future__ import annotations

import logging
import threading

import pytest

from cpslam.common.bus import Sample, Subscription
from cpslam.common.bus import subscription as subscription_module


def sample(i: int) -> Sample:
    return Sample(f"k/{i}", str(i).encode(), 0.0)


def test_drop_oldest_and_warn_once_per_interval(
    caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(subscription_module, "DROP_LOG_INTERVAL_S", 3600.0)
    sub = Subscription("k/*", queue_size=2)
    with caplog.at_level(logging.WARNING):
        for i in range(10):
            sub.deliver(sample(i))
    assert sub.dropped == 8 and sub.delivered == 10 and len(sub) == 2
    assert [sub.get(0).key, sub.get(0).key] == ["k/8", "k/9"]
    warnings = [r for r in caplog.records if "too slow" in r.getMessage()]
    assert len(warnings) == 1 and "'k/*'" in warnings[0].getMessage()


def test_warning_repeats_after_interval(
    caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(subscription_module, "DROP_LOG_INTERVAL_S", 0.0)
    sub = Subscription("k/*", queue_size=1)
    with caplog.at_level(logging.WARNING):
        for i in range(4):
            sub.deliver(sample(i))
    assert len([r for r in caplog.records if "too slow" in r.getMessage()]) == 3


def test_get_timeout_and_close_wakes_waiters() -> None:
    sub = Subscription("k/*")
    assert sub.get(timeout=0.05) is None
    results: list[Sample | None] = []
    waiter = threading.Thread(target=lambda: results.append(sub.get()))
    waiter.start()
    sub.deliver(sample(1))
    waiter.join(2.0)
    assert results[0] is not None and results[0].key == "k/1"
    sub.deliver(sample(2))
    sub.close()
    assert sub.get(0) is None  # pending samples are discarded at close
    sub.deliver(sample(3))
    assert sub.delivered == 2
    assert list(sub) == []


def test_close_from_inside_callback_does_not_deadlock() -> None:
    done = threading.Event()
    holder: list[Subscription] = []

    def callback(s: Sample) -> None:
        holder[0].close()
        done.set()

    sub = Subscription("k/*", callback=callback)
    holder.append(sub)
    sub.deliver(sample(1))
    assert done.wait(2.0)
    assert sub.closed


def test_queue_size_must_be_positive() -> None:
    with pytest.raises(ValueError, match="queue_size"):
        Subscription("k", queue_size=0)

"""Counting refused messages and rate-limiting their log lines."""

from __future__ import annotations

import logging
import threading

import pytest

from impulse.bus.rejects import RejectCounter


class StepClock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def test_counts_by_reason_and_logs_once_per_interval(caplog: pytest.LogCaptureFixture) -> None:
    clock = StepClock()
    counter = RejectCounter(log_every_s=10.0, clock=clock)
    with caplog.at_level(logging.WARNING, logger="impulse.bus"):
        counter.record("bad_magic", "impulse/r/v1/traj/a0", "frame starts with b'XXXX'")
        for _ in range(5):
            counter.record("bad_magic", "impulse/r/v1/traj/a1", "frame starts with b'YYYY'")
        counter.record("stale", "a2", "policy 3 behind")
        clock.now += 10.0
        counter.record("bad_magic", "impulse/r/v1/traj/a3", "frame starts with b'ZZZZ'")
    assert counter.counts() == {"bad_magic": 7, "stale": 1}
    assert counter.total == 8
    lines = [record.getMessage() for record in caplog.records if record.name == "impulse.bus"]
    assert len(lines) == 3
    assert "reason=bad_magic" in lines[0] and "source=impulse/r/v1/traj/a0" in lines[0] and "XXXX" in lines[0]
    assert "reason=stale" in lines[1] and "(0 more" in lines[1]
    assert "traj/a3" in lines[2] and "(5 more" in lines[2]


def test_unknown_reason_is_a_programming_error() -> None:
    with pytest.raises(ValueError, match="unknown reject reason"):
        RejectCounter().record("bad vibes", "x", "y")


def test_counting_is_thread_safe() -> None:
    counter = RejectCounter(log_every_s=3600.0)
    threads = [
        threading.Thread(target=lambda: [counter.record("truncated", "t", "d") for _ in range(2000)]) for _ in range(4)
    ]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert counter.counts() == {"truncated": 8000}

"""The shared run loop's checkpoint cadence: on the configured updates, and once more at the end only if updates
were made since the last checkpoint. A process stopped before its first update writes no checkpoint (one of
update 0 would make the next start of the same run refuse its directory as one that already holds checkpoints)."""

from __future__ import annotations

import io
import json

from impulse.bus.service import CycleReport, Progress
from impulse.deploy.runtime.progress import ProgressLine
from impulse.deploy.runtime.runloop import LoopOptions, run_loop


class CountingService:
    """A service that makes one update per cycle until `updates` and records the updates it was saved at."""

    def __init__(self, updates: int, done: int = 0):
        self.update = self.first = done
        self.target = done + updates
        self.started = self.closed = 0
        self.saved_at: list[int] = []

    def start(self) -> None:
        self.started += 1

    def cycle(self) -> CycleReport:
        assert self.started == 1, "the loop starts the service once, before its first cycle"
        self.update += 1
        return CycleReport(env_steps=10, updates=1, metrics={"episodes": 1.0, "solved": 1.0, "return_sum": 1.0})

    def save(self, summary: dict[str, float]) -> None:
        self.saved_at.append(self.update)

    def finished(self) -> bool:
        return self.update >= self.target

    def progress(self) -> Progress:
        return Progress(env_steps_done=10 * self.first, updates_done=self.first, total_env_steps=1000)

    def close(self) -> None:
        self.closed += 1


def run(service: CountingService, *, every: int, stop_after: int | None = None) -> None:
    run_loop(service, LoopOptions(checkpoint_every=every, progress=ProgressLine(1000, stream=io.StringIO()),
                                  should_stop=None if stop_after is None else lambda: service.update >= stop_after))
    assert service.started == 1 and service.closed == 1, "the loop starts and closes the service once"


def test_a_service_stopped_before_its_first_update_writes_no_checkpoint() -> None:
    service = CountingService(updates=5)
    run(service, every=2, stop_after=0)
    assert service.saved_at == []
    resumed = CountingService(updates=5, done=4)
    run(resumed, every=2, stop_after=4)
    assert resumed.saved_at == [], "nothing new since the checkpoint it resumed"


def test_checkpoints_on_the_cadence_and_once_more_at_the_end() -> None:
    service = CountingService(updates=5)
    run(service, every=2)
    assert service.saved_at == [2, 4, 5]
    stopped = CountingService(updates=5)
    run(stopped, every=2, stop_after=4)
    assert stopped.saved_at == [2, 4], "the last update was just saved"


def test_a_resumed_run_has_one_metrics_row_per_update(tmp_path) -> None:
    """A run killed after update 5 with its newest checkpoint at update 3 resumes from 3 and redoes 4 and 5: the
    dead rows (and a line cut short by the kill) are set aside, never deleted, and each update has one row."""
    path = tmp_path / "metrics.jsonl"
    first = CountingService(updates=5)
    run_loop(first, LoopOptions(metrics_path=path, checkpoint_every=3, progress=ProgressLine(1000, io.StringIO())))
    with path.open("a") as file:
        file.write('{"update": 6, "env_st')  # killed mid-line
    resumed = CountingService(updates=4, done=3)
    run_loop(resumed, LoopOptions(metrics_path=path, checkpoint_every=3, progress=ProgressLine(1000, io.StringIO())))
    rows = [json.loads(line) for line in path.read_text().splitlines()]
    assert [row["update"] for row in rows] == [1, 2, 3, 4, 5, 6, 7]
    aside = (tmp_path / "metrics-superseded.jsonl").read_text().splitlines()
    assert [json.loads(line)["update"] for line in aside[:2]] == [4, 5] and aside[2] == '{"update": 6, "env_st'


def test_a_progress_line_never_passes_the_runs_budget(caplog) -> None:
    import logging

    stream = io.StringIO()
    line = ProgressLine(61_440, stream=stream, log_every_s=0)
    with caplog.at_level(logging.INFO):
        line.update(65_536, 1000.0, {})
    text = stream.getvalue() + caplog.text
    assert "61,440/61,440 steps" in text and "65,536" not in text, text


def test_a_resumed_run_reports_the_rate_of_its_own_steps() -> None:
    """The summary's rate counts the env steps this process made, not the resumed run's earlier ones."""
    resumed = CountingService(updates=4, done=1000)
    summary = run_loop(resumed, LoopOptions(progress=ProgressLine(100_000, io.StringIO())))
    assert summary.env_steps == 10 * 1004 and summary.steps_here == 40
    assert summary.steps_per_s == 40 / summary.seconds


def test_saves_falling_due_too_soon_after_the_last_wait_and_the_last_save_never_does() -> None:
    """With a rest between saves longer than the run, the cadence saves once (its first due save) and the loop
    saves once more when it ends."""
    service = CountingService(updates=6)
    run_loop(service, LoopOptions(checkpoint_every=1, min_seconds_between_saves=3600.0,
                                  progress=ProgressLine(1000, stream=io.StringIO())))
    assert service.saved_at == [1, 6]

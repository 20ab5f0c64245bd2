"""The run loop every long-running Impulse process shares: `impulse train` (fused) and each distributed service.

A process hands the loop a `Service`: an object that does one cycle of its work at a time (one fused iteration,
one learner update, one actor rollout) and can write a checkpoint. The loop owns what every process needs and
none should copy:

- the stop flag: the first Ctrl-C or SIGTERM asks the loop to finish the current cycle, checkpoint and stop; a
  second one aborts at once;
- the metrics window: the solve rate and return over the episodes of the last few cycles (summed counts, not a
  mean of per-cycle means), shown on the progress line and stored with each checkpoint;
- the checkpoint cadence: every `checkpoint_every` updates, and once more when the loop ends for any reason if
  updates were made since the last one (a process stopped before its first update writes none: a checkpoint of
  update 0 holds nothing worth resuming, and it would make the next start of the same run refuse the directory as
  one that "already holds checkpoints");
- `metrics.jsonl` (one line per cycle that did something; a resumed run first sets aside the rows of the updates
  it redoes), the same rows to the scalar sinks (TensorBoard, W&B: `monitor.scalars`) and the progress line;
- starting the service (`Service.start`) under the stop signal, and closing it, once, whatever ended the loop.

Services implement `bus.service.Service` (a Protocol) and report with `bus.service.CycleReport`, so the rooms that
implement them never import `deploy`: the learner, the actor, the curriculum service and the fused trainer all run
in this one loop.
"""

from __future__ import annotations

import logging
import signal
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from impulse.bus.service import Service
from impulse.deploy.runtime.progress import MetricsFile, ProgressLine

if TYPE_CHECKING:
    from impulse.monitor.scalars import ScalarSink

log = logging.getLogger("impulse.run")


class StopFlag:
    """SIGINT/SIGTERM ask the loop to stop after the current cycle (checkpointing first, where it has state); a
    second signal aborts. `says` is the warning logged at the first signal: what the process does next;
    `on_signal` is told at once, for work that would otherwise wait long inside a cycle."""

    def __init__(self, says: str = "stopping after this cycle", on_signal: Callable[[], None] | None = None) -> None:
        self.says = says
        self.on_signal = on_signal
        self.stop = False
        self._previous: dict[int, Any] = {}

    def __enter__(self) -> StopFlag:
        for sig in (signal.SIGINT, signal.SIGTERM):
            self._previous[sig] = signal.signal(sig, self._handle)
        return self

    def _handle(self, signum: int, frame: Any) -> None:
        if self.stop:
            raise KeyboardInterrupt
        log.warning("%s; send again to abort", self.says)
        self.stop = True
        if self.on_signal is not None:
            self.on_signal()

    def __exit__(self, *exc: Any) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)


class MetricsWindow:
    """Episode outcomes over the last `size` cycles that finished episodes."""

    def __init__(self, size: int):
        self._records: deque[dict[str, float]] = deque(maxlen=max(1, size))

    def add(self, metrics: dict[str, float]) -> None:
        if metrics.get("episodes"):
            self._records.append(metrics)

    def summary(self) -> dict[str, float]:
        """{"episodes", "solve_rate", "episode_return"} over the window; {"episodes": 0} before any episode."""
        episodes = sum(r["episodes"] for r in self._records)
        if episodes == 0:
            return {"episodes": 0}
        return {
            "episodes": int(episodes),
            "solve_rate": sum(r.get("solved", 0.0) for r in self._records) / episodes,
            "episode_return": sum(r.get("return_sum", 0.0) for r in self._records) / episodes,
        }


@dataclass
class LoopSummary:
    cycles: int
    updates: int
    env_steps: int
    """The running total, a resumed run's earlier steps included."""
    steps_here: int
    """Env steps this process made."""
    seconds: float
    """From the service's start to the end of its last cycle (closing not counted)."""
    stopped: bool
    """Ended by a signal or `should_stop` rather than by the service finishing."""
    last: dict[str, float]
    window: dict[str, float]

    @property
    def steps_per_s(self) -> float:
        """This process's env steps per second of its cycles."""
        return self.steps_here / self.seconds if self.seconds > 0 else 0.0


@dataclass(frozen=True)
class LoopOptions:
    """How the loop drives a service (what the service itself knows, its progress, it says)."""

    metrics_path: Path | None = None
    """metrics.jsonl to append one line per cycle to; None: no file (actors, the curriculum service)."""
    checkpoint_every: int = 0
    """Save every this many units of `CycleReport.updates`; 0: only when the loop ends."""
    min_seconds_between_saves: float = 0.0
    """A save that falls due sooner than this after the last one waits until this much time has passed (the loop's
    last save, when it ends, never waits)."""
    window_size: int = 10
    """Cycles with finished episodes the metrics window spans."""
    idle_wait_s: float = 0.005
    """Sleep after a cycle that had nothing to do."""
    progress: ProgressLine | None = None
    """The progress line; None: one for the service's total env steps (none when it has no goal)."""
    should_stop: Callable[[], bool] | None = None
    """Polled before every cycle: True stops the loop as a signal would."""
    on_cycle: Callable[[dict[str, Any], dict[str, float]], None] | None = None
    """Sees every metrics record and the window summary after it (Rerun logging, the learner's status line)."""
    every_turn: Callable[[], None] | None = None
    """Called at every turn of the loop, busy or idle (a monitor that logs on a schedule of its own)."""
    scalar_sinks: Callable[[int], list[ScalarSink]] | None = None
    """Opens the sinks (TensorBoard, W&B) that get every metrics.jsonl row too, given the env steps the service
    resumes at (so they can drop what the rewound metrics.jsonl drops); closed when the loop ends."""


def run_loop(service: Service, options: LoopOptions = LoopOptions()) -> LoopSummary:
    """Start `service` and drive it until it is finished, a signal arrives or `options.should_stop()` is true,
    then checkpoint once more if it made updates since the last checkpoint, and close it. A resumed service's
    progress (env steps and updates done) continues its counters; each metrics.jsonl line carries the running
    totals."""
    start_at = service.progress()
    updates_done = start_at.updates_done
    metrics_path, checkpoint_every = options.metrics_path, options.checkpoint_every
    metrics_file = MetricsFile(metrics_path, through_update=updates_done) if metrics_path is not None else None
    progress = options.progress
    if progress is None and start_at.total_env_steps > 0:
        progress = ProgressLine(start_at.total_env_steps)
    window = MetricsWindow(options.window_size)
    env_steps, updates, cycles = start_at.env_steps_done, updates_done, 0
    saved_at = updates_done
    last_save = -float("inf")
    last: dict[str, float] = {}
    start = time.perf_counter()  # again once the service has started: its rate counts the cycles only
    steps_here = 0
    cycles_ended = None
    stopped = False
    sinks: list[ScalarSink] = []
    try:
        if options.scalar_sinks is not None:
            sinks = options.scalar_sinks(start_at.env_steps_done)
        says = "stopping after this cycle" + (" (checkpointing first)" if checkpoint_every > 0 else "")
        with StopFlag(says, getattr(service, "request_stop", None)) as stop:
            service.start()
            start = time.perf_counter()
            while not service.finished():
                if stop.stop or (options.should_stop is not None and options.should_stop()):
                    stopped = True
                    break
                report = service.cycle()
                if options.every_turn is not None:
                    options.every_turn()
                if report is None:
                    time.sleep(options.idle_wait_s)
                    continue
                cycles += 1
                env_steps += report.env_steps
                steps_here += report.env_steps
                updates += report.updates
                window.add(report.metrics)
                elapsed = time.perf_counter() - start
                last = {"update": updates, "env_steps": env_steps, "time_s": round(time.time(), 3),
                        **report.metrics}
                if metrics_file is not None:
                    metrics_file.write(last)
                for sink in sinks:
                    sink.write(last)
                if options.on_cycle is not None:
                    options.on_cycle(last, window.summary())
                if progress is not None:
                    progress.update(env_steps, steps_here / elapsed if elapsed > 0 else 0.0, window.summary())
                due = checkpoint_every > 0 and updates // checkpoint_every > saved_at // checkpoint_every
                rested = time.perf_counter() - last_save >= options.min_seconds_between_saves
                if report.updates and due and rested:
                    service.save(window.summary())
                    saved_at, last_save = updates, time.perf_counter()
            stopped = stopped or stop.stop
            cycles_ended = time.perf_counter()
            if updates != saved_at:
                service.save(window.summary())
    finally:
        try:
            service.close()
        finally:
            if progress is not None:
                progress.close()
            if metrics_file is not None:
                metrics_file.close()
            for sink in sinks:
                sink.close()
    seconds = (cycles_ended or time.perf_counter()) - start
    return LoopSummary(cycles, updates, env_steps, steps_here, seconds, stopped, last, window.summary())

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
  it redoes), the same rows to the scalar sinks (TensorBoard, W&B: `monitor.scalars`) and the progress line, which
  is also told the loop's phase (training, checkpointing);
- starting the service (`Service.start`) under the stop signal, and closing it, once, whatever ended the loop;
- a full disk (below).

A full disk (ENOSPC, EDQUOT or EIO: `engine.io_errors.DiskFullError`, whose message names the path and the space
left on its file system). When a metrics.jsonl row or a checkpoint cannot be written, the loop logs that one line
and waits: it runs no further cycle (so no update is made whose row or checkpoint could not be kept), tries the
same write again every `LoopOptions.disk_retry_s` (DISK_RETRY_S, 10 s), says every `disk_remind_s` (DISK_REMIND_S,
60 s) that it is still waiting, and goes on once the write succeeds: the row is written exactly once (a failed
append leaves the file as it was, `progress.MetricsFile`), and a failed checkpoint leaves no partial checkpoint
behind (`learner.checkpoint` removes what orbax had written of it), so the newest complete one stays the one a
resume takes. The scalar sinks (TensorBoard, W&B) do not make the loop wait: they hold what they could not write
and write it with the next row (`monitor.scalars`). A stop signal (or `should_stop`) while the loop waits ends the
wait: the row waited on is tried once more, then the final checkpoint once; if that cannot be written either, the
process ends with one line saying so (`CheckpointNotWritten`, exit status 1) and its earlier checkpoints intact. A
second signal aborts at once, as always. docs/distributed.md ("A full disk") says the same for users.

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
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any

from impulse.bus.service import Service
from impulse.deploy.runtime.progress import MetricsFile, ProgressLine
from impulse.engine.io_errors import DiskFullError

if TYPE_CHECKING:
    from impulse.monitor.scalars import ScalarSink

log = logging.getLogger("impulse.run")

DISK_RETRY_S = 10.0
"""While the disk is full, how often the loop tries the write it waits on again."""
DISK_REMIND_S = 60.0
"""While the disk is full, how often the loop says again that it is waiting."""
WAIT_POLL_S = 0.2
"""While the loop waits for space, how often it looks at the stop signal."""


class CheckpointNotWritten(SystemExit):
    """The loop's last checkpoint could not be written for lack of disk: the process ends with this one line on
    stderr and exit status 1 (a `SystemExit`, so no command prints a traceback for it), its earlier checkpoints
    intact."""


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
    """From the service's start to the end of its last cycle (closing and waiting for disk space not counted)."""
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
    disk_retry_s: float = DISK_RETRY_S
    """While the disk is full, how often the write waited on is tried again (the module docstring)."""
    disk_remind_s: float = DISK_REMIND_S
    """While the disk is full, how often the loop says that it is still waiting."""


class DiskWait:
    """The loop's wait for disk space (the module docstring): `write` runs a write until it succeeds, or until a
    stop is asked for while it waits."""

    def __init__(self, stop: StopFlag, should_stop: Callable[[], bool] | None, retry_s: float, remind_s: float):
        self.stop = stop
        self.should_stop = should_stop
        self.retry_s = retry_s
        self.remind_s = remind_s
        self.waited_s = 0.0
        """Seconds spent waiting so far (left out of the loop's rates)."""

    def stopping(self) -> bool:
        return self.stop.stop or (self.should_stop is not None and self.should_stop())

    def write(self, what: str, attempt: Callable[[], None]) -> bool:
        """Run `attempt` (one write of `what`, e.g. "the metrics row of update 12"); on `DiskFullError` log it once,
        then try again every `retry_s` until it succeeds (True), reminding every `remind_s`; False if a stop was
        asked for first (the write not made)."""
        try:
            attempt()
            return True
        except DiskFullError as err:
            failure = err
        log.error("%s: %s; training waits, trying again every %g s (free some space to go on; a stop signal "
                  "stops the run, checkpointing once)", what, failure, self.retry_s)
        says = self.stop.says
        self.stop.says = "stopping while waiting for disk space: the final checkpoint is tried once"
        started = time.monotonic()
        next_try, next_reminder = started + self.retry_s, started + self.remind_s
        try:
            while not self.stopping():
                now = time.monotonic()
                if now >= next_try:
                    try:
                        attempt()
                    except DiskFullError as err:
                        failure = err
                        next_try = time.monotonic() + self.retry_s
                    else:
                        log.info("%s: written after %.0f s waiting for disk space; training goes on", what,
                                 time.monotonic() - started)
                        return True
                if now >= next_reminder:
                    log.warning("still waiting for disk space (%.0f s): %s", now - started, failure)
                    next_reminder = now + self.remind_s
                time.sleep(max(min(WAIT_POLL_S, next_try - time.monotonic()), 0.0))
        finally:
            self.stop.says = says
            self.waited_s += time.monotonic() - started
        return False


def _try_once(what: str, attempt: Callable[[], None]) -> DiskFullError | None:
    """One attempt at a write (when stopping, no waiting): None if it was made, else its `DiskFullError`, logged."""
    try:
        attempt()
    except DiskFullError as err:
        log.error("%s: %s", what, err)
        return err
    return None


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
    not_saved: DiskFullError | None = None  # the last checkpoint could not be written (CheckpointNotWritten)
    disk: DiskWait | None = None
    try:
        if options.scalar_sinks is not None:
            sinks = options.scalar_sinks(start_at.env_steps_done)
        says = "stopping after this cycle" + (" (checkpointing first)" if checkpoint_every > 0 else "")
        with StopFlag(says, getattr(service, "request_stop", None)) as stop:
            disk = DiskWait(stop, options.should_stop, options.disk_retry_s, options.disk_remind_s)
            service.start()
            start = time.perf_counter()
            _phase(progress, "training")
            while not service.finished():
                if disk.stopping():
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
                elapsed = time.perf_counter() - start - disk.waited_s
                last = {"update": updates, "env_steps": env_steps, "time_s": round(time.time(), 3),
                        **report.metrics}
                if metrics_file is not None:
                    what = f"the metrics row of update {updates}"
                    if not disk.write(what, partial(metrics_file.write, last)):
                        _try_once(what, partial(metrics_file.write, last))
                        stopped = True
                        break
                _to_sinks(sinks, last)
                if options.on_cycle is not None:
                    options.on_cycle(last, window.summary())
                if progress is not None:
                    progress.update(env_steps, steps_here / elapsed if elapsed > 0 else 0.0, window.summary(),
                                    record=last)
                due = checkpoint_every > 0 and updates // checkpoint_every > saved_at // checkpoint_every
                rested = time.perf_counter() - last_save >= options.min_seconds_between_saves
                if report.updates and due and rested:
                    _phase(progress, "checkpointing")
                    if not disk.write(f"the checkpoint of update {updates}", lambda: service.save(window.summary())):
                        stopped = True
                        break
                    saved_at, last_save = updates, time.perf_counter()
                    _phase(progress, "training")
            stopped = stopped or stop.stop
            cycles_ended = time.perf_counter()
            if updates != saved_at:
                _phase(progress, "checkpointing")
                what = f"the final checkpoint (update {updates})"
                if stopped or not disk.write(what, lambda: service.save(window.summary())):
                    not_saved = _try_once(what, lambda: service.save(window.summary()))
    finally:
        try:
            service.close()
        except DiskFullError as err:  # a checkpoint written in the background failed (learner.checkpoint)
            log.error("closing: %s", err)
            not_saved = not_saved or err
        finally:
            if progress is not None:  # a loop that ended by an error or a signal has stopped, not finished
                progress.close("done" if cycles_ended is not None and not stopped else "stopped")
            if metrics_file is not None:
                metrics_file.close()
            for sink in sinks:
                try:
                    sink.close()
                except DiskFullError as err:
                    log.error("closing a metrics sink: %s", err)
    if not_saved is not None:
        raise CheckpointNotWritten(f"the final checkpoint (update {updates}) could not be written: {not_saved}; the "
                                   "checkpoints written before it are intact")
    seconds = (cycles_ended or time.perf_counter()) - start - (disk.waited_s if disk is not None else 0.0)
    return LoopSummary(cycles, updates, env_steps, steps_here, seconds, stopped, last, window.summary())


def _phase(progress: ProgressLine | None, phase: str) -> None:
    """Tell the progress line (if any) what the loop does now."""
    if progress is not None:
        progress.phase(phase)


def _to_sinks(sinks: list[ScalarSink], row: dict[str, Any]) -> None:
    """Hand `row` to every scalar sink. Ours hold what a full disk refuses and never raise for it; a sink that
    raises `DiskFullError` anyway loses that row (metrics.jsonl has it), said in one line."""
    for sink in sinks:
        try:
            sink.write(row)
        except DiskFullError as err:
            log.error("a metrics sink could not write update %s: %s", row.get("update"), err)

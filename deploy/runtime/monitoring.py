"""Wiring the run's processes to Rerun (`monitor`): who opens a monitor, with which layout, and what each logs.

Every process of a run with `monitor.enabled` opens one `Monitor` on `monitor.url` with the run's name as
recording id and the run's default blueprint. The learner and the actors log their per-cycle metrics and their
status numbers (`MetricsLogger`); actors also stream rollouts (`actors.process`); the curriculum service logs its
statistics, histograms, top-level gallery and knob changes (`CurriculumLogger`).

Rerun is imported only once monitoring is on (the imports of `monitor.stream`, `monitor.blueprint` and
`monitor.metrics` inside this module's functions), so a run with it off needs no rerun-sdk (a lent GPU machine, whose
package set cannot take its 170 MB wheel, runs the distributed benchmark that way: docs/gpu.md).

The processes that write `metrics.jsonl` also hand its rows to TensorBoard and W&B (`monitor.scalars`), whatever
`monitor.enabled` says: `scalar_sinks_for` is their run loop's opener.
"""

from __future__ import annotations

import dataclasses
import time
import tomllib
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import jax

from impulse.actors.process import actor_name
from impulse.curriculum.stats import top_levels
from impulse.deploy.config import config_to_toml
from impulse.deploy.run_config import RunConfig
from impulse.engine.levels.drawing import scene_drawing
from impulse.monitor.scalars import ScalarSink, check_sinks, open_sinks

if TYPE_CHECKING:
    from impulse.monitor.stream import Monitor

STATUS_EVERY_S = 2.0
OnCycle = Callable[[dict[str, Any], dict[str, float]], None]


def run_blueprint(config: RunConfig) -> Any:
    """The default layout for this run's processes (its actors, whether it has a curriculum service)."""
    from impulse.monitor.blueprint import default_blueprint  # Rerun: the module docstring

    return default_blueprint([actor_name(i) for i in range(config.actors.num_actors)],
                             config.monitor.watch_envs, config.monitor.gallery, config.uses_curriculum_service)


def open_monitor(config: RunConfig) -> Monitor | None:
    """This process's monitor, or None when monitoring is off."""
    if not config.monitor.enabled:
        return None
    from impulse.monitor.stream import Monitor

    return Monitor(config.name, url=config.monitor.url, blueprint=run_blueprint(config),
                   frames_per_s=config.monitor.frames_per_s, frame_queue=config.monitor.queue_rollouts)


class MetricsLogger:
    """The run loop's `on_cycle` for a service: each cycle's metrics and the window summary, and every
    `STATUS_EVERY_S` the numbers of the process's status line (counters, rates, drops)."""

    def __init__(self, monitor: Monitor, process: str, status: Callable[[], dict[str, Any]],
                 step_timeline: str | None = None, then: OnCycle | None = None):
        self.monitor, self.process, self.status = monitor, process, status
        self.step_timeline = step_timeline
        self.then = then
        self._status_at = -float("inf")

    def __call__(self, record: dict[str, Any], window: dict[str, float]) -> None:
        from impulse.monitor.metrics import log_process_metrics

        if self.then is not None:
            self.then(record, window)
        step = (self.step_timeline, int(record["update"])) if self.step_timeline else None
        values = {**record, "window": dict(window)}
        self.monitor.log(lambda rec: log_process_metrics(rec, self.process, values, step=step))
        if time.monotonic() - self._status_at >= STATUS_EVERY_S:
            self._status_at = time.monotonic()
            status = {"status": self.status()}  # apart from the cycle's metrics: some names are in both
            self.monitor.log(lambda rec: log_process_metrics(rec, self.process, status))


class CurriculumLogger:
    """What the curriculum service shows in the viewer, logged every `monitor.curriculum_every_s` (and at once
    when a live knob changes): buffer statistics, histograms, the gallery of top levels and the knobs."""

    def __init__(self, monitor: Monitor, service: Any, config: RunConfig):
        self.monitor, self.service = monitor, service
        self.every_s, self.gallery = config.monitor.curriculum_every_s, config.monitor.gallery
        self._at = -float("inf")
        self._knobs: dict[str, Any] = {}

    def poll(self) -> None:
        from impulse.monitor.metrics import log_knobs

        knobs = self.service.live_knobs()
        if knobs != self._knobs:
            changed = {name: [self._knobs[name], value] for name, value in knobs.items()
                       if name in self._knobs and self._knobs[name] != value}
            self._knobs = knobs
            self.monitor.log(lambda rec: log_knobs(rec, knobs, changed))
        if time.monotonic() - self._at < self.every_s:
            return
        self._at = time.monotonic()
        self._log_buffer()

    def _log_buffer(self) -> None:
        from impulse.monitor.metrics import CURRICULUM, log_gallery, log_histograms, log_scalars

        report = self.service.inspect(self.gallery)
        levels = top_levels(self.service.state, self.service.curriculum.spec.sizes, self.gallery)
        drawings = [scene_drawing(jax.tree.map(lambda x, i=i: x[i], levels)) for i in range(len(report["top"]))]
        captions = [_caption(rank, row) for rank, row in enumerate(report["top"])]
        summary = report["summary"]

        def log(rec: Any) -> int:
            log_scalars(rec, f"{CURRICULUM}/stats", summary)
            log_histograms(rec, report["histograms"])
            log_gallery(rec, drawings, captions, self.gallery)
            return 0

        self.monitor.log(log)


def _caption(rank: int, row: dict[str, Any]) -> str:
    solved = "not played" if row["solve_rate"] is None else f"solved {row['solve_rate']:.0%}"
    return (f"#{rank + 1} level {row['level_id']:016x}\nscore {row['score']:.4f} · {solved} over "
            f"{row['episodes']:.0f} episodes\ngeneration {row['generation']} · {row['replays']} replays")


def viewer_config(config: RunConfig) -> RunConfig:
    """The run's config with monitoring on, as `impulse launch --view` writes it."""
    return dataclasses.replace(config, monitor=dataclasses.replace(config.monitor, enabled=True))


def scalar_sinks_for(config: RunConfig, run_dir: Path) -> Callable[[int], list[ScalarSink]]:
    """The run loop's `scalar_sinks` for a process writing `run_dir`'s metrics.jsonl: TensorBoard and W&B as
    `config.monitor` says, W&B with the resolved config. Checks first what they need (`ScalarSinkError`), so that a
    missing W&B client stops the process before its run starts."""
    check_sinks(config.monitor)
    resolved = tomllib.loads(config_to_toml(config))

    def open_for(resume_env_steps: int) -> list[ScalarSink]:
        return open_sinks(config.monitor, run_dir, config.name, resolved, resume_env_steps)

    return open_for

"""Curves and the curriculum in Rerun: what the learner, the actors and the curriculum service report.

Entity paths (the default blueprint, `monitor.blueprint`, lays panels over them):

    metrics/<process>/<name>          Scalars: every number a process reports per cycle or on its status line
    curriculum/stats/<name>           Scalars: the buffer statistics (`curriculum.stats.buffer_summary`)
    curriculum/histograms/<name>      BarChart: score and solve-rate histograms of the buffered levels
    curriculum/knobs/<name>           Scalars: the live-tuned knobs' values (logged when they change)
    curriculum/knob_changes           TextLog: "name: old -> new"
    curriculum/top/<rank>/scene/...   the top levels by score, drawn like rollouts (a gallery)
    curriculum/top/<rank>/caption     TextDocument: id, score, solve rate, episodes

Every record is logged on the `wall` timeline (time.time(), shared by every process of a run, so curves line up
with rollouts) and, where the process has one, on its own step counter (`update` for the learner). Non-numeric
and non-finite values are skipped.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping, Sequence
from typing import Any

import rerun as rr

from impulse.engine.levels.drawing import SceneDrawing
from impulse.monitor.draw import log_scene

METRICS = "metrics"
CURRICULUM = "curriculum"


def _stamp(recording: rr.RecordingStream, at: float | None, step: tuple[str, int] | None) -> None:
    recording.reset_time()
    recording.set_time("wall", timestamp=time.time() if at is None else at)
    if step is not None:
        recording.set_time(step[0], sequence=int(step[1]))


def numbers(values: Mapping[str, Any], prefix: str = "") -> dict[str, float]:
    """The finite numbers of a (nested) status or metrics dict, flattened to "a/b" names; bools count as 0/1."""
    flat: dict[str, float] = {}
    for name, value in values.items():
        key = f"{prefix}{name}"
        if isinstance(value, Mapping):
            flat.update(numbers(value, f"{key}/"))
        elif isinstance(value, bool | int | float) and math.isfinite(float(value)):
            flat[key] = float(value)
    return flat


def log_scalars(recording: rr.RecordingStream, path: str, values: Mapping[str, Any], *,
                step: tuple[str, int] | None = None, at: float | None = None) -> int:
    """Each finite number of `values` as Scalars under `path/<name>`; returns how many were logged."""
    _stamp(recording, at, step)
    flat = numbers(values)
    for name, value in flat.items():
        recording.log(f"{path}/{name}", rr.Scalars(value))
    return len(flat)


def log_process_metrics(recording: rr.RecordingStream, process: str, values: Mapping[str, Any], *,
                        step: tuple[str, int] | None = None, at: float | None = None) -> int:
    """A process's metrics under `metrics/<process>/`."""
    return log_scalars(recording, f"{METRICS}/{process}", values, step=step, at=at)


def log_histograms(recording: rr.RecordingStream, histograms: Mapping[str, Mapping[str, Sequence[float]]],
                   at: float | None = None) -> None:
    """Histograms as {"edges", "counts"} (`curriculum.stats.histogram`) as BarCharts at the bins' centres."""
    _stamp(recording, at, None)
    for name, histogram in histograms.items():
        counts, edges = list(histogram.get("counts", [])), list(histogram.get("edges", []))
        if not counts or len(edges) != len(counts) + 1:
            continue
        centres = [(a + b) / 2 for a, b in zip(edges[:-1], edges[1:], strict=True)]
        widths = [b - a for a, b in zip(edges[:-1], edges[1:], strict=True)]
        recording.log(f"{CURRICULUM}/histograms/{name}", rr.BarChart(counts, abscissa=centres, widths=widths))


def log_gallery(recording: rr.RecordingStream, drawings: Sequence[SceneDrawing], captions: Sequence[str],
                capacity: int, at: float | None = None) -> None:
    """The top levels, best first, in `capacity` gallery slots (slots beyond the levels given are cleared)."""
    _stamp(recording, at, None)
    for rank in range(capacity):
        path = f"{CURRICULUM}/top/{rank}"
        if rank < len(drawings):
            log_scene(recording, f"{path}/scene", drawings[rank])
            recording.log(f"{path}/caption", rr.TextDocument(captions[rank]))
        else:
            recording.log(path, rr.Clear(recursive=True))


def log_knobs(recording: rr.RecordingStream, knobs: Mapping[str, Any], changed: Mapping[str, Sequence[Any]],
              at: float | None = None) -> None:
    """The live knobs' current values, and a line per change ({name: [old, new]})."""
    log_scalars(recording, f"{CURRICULUM}/knobs", knobs, at=at)
    for name, (old, new) in changed.items():
        recording.log(f"{CURRICULUM}/knob_changes", rr.TextLog(f"{name}: {old} -> {new}"))

"""Run directories read back as data: their `config.toml` and `metrics.jsonl`, summarised and compared.

`impulse compare` (deploy/commands/compare.py) prints what this module computes; it lives here, below the command
line, because a notebook or a benchmark asks the same questions of finished runs: how far did each run get, how
good did it become, how fast did it reach a bar, and which settings differ between them. Both modes write the same
files (`impulse train` and the learner of `impulse launch`, through one run loop), so one reader serves both; the
columns they share are `SHARED_COLUMNS` (docs/metrics.md describes every column).

Only the standard library and `monitor.charts` are used: reading runs needs neither JAX nor the config classes
(the resolved `config.toml` is read as plain TOML, so a run written by an older version still reads).
"""

from __future__ import annotations

import difflib
import json
import math
import os
import tomllib
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal

from impulse.monitor.charts import PALETTE, Panel, Series, render

CONFIG_FILE = "config.toml"
METRICS_FILE = "metrics.jsonl"

PROGRESS_COLUMNS: tuple[str, ...] = ("update", "env_steps", "time_s", "steps_per_s")
"""Written by the run loop (deploy/runtime/runloop.py) for every process that has a metrics file."""
EPISODE_COLUMNS: tuple[str, ...] = (
    "episodes", "solved", "failed", "timed_out", "nan_episodes", "return_sum", "length_sum", "solve_rate",
    "episode_return", "episode_length",
)
"""The episodes of the batch trained on (`actors.trajectory.episode_metrics`)."""
PPO_COLUMNS: tuple[str, ...] = (
    "total_loss", "policy_loss", "value_loss", "entropy", "approx_kl", "clip_fraction", "trained_fraction",
    "policy_lag", "behaviour_kl", "trace_weight",
)
"""The PPO update (`learner.update.ppo_update`); in fused mode `policy_lag` is 0, `behaviour_kl` 0 and
`trace_weight` 1 (up to rounding)."""
SHARED_COLUMNS: tuple[str, ...] = PROGRESS_COLUMNS + EPISODE_COLUMNS + PPO_COLUMNS
"""The columns of every metrics.jsonl row in both modes, meaning the same in both (docs/metrics.md, "both"):
what makes a fused and a distributed run comparable. tests/learner/test_learns.py (fused) and
tests/deploy/test_launch_faults.py (`impulse launch`) check that their rows hold every one."""
EVAL_COLUMNS: tuple[str, ...] = ("eval/policy_version", "eval/mean")
"""The evaluation columns both modes write on the rows of the updates where the policy was scored
(`learner.scoring.evaluation_columns`; per-set, per-group and per-level columns follow the levels evaluated)."""

DISTRIBUTED_ONLY: tuple[str, ...] = ("queue", "actor")
"""Columns only the learner of a distributed run writes (its inbox, the actor of the batch)."""
FUSED_ONLY: tuple[str, ...] = ("reward_per_step", "levels_new")
"""Columns only the fused trainer writes."""

MACHINE_COLUMNS: tuple[str, ...] = ("time_s", "steps_per_s")
"""Columns that measure the machine rather than the learning: left out when runs are checked for identity."""

DEFAULT_METRIC = "solve_rate"
EVAL_MEAN = "eval/mean"
IDENTITY_KEYS: tuple[str, ...] = ("name", "run_dir")
"""Config keys that name a run rather than set it up: left out of the config differences (they always differ)."""

Mode = Literal["fused", "distributed", "unknown"]
Axis = Literal["env_steps", "time_s", "update"]
AXES: tuple[Axis, ...] = ("env_steps", "time_s", "update")


class RunError(ValueError):
    """A path that cannot be compared (not a run directory, no metrics yet, a column no run has). The message is
    one line, complete, for the person at the terminal."""


@dataclass(frozen=True)
class Run:
    """One run directory as read: where it is, the label it is shown under, its mode, its resolved configuration
    (dotted keys) and its metrics rows (one per update, in file order)."""

    path: Path
    label: str
    mode: Mode
    config: dict[str, Any]
    rows: list[dict[str, Any]]


Window = tuple[float, float]
"""A stretch of a run along the comparison's `by` axis, both ends included (-inf or inf for an open end)."""


@dataclass(frozen=True)
class MetricSummary:
    """One metric of one run: its last finite value, its best (highest) value and where it was reached (in the
    comparison's `by` units), the first update at which it reached the threshold (None: not reached, or no
    threshold asked for), and over a window, the mean of its values there with the standard error of that mean
    (over the values, which are correlated: a run's evaluation points follow one policy) and how many there were."""

    final: float | None
    best: float | None
    best_at: float | None
    reached_env_steps: int | None = None
    reached_s: float | None = None
    reached_update: int | None = None
    window_mean: float | None = None
    window_se: float | None = None
    window_points: int = 0


@dataclass(frozen=True)
class RunSummary:
    """What a comparison shows of one run (one table row)."""

    label: str
    path: str
    mode: Mode
    updates: int
    env_steps: int
    wall_s: float
    """Wall clock from the first update's row to the last's (start-up and compilation before the first update are
    not counted; pauses between a stop and a resume are)."""
    done: float | None
    """Share of the configured `total_env_steps` done, at most 1 (the last update may overshoot the total; below
    1: still running, stopped or crashed)."""
    metrics: dict[str, MetricSummary] = field(default_factory=dict)


def run_directory(path: Path | str) -> Path:
    """The run directory `path` names: itself, or the folder of a `config.toml` or `metrics.jsonl` given instead
    (what tab completion often produces)."""
    path = Path(path)
    if path.is_file() and path.name in (CONFIG_FILE, METRICS_FILE):
        return path.parent
    return path


def read_config(run_dir: Path) -> dict[str, Any]:
    """The run's resolved configuration as {dotted key: value}; RunError when there is none (not a run)."""
    if not run_dir.is_dir():
        raise RunError(f"{run_dir} is not a directory")
    path = run_dir / CONFIG_FILE
    if not path.is_file():
        raise RunError(f"{run_dir} is not a run directory: it has no {CONFIG_FILE}")
    try:
        return flatten(tomllib.loads(path.read_text(errors="replace")))
    except tomllib.TOMLDecodeError as err:
        raise RunError(f"{path} is not valid TOML: {err}") from None


def flatten(tree: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """{"ppo": {"num_envs": 64}} -> {"ppo.num_envs": 64}: tables become dotted keys, other values stay (lists
    included), in the file's order."""
    flat: dict[str, Any] = {}
    for key, value in tree.items():
        dotted = f"{prefix}{key}"
        if isinstance(value, dict):
            flat.update(flatten(value, dotted + "."))
        else:
            flat[dotted] = value
    return flat


def read_metrics(path: Path) -> list[dict[str, Any]]:
    """The rows of a metrics.jsonl, oldest first. Lines that are not a JSON object with an `update` are skipped: a
    running run's last line may be cut short while it is written. `null` values (NaN when written) stay None."""
    if not path.is_file():
        return []
    rows = []
    for line in path.read_text(errors="replace").splitlines():
        try:
            row = json.loads(line)
        except ValueError:
            continue
        if isinstance(row, dict) and isinstance(row.get("update"), int):
            rows.append(row)
    return rows


def run_mode(rows: Sequence[dict[str, Any]], run_dir: Path) -> Mode:
    """Which mode wrote the run: the columns only one mode writes say it (docs/metrics.md); without them, a
    `logs/` folder (one log per process) is what `impulse launch` leaves, never `impulse train`."""
    names = columns(rows)
    if any(name in names for name in DISTRIBUTED_ONLY):
        return "distributed"
    if any(name in names for name in FUSED_ONLY):
        return "fused"
    if (run_dir / "logs").is_dir():
        return "distributed"
    return "unknown"


def columns(rows: Iterable[dict[str, Any]]) -> set[str]:
    """Every column that appears in any of the rows."""
    return {name for row in rows for name in row}


def labels(paths: Sequence[Path]) -> list[str]:
    """How runs are named in a comparison: the directory's name (`runs/NAME`), and where two names clash, as many
    of the folders above it as tell them apart (`seed-0/ppo`, `seed-1/ppo`)."""
    parts = [Path(os.path.abspath(path)).parts for path in paths]  # `..` folded, links kept
    names = []
    for mine in parts:
        for depth in range(1, len(mine) + 1):
            name = str(Path(*mine[-depth:]))
            if sum(other[-depth:] == mine[-depth:] for other in parts) == 1 or depth == len(mine):
                break
        names.append(name)
    return names


def read_run(path: Path | str, label: str | None = None) -> Run:
    """Read one run directory; RunError when it is not a run or has no metrics rows yet."""
    run_dir = run_directory(path)
    config = read_config(run_dir)
    rows = read_metrics(run_dir / METRICS_FILE)
    if not rows:
        raise RunError(f"{run_dir} has no metrics yet: {METRICS_FILE} is missing or holds no update "
                       "(a run writes its first row after its first update)")
    return Run(run_dir, label or labels([run_dir])[0], run_mode(rows, run_dir), config, rows)


def read_runs(paths: Sequence[Path | str]) -> list[Run]:
    """Read every run, labelled apart (`labels`)."""
    dirs = [run_directory(path) for path in paths]
    return [read_run(path, label) for path, label in zip(dirs, labels(dirs))]


def default_metrics(runs: Sequence[Run]) -> list[str]:
    """The training solve rate, and the evaluation mean when any run was evaluated while training."""
    return [DEFAULT_METRIC] + ([EVAL_MEAN] if any(EVAL_MEAN in columns(run.rows) for run in runs) else [])


def check_metrics(runs: Sequence[Run], metrics: Sequence[str]) -> None:
    """RunError naming a metric that no run has, with the nearest names and every column the runs do have (a
    metric some runs lack is fine: they show no value)."""
    present = set().union(*(columns(run.rows) for run in runs))
    for metric in metrics:
        if metric not in present:
            near = difflib.get_close_matches(metric, sorted(present), n=3)
            hint = f" (did you mean {', '.join(near)}?)" if near else ""
            raise RunError(f"no run has the column {metric!r}{hint}; their columns: {', '.join(sorted(present))}")


@dataclass(frozen=True)
class Mismatch:
    """One value on which runs checked for identity differ: the update's row, the column, every run's value."""

    update: int
    column: str
    values: tuple[Any, ...]


def mismatches(runs: Sequence[Run], updates: int, ignore: Iterable[str] = MACHINE_COLUMNS) -> list[Mismatch]:
    """Where the runs' first `updates` rows differ, in every column all of them have on that row (`ignore` left
    out): empty when they agree bit for bit. metrics.jsonl holds each value as Python writes a float (the shortest
    text that reads back to the same double), so equal text is equal bits; null (NaN) equals null. RunError for a
    run with fewer rows."""
    for run in runs:
        if len(run.rows) < updates:
            raise RunError(f"{run.path} has {len(run.rows)} metrics rows, fewer than the {updates} to check")
    skipped = set(ignore)
    found = []
    for rows in zip(*(run.rows[:updates] for run in runs)):
        shared = [name for name in rows[0] if name not in skipped and all(name in row for row in rows)]
        for name in shared:
            values = tuple(row[name] for row in rows)
            if any(value != values[0] for value in values[1:]):
                found.append(Mismatch(rows[0]["update"], name, values))
    return found


def finite_number(value: Any) -> float | int | None:
    """A finite int or float from a Python, numpy or JAX scalar; None for anything else (NaN, text, bools). What
    counts as a metric value, for `impulse compare` and for the scalar sinks (`monitor.scalars`) alike."""
    if hasattr(value, "item") and getattr(value, "size", 1) == 1:
        value = value.item()
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    return value if math.isfinite(value) else None


def elapsed_s(run: Run) -> list[float]:
    """Seconds since the first row, for each row (the rows' `time_s` are Unix seconds)."""
    times = [finite_number(row.get("time_s")) for row in run.rows]
    start = next((t for t in times if t is not None), 0.0)
    return [t - start if t is not None else math.nan for t in times]


def axis_values(run: Run, by: Axis) -> list[float]:
    """Each row's position along `by`: env steps, seconds since the first row, or the update."""
    if by == "time_s":
        return elapsed_s(run)
    return [float(row.get(by) or 0) for row in run.rows]


def curve(run: Run, metric: str, by: Axis) -> tuple[list[float], list[float]]:
    """(xs, ys) of the rows where `metric` has a finite value: the metric against `by`, ready to plot (rows without
    a value, such as a solve rate of a batch where no episode ended, are left out rather than broken into gaps)."""
    xs, ys = [], []
    for x, row in zip(axis_values(run, by), run.rows):
        y = finite_number(row.get(metric))
        if y is not None and math.isfinite(x):
            xs.append(x)
            ys.append(y)
    return xs, ys


def window_mean(xs: Sequence[float], ys: Sequence[float], window: Window) -> tuple[float | None, float | None, int]:
    """(mean, standard error of the mean, count) of the values `ys` whose positions `xs` lie in `window`; the
    standard error needs two values, the mean one."""
    low, high = window
    inside = [y for x, y in zip(xs, ys) if low <= x <= high]
    if not inside:
        return None, None, 0
    mean = sum(inside) / len(inside)
    if len(inside) < 2:
        return mean, None, 1
    variance = sum((y - mean) ** 2 for y in inside) / (len(inside) - 1)
    return mean, math.sqrt(variance / len(inside)), len(inside)


def summarise_metric(run: Run, metric: str, by: Axis = "env_steps", threshold: float | None = None,
                     window: Window | None = None) -> MetricSummary:
    """Final, best, (with a threshold) the first row at or above it and (with a window) the mean over the window,
    for one metric of one run."""
    xs, ys = curve(run, metric, by)
    if not ys:
        return MetricSummary(None, None, None)
    best = max(range(len(ys)), key=lambda i: ys[i])
    mean, se, points = window_mean(xs, ys, window) if window is not None else (None, None, 0)
    summary = MetricSummary(final=ys[-1], best=ys[best], best_at=xs[best], window_mean=mean, window_se=se,
                            window_points=points)
    if threshold is None:
        return summary
    for row, seconds in zip(run.rows, elapsed_s(run)):
        value = finite_number(row.get(metric))
        if value is not None and value >= threshold:
            return replace(summary, reached_env_steps=int(row.get("env_steps") or 0), reached_s=seconds,
                           reached_update=int(row["update"]))
    return summary


def summarise(run: Run, metrics: Sequence[str], by: Axis = "env_steps",
              threshold: float | None = None, window: Window | None = None) -> RunSummary:
    """One run's table row: its progress (updates, env steps, wall clock, share of the planned steps done) and each
    metric's summary."""
    last = run.rows[-1]
    env_steps = int(last.get("env_steps") or 0)
    total = finite_number(run.config.get("total_env_steps"))
    times = [t for t in elapsed_s(run) if math.isfinite(t)]
    return RunSummary(
        label=run.label, path=str(run.path), mode=run.mode, updates=int(last["update"]), env_steps=env_steps,
        wall_s=times[-1] if times else 0.0, done=min(env_steps / total, 1.0) if total else None,
        metrics={metric: summarise_metric(run, metric, by, threshold, window) for metric in metrics},
    )


MISSING = object()
"""A key a run's config does not have (written by another version): shown as absent in a config difference."""


def config_diff(runs: Sequence[Run], ignore: Iterable[str] = IDENTITY_KEYS) -> dict[str, list[Any]]:
    """{dotted key: [each run's value, or MISSING]} for the keys whose values differ between the runs, in the order
    the configs list them. The keys that name a run (`IDENTITY_KEYS`) are left out: they always differ."""
    skip = set(ignore)
    keys: dict[str, None] = {}
    for run in runs:
        keys.update(dict.fromkeys(run.config))
    diff = {}
    for key in keys:
        if key in skip:
            continue
        values = [run.config.get(key, MISSING) for run in runs]
        if any(v is MISSING or v != values[0] for v in values) and not all(v is MISSING for v in values):
            diff[key] = values
    return diff


def plot_runs(runs: Sequence[Run], metrics: Sequence[str], by: Axis, path: Path | str) -> Path:
    """A PNG of each metric (one panel each) against `by`, one line per run (`monitor.charts`); returns its path."""
    x_label = {"env_steps": "env steps", "time_s": "seconds since the first update", "update": "update"}[by]
    panels = []
    for metric in metrics:
        series = []
        for i, run in enumerate(runs):
            xs, ys = curve(run, metric, by)
            series.append(Series(run.label, xs, ys, color=PALETTE[i % len(PALETTE)], width=2,
                                 markers=len(xs) <= 40))
        panels.append(Panel(metric, series, x_label=x_label, note="no values"))
    return render(panels, path)

"""`impulse compare RUN_DIR [RUN_DIR ...]`: training runs of either mode side by side, as a table.

One row per run: its label, mode, progress (share of `total_env_steps` done, updates, env steps, wall clock), and
for each metric (default: `solve_rate`, and `eval/mean` when a run has it) the final and best values and, with
`--threshold`, the env steps and time at which it first reached the bar, and with `--window LOW:HIGH` the mean and
standard error of its values between LOW and HIGH along `--by`. Below the table, the config keys whose
values differ between the runs. `--plot FILE.png` draws the curves, `--json` prints the same as JSON.
`--identical N` checks instead that the runs' first N updates agree bit for bit (exit status 1, listing the values,
where they do not). Reading, summarising and diffing are `monitor.runs`'s; this module parses and prints. Exit
status 2, with one line on stderr, for a path that is not a run, a run without metrics yet, or a metric no run
has.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Sequence
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING, Any

from impulse.deploy.runtime.exit_codes import EXIT_USAGE
from impulse.monitor.runs import (
    AXES,
    MACHINE_COLUMNS,
    MISSING,
    RunError,
    check_metrics,
    config_diff,
    default_metrics,
    mismatches,
    plot_runs,
    read_runs,
    summarise,
)

if TYPE_CHECKING:
    from impulse.monitor.runs import Axis, MetricSummary, RunSummary, Window


def run(args: argparse.Namespace, _config: object = None) -> int:
    # Loaded here, not with the CLI: the services' entry points import no monitor code but its config section.

    if args.identical is not None:
        return check_identical(args.runs, args.identical)

    if args.by not in AXES:
        print(f"impulse compare: --by must be one of {', '.join(AXES)}, got {args.by!r}", file=sys.stderr)
        return EXIT_USAGE
    try:
        window = parse_window(args.window) if args.window is not None else None
    except ValueError as err:
        print(f"impulse compare: {err}", file=sys.stderr)
        return EXIT_USAGE
    try:
        runs = read_runs(args.runs)
        metrics = list(dict.fromkeys(args.metrics)) if args.metrics else default_metrics(runs)
        check_metrics(runs, metrics)
    except RunError as err:
        print(f"impulse compare: {err}", file=sys.stderr)
        return EXIT_USAGE
    summaries = [summarise(r, metrics, args.by, args.threshold, window) for r in runs]
    diff = config_diff(runs)
    labels = [r.label for r in runs]
    if args.plot is not None:
        plotted = plot_runs(runs, metrics, args.by, args.plot)
        print(f"impulse compare: curves written to {plotted}", file=sys.stderr)
    if args.json:
        print(json.dumps(as_json(summaries, metrics, args.by, args.threshold, window, diff, labels), indent=2))
    else:
        print(table(summaries, metrics, args.by, args.threshold, window))
        print()
        print(diff_table(diff, labels))
    return 0


def parse_window(text: str) -> Window:
    """`--window LOW:HIGH` as (low, high); an empty end is open (-inf or inf). ValueError, naming the problem,
    for anything else."""
    low_text, colon, high_text = text.partition(":")
    if not colon:
        raise ValueError(f"--window must be LOW:HIGH (an end may be empty, as in 500:), got {text!r}")
    try:
        low = float(low_text) if low_text.strip() else -math.inf
        high = float(high_text) if high_text.strip() else math.inf
    except ValueError:
        raise ValueError(f"--window must be LOW:HIGH with numbers, got {text!r}") from None
    if math.isnan(low) or math.isnan(high) or low > high:
        raise ValueError(f"--window {text!r} is empty: LOW must be at most HIGH")
    return low, high


def window_label(window: Window, by: Axis) -> str:
    """The window as a column heading's range: 500-1.25k, 500-end, start-1.25k (in `by`'s units)."""
    low, high = window
    return (f"{'start' if math.isinf(low) else position(low, by)}-"
            f"{'end' if math.isinf(high) else position(high, by)}")


def check_identical(paths: Sequence[Path], updates: int) -> int:
    """`--identical N`: 0 and one line when the runs agree bit for bit over their first N updates; 1 and every
    differing value otherwise; 2 for a path that is not a run or one with fewer rows."""

    if updates < 1:
        print(f"impulse compare: --identical needs at least 1 update, got {updates}", file=sys.stderr)
        return EXIT_USAGE
    try:
        runs = read_runs(paths)
        found = mismatches(runs, updates)
    except RunError as err:
        print(f"impulse compare: {err}", file=sys.stderr)
        return EXIT_USAGE
    labels = [run.label for run in runs]
    if not found:
        print(f"identical: the first {updates} updates of {', '.join(labels)} agree bit for bit "
              f"({', '.join(MACHINE_COLUMNS)} left out)")
        return 0
    rows = [[str(m.update), m.column, *(json.dumps(value) for value in m.values)] for m in found]
    print(f"not identical: {len(found)} values differ in the first {updates} updates\n"
          + aligned(["update", "column", *labels], rows, left=2))
    return 1


def as_json(summaries: Sequence[RunSummary], metrics: Sequence[str], by: Axis, threshold: float | None,
            window: Window | None, diff: dict[str, list[Any]], labels: Sequence[str]) -> dict[str, Any]:
    """The comparison as JSON-ready data: the options (an open window end as null), one object per run, and
    {key: {label: value}} of the config differences (null where a run's config lacks the key)."""

    return {
        "metrics": list(metrics), "by": by, "threshold": threshold,
        "window": None if window is None else [None if math.isinf(end) else end for end in window],
        "runs": [asdict(summary) for summary in summaries],
        "config_diff": {key: {label: None if value is MISSING else value for label, value in zip(labels, values)}
                        for key, values in diff.items()},
    }


def steps(value: float | None) -> str:
    """Env steps or updates, compact: 81,920 -> 81.9k, 2,000,000 -> 2M."""
    if value is None:
        return "-"
    if abs(value) >= 1e6:
        return f"{value / 1e6:.3g}M"
    if abs(value) >= 1e4:
        return f"{value / 1e3:.3g}k"
    return f"{value:,.0f}"


def duration(seconds: float | None) -> str:
    """Wall clock: 75 -> 1:15, 3725 -> 1:02:05."""
    if seconds is None or not math.isfinite(seconds):
        return "-"
    whole = int(round(seconds))
    hours, rest = divmod(whole, 3600)
    return f"{hours}:{rest // 60:02d}:{rest % 60:02d}" if hours else f"{rest // 60}:{rest % 60:02d}"


def number(value: float | None) -> str:
    """A metric value, four significant digits."""
    return "-" if value is None else f"{value:.4g}"


def mean_cell(summary: MetricSummary) -> str:
    """A window's mean: 0.3901 ± 0.01812 (n=6); without a standard error (one value) the mean and n alone."""
    if summary.window_mean is None:
        return "-"
    spread = "" if summary.window_se is None else f" ± {number(summary.window_se)}"
    return f"{number(summary.window_mean)}{spread} (n={summary.window_points})"


def position(value: float | None, by: Axis) -> str:
    """Where along `by` a value was reached."""
    if value is None:
        return "-"
    return duration(value) if by == "time_s" else steps(value)


def table(summaries: Sequence[RunSummary], metrics: Sequence[str], by: Axis, threshold: float | None,
          window: Window | None = None) -> str:
    """The comparison as an aligned text table, one row per run (text left, numbers right)."""
    header = ["run", "mode", "done", "updates", "env steps", "wall"]
    for metric in metrics:
        header += [f"{metric} final", f"best (at {by})"]
        if threshold is not None:
            header += [f">={threshold:g} steps", f">={threshold:g} time"]
        if window is not None:
            header += [f"mean {window_label(window, by)}"]
    rows = []
    for s in summaries:
        row = [s.label, s.mode, "-" if s.done is None else f"{s.done:.0%}", f"{s.updates:,}", steps(s.env_steps),
               duration(s.wall_s)]
        for metric in metrics:
            m = s.metrics[metric]
            row += [number(m.final), f"{number(m.best)} @{position(m.best_at, by)}" if m.best is not None else "-"]
            if threshold is not None:
                row += [steps(m.reached_env_steps), duration(m.reached_s)]
            if window is not None:
                row += [mean_cell(m)]
        rows.append(row)
    return aligned(header, rows, left=2)


def diff_table(diff: dict[str, list[Any]], labels: Sequence[str]) -> str:
    """The config keys whose values differ, one line each with every run's value."""

    if not diff:
        return "config: no differences (name and run_dir aside)" if len(labels) > 1 else "config: one run"
    rows = [[key, *("(absent)" if v is MISSING else toml_value(v) for v in values)] for key, values in diff.items()]
    return "config differences:\n" + aligned(["key", *labels], rows, left=len(labels) + 1)


def toml_value(value: Any) -> str:
    """A config value as it reads in config.toml (strings quoted, lists bracketed)."""
    return json.dumps(value) if isinstance(value, str | list | bool) else str(value)


def aligned(header: Sequence[str], rows: Sequence[Sequence[str]], left: int) -> str:
    """Columns padded to their widest cell: the first `left` columns aligned left, the others right."""
    widths = [max(len(str(cell)) for cell in column) for column in zip(header, *rows)]

    def line(cells: Sequence[str]) -> str:
        cells = (c.ljust(w) if i < left else c.rjust(w) for i, (c, w) in enumerate(zip(cells, widths)))
        return "  ".join(cells).rstrip()

    return "\n".join([line(header), line(["-" * w for w in widths]), *(line(r) for r in rows)])

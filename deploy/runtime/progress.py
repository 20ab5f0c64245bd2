"""What a person watching a training run sees, and what a script reading it afterwards parses.

`MetricsFile` appends one JSON object per line, each written whole or not at all (`engine.io_errors.append_whole`),
so a crash loses at most the line being written and a write that fails on a full disk (`DiskFullError`) leaves the
file as it was, ready for the same row to be written again; after a resume it first sets aside the rows of the
updates the run redoes (`rewind_metrics`).

What is shown while a command runs, built on rich (its Live display and Table), one job for each helper:

- `LiveArea`: a live display at the bottom of a terminal with everything else the process prints (log lines,
  `print`s) scrolling above it, never under or through it; every live display of the commands is one.
- `fitted_table`: a table no wider than the terminal, its columns left out by priority when they do not all fit
  (the launcher's status display and the progress row both are one).
- `ProgressLine`: a run's progress (phase, update n/N, steps/s, ETA, solve rate, skipped non-finite updates) as a
  live row on a terminal, and a log line every few seconds when the output is not a terminal (CI logs, `nohup`).
- `Heartbeat`: what a command does while it has nothing else to show (building, compiling, evaluating, writing a
  video): a spinner with the phase and its seconds on a terminal, and a log line every few seconds that nothing
  else was said otherwise.

A terminal is a tty whose TERM is not "dumb" (`interactive`); anything else gets plain log lines, as a log file
should.
"""

from __future__ import annotations

import io
import json
import logging
import math
import os
import sys
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, NamedTuple, TextIO

from rich.cells import cell_len
from rich.console import Console, ConsoleOptions, JustifyMethod, RenderableType, RenderResult
from rich.live import Live
from rich.progress_bar import ProgressBar
from rich.spinner import Spinner
from rich.table import Table
from rich.text import Text

from impulse.engine.io_errors import append_whole, check_space, writing

log = logging.getLogger(__name__)


def _plain(value: Any) -> Any:
    """JSON-friendly scalars from numpy/JAX values."""
    if hasattr(value, "item") and getattr(value, "size", 1) == 1:
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


SUPERSEDED_SUFFIX = "-superseded"
"""`metrics.jsonl`'s rows of updates a resumed run redoes go to `metrics-superseded.jsonl` beside it."""


def rewind_metrics(path: Path, through_update: int) -> int:
    """Keep in `path` only the rows of updates up to `through_update` (the checkpoint a run resumes from), so that
    after a resume each update has one row; the rows of the updates that died with the previous process (and
    lines cut short by a crash) are moved, never deleted, to `<stem>-superseded.jsonl`. Returns how many moved."""
    if not path.is_file():
        return 0
    kept, superseded = [], []
    for line in path.read_text(errors="replace").splitlines(keepends=True):
        if not line.strip():
            continue
        try:
            update = json.loads(line).get("update")
        except (ValueError, AttributeError):
            update = None
        (kept if isinstance(update, int) and update <= through_update else superseded).append(line)
    if not superseded:
        return 0
    aside = path.with_name(f"{path.stem}{SUPERSEDED_SUFFIX}{path.suffix}")
    with writing(aside), aside.open("a") as out:
        out.writelines(line if line.endswith("\n") else line + "\n" for line in superseded)
    scratch = path.with_name(f".{path.name}.tmp")
    try:
        with writing(scratch):
            scratch.write_text("".join(kept))
    except OSError:
        scratch.unlink(missing_ok=True)  # what was written of it would only take space
        raise
    scratch.replace(path)
    log.info("%s: %d rows after update %d (redone by this resumed run) moved to %s", path, len(superseded),
             through_update, aside.name)
    return len(superseded)


class MetricsFile:
    """metrics.jsonl in the run directory, appended to row by row. Opened with `through_update` (a resumed run's
    checkpoint), it first sets aside the rows of later updates (`rewind_metrics`): each update has one row.

    Each row goes to the file in one unbuffered append, whole or not at all: a row that does not fit on the disk
    raises `DiskFullError` (naming the file and the space left) and leaves the file as it was, so writing the same
    row again once there is space adds it exactly once."""

    def __init__(self, path: str | Path, through_update: int | None = None):
        self.path = Path(path)
        with writing(self.path):
            self.path.parent.mkdir(parents=True, exist_ok=True)
            if through_update is not None:
                rewind_metrics(self.path, through_update)
            self._fd: int | None = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)

    def write(self, record: dict[str, Any]) -> None:
        """Append `record` as one JSON line (non-finite numbers as null); `DiskFullError` if it does not fit."""
        if self._fd is None:
            raise ValueError(f"{self.path} is closed")
        line = (json.dumps({k: _plain(v) for k, v in record.items()}) + "\n").encode()
        with writing(self.path):
            check_space(self.path, len(line))
            append_whole(self._fd, line)

    def close(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None


def _duration(seconds: float) -> str:
    if not math.isfinite(seconds):
        return "?"
    seconds = int(seconds)
    hours, rest = divmod(seconds, 3600)
    return f"{hours}:{rest // 60:02d}:{rest % 60:02d}" if hours else f"{rest // 60}:{rest % 60:02d}"


TERMINAL_FALLBACK_COLUMNS = 200
"""The width a live display is drawn at on a terminal whose size cannot be read (an emulator behind a file object,
as tests use): the lines it is given are drawn as they are, not cut again."""
HEARTBEAT_EVERY_S = 5.0
"""Off a terminal, a phase that has been quiet this long says in a log line that it still runs."""
COLUMN_GAP = 2
"""Spaces between two columns of a fitted table."""
MIN_FLEXIBLE = 12
"""The fewest characters a flexible column (what is left of a row) is shown with; with less room it is left out."""
SKIPPED_NON_FINITE = "skipped/non_finite"
"""The metrics.jsonl column of updates skipped as non-finite (`learner.non_finite.SKIPPED_COLUMN`, named here so
that this module loads without JAX: the command line imports it)."""


def interactive(stream: TextIO) -> bool:
    """Whether `stream` is a terminal a live display can redraw in place: a tty whose TERM is not "dumb"."""
    try:
        tty = stream.isatty()
    except (AttributeError, ValueError):  # no isatty, or closed
        return False
    return bool(tty) and os.environ.get("TERM", "").lower() not in ("dumb", "unknown")


def _readable_size(stream: TextIO) -> bool:
    """Whether the terminal behind `stream` says how wide it is."""
    try:
        os.get_terminal_size(stream.fileno())
    except (AttributeError, OSError, ValueError, io.UnsupportedOperation):
        return False
    return True


class LiveArea:
    """A rich Live display at the bottom of the terminal `stream`, with everything else the process prints scrolling
    above it. While it is shown, stdout and stderr (those of them that are terminals: a redirected stdout, such as a
    benchmark's JSON lines, stays where it goes) are written through its console, and so are the log handlers that
    wrote to them, in their own format. `renderable` is asked for what to draw at every refresh: by itself
    `refresh_per_second` times a second with `auto_refresh`, else when `refresh` is called and when a line is
    printed above it. Without `redirect` nothing else may write to `stream` while it is shown. `width`: the
    columns to draw in (default: the terminal's, as it is resized).

    When it stops, its last drawing stays on the screen, above what is printed next (`transient`: it is erased)."""

    def __init__(self, stream: TextIO, renderable: Callable[[], RenderableType], *, auto_refresh: bool,
                 refresh_per_second: float = 2.0, redirect: bool = True, transient: bool = False,
                 width: int | None = None) -> None:
        # `width` None: the terminal's own, read again at every drawing (it may be resized), or a fixed one where
        # it cannot be read.
        if width is None and not _readable_size(stream):
            width = TERMINAL_FALLBACK_COLUMNS
        self.console = Console(file=stream, force_terminal=True, width=width, highlight=False, markup=False,
                               emoji=False)
        self._redirect = redirect
        self._live = Live(console=self.console, get_renderable=renderable, auto_refresh=auto_refresh,
                          refresh_per_second=refresh_per_second, transient=transient,
                          redirect_stdout=redirect and (sys.stdout is stream or interactive(sys.stdout)),
                          redirect_stderr=redirect and (sys.stderr is stream or interactive(sys.stderr)))
        self._swapped: list[tuple[logging.StreamHandler, Any]] = []
        self.started = False

    def start(self) -> None:
        """Draw it, and from now on print everything else above it."""
        if self.started:
            return
        before = (sys.stdout, sys.stderr)
        self._live.start(refresh=True)
        self.started = True
        if not self._redirect:
            return
        for handler in logging.getLogger().handlers:
            if not isinstance(handler, logging.StreamHandler):
                continue
            for old, now in zip(before, (sys.stdout, sys.stderr), strict=True):
                if handler.stream is old and now is not old:  # the stream is redirected through the console now
                    self._swapped.append((handler, handler.setStream(now)))
                    break

    def refresh(self) -> None:
        """Draw it again now."""
        if self.started:
            self._live.refresh()

    def stop(self) -> None:
        """Stop redrawing, leaving the last drawing on the screen, and give the streams and handlers back."""
        if not self.started:
            return
        for handler, old in reversed(self._swapped):
            handler.setStream(old)
        self._swapped.clear()
        self._live.stop()
        self.started = False


Cell = str | Text | RenderableType
"""A table cell: text (measured by its length) or a drawing such as a bar (as wide as its column's `width`)."""


class Column(NamedTuple):
    """A column of a fitted table."""

    key: str
    header: str
    keep: int
    """Rank in keeping: when the columns do not all fit, the highest ranks are left out first."""
    justify: JustifyMethod = "left"
    required: bool = False
    """Shown at any width, its cells cut short with "…" if need be."""
    flexible: bool = False
    """Takes the width the other columns leave (its cells cut short with "…"); left out with less than
    MIN_FLEXIBLE."""
    width: int | None = None
    """The width of cells that are drawings rather than text (a bar)."""


def _cell_width(cell: Cell, column: Column) -> int:
    if isinstance(cell, str):
        return cell_len(cell)
    if isinstance(cell, Text):
        return cell.cell_len
    return column.width or 0


def _empty(cell: Cell | None) -> bool:
    return cell is None or (isinstance(cell, str | Text) and not str(cell))


def fitted_table(columns: Sequence[Column], rows: Sequence[dict[str, Cell]], width: int) -> Table:
    """A rich Table of `rows` (their cells by column key) no wider than `width`, with a header: a column no row has
    a cell for is left out, and so are those that do not fit, in the order of their `keep` rank (the required ones
    always stay, the flexible one gets what is left); the others keep their order, left to right."""
    present = [column for column in columns if any(not _empty(row.get(column.key)) for row in rows)]
    natural = {column.key: max([cell_len(column.header)] + [_cell_width(row[column.key], column) for row in rows
                                                           if not _empty(row.get(column.key))])
               for column in present}
    chosen: set[str] = set()
    used = -COLUMN_GAP
    for column in sorted(present, key=lambda c: c.keep):
        if column.flexible:
            continue
        need = natural[column.key] + COLUMN_GAP
        if column.required or used + need <= width:
            chosen.add(column.key)
            used += need
    left = width - used - COLUMN_GAP
    flexible = [column for column in present if column.flexible]
    if flexible and left >= MIN_FLEXIBLE:
        chosen.add(flexible[0].key)
        natural[flexible[0].key] = left
    shown = [column for column in present if column.key in chosen]
    widths = _narrowed({column.key: natural[column.key] for column in shown}, width - COLUMN_GAP * (len(shown) - 1))
    table = Table(box=None, padding=(0, 1), pad_edge=False, show_edge=False, header_style="bold")
    for column in shown:
        table.add_column(column.header, justify=column.justify, no_wrap=True, overflow="ellipsis",
                         max_width=widths[column.key])
    for row in rows:
        table.add_row(*(row.get(column.key) or "" for column in shown))
    return table


def _narrowed(widths: dict[str, int], room: int) -> dict[str, int]:
    """`widths` made to add up to at most `room`, taking from the widest column first (a long phase or alarm is
    cut before a short number is), never below one character."""
    widths = dict(widths)
    excess = sum(widths.values()) - room
    while excess > 0:
        widest = max(widths, key=lambda key: widths[key])
        if widths[widest] <= 1:
            break
        widths[widest] -= 1
        excess -= 1
    return widths


class Fitted:
    """A renderable drawn by `build(width)` at the width it is given (the terminal's, at every redraw)."""

    def __init__(self, build: Callable[[int], RenderableType]) -> None:
        self.build = build

    def __rich_console__(self, console: Console, options: ConsoleOptions) -> RenderResult:
        yield self.build(options.max_width)


PROGRESS_COLUMNS = (
    Column("phase", "phase", 0, required=True),
    Column("update", "update", 1, justify="right", required=True),
    Column("steps_per_s", "steps/s", 4, justify="right"),
    Column("eta", "ETA", 5, justify="right"),
    Column("solved", "solved", 3, justify="right", required=True),
    Column("skipped", "skipped", 2, required=True),
    Column("return", "return", 6, justify="right"),
    Column("episodes", "episodes", 7, justify="right"),
    Column("bar", "", 8, width=20),
)
"""The progress row's columns: the phase, the update (or steps) done, the skipped non-finite updates and the solve
rate stay at any width; the rest are left out from the right as the terminal narrows."""


STEADY_PHASES = ("training", "done", "stopped")
"""Phases shown without their seconds: they are not a wait."""


def _phase_text(phase: str, since: float, quiet: tuple[str, ...] = STEADY_PHASES) -> str:
    """A phase with its seconds so far, unless it is a steady one (`STEADY_PHASES`)."""
    return phase if phase in quiet else f"{phase} {time.monotonic() - since:.0f} s"


class ProgressLine:
    """The progress of a run of `total` environment steps (`num_updates` updates when known): on a terminal a live
    row below the log lines (phase, update n/N, steps/s, ETA, solve rate, return, episodes and skipped non-finite
    updates); otherwise a log line every `log_every_s` seconds, as a log file should have it."""

    def __init__(self, total: int, stream: TextIO | None = None, log_every_s: float = 10.0,
                 num_updates: int | None = None):
        self.total = total
        self.num_updates = num_updates
        self.stream = stream or sys.stderr
        self.interactive = interactive(self.stream)
        self.log_every_s = log_every_s
        self._last_log = -math.inf
        self._phase = ("training", time.monotonic())
        self._cells: dict[str, Cell] = {}
        self._live: LiveArea | None = None

    def phase(self, name: str) -> None:
        """What the run does now: "training", "checkpointing", "evaluating 42 levels x 20 attempts" (with its
        seconds so far on the row, unless it is training)."""
        self._phase = (name, time.monotonic())
        self._draw()

    def update(self, done: int, steps_per_second: float, metrics: dict[str, Any],
               record: dict[str, Any] | None = None) -> None:
        """After a cycle: `done` env steps of the run so far at `steps_per_second`, the metrics window's summary
        (`metrics`: solve rate, return, episodes) and the cycle's metrics row (`record`: its update and skipped
        non-finite updates)."""
        fraction = min(done / max(self.total, 1), 1.0)
        eta = max(self.total - done, 0) / steps_per_second if steps_per_second > 0 else math.inf
        # An actor may produce more than the run's budget (batches the learner dropped): never past 100%.
        parts = [f"{min(done, self.total):,}/{self.total:,} steps", f"{steps_per_second:,.0f} steps/s",
                 f"ETA {_duration(eta)}"]
        cells: dict[str, Cell] = {"steps_per_s": f"{steps_per_second:,.0f}", "eta": _duration(eta),
                                  "bar": ProgressBar(total=1.0, completed=fraction, width=20)}
        for key, label, fmt in (
            ("episode_return", "return", "{:.3f}"),
            ("solve_rate", "solved", "{:.0%}"),
            ("episodes", "episodes", "{:,}"),
        ):
            value = metrics.get(key)
            if value is not None and not (isinstance(value, float) and math.isnan(value)):
                parts.append(f"{label} {fmt.format(value)}")
                cells[label] = fmt.format(value)
        cells.setdefault("solved", "-")
        update = (record or {}).get("update")
        if isinstance(update, int) and self.num_updates:
            cells["update"] = f"{min(update, self.num_updates):,}/{self.num_updates:,}"
        else:
            cells["update"] = f"{min(done, self.total):,}/{self.total:,} steps"
        skipped = (record or {}).get(SKIPPED_NON_FINITE)
        if skipped:
            cells["skipped"] = Text(f"{skipped:.0f} non-finite", style="bold red")
            parts.append(f"SKIPPED {skipped:.0f} non-finite updates")
        text = " | ".join(parts)
        if self.interactive:
            self._cells = cells
            self._draw()
        elif time.monotonic() - self._last_log >= self.log_every_s or done >= self.total:
            self._last_log = time.monotonic()
            log.info("progress %s", text)

    def _row(self, width: int) -> RenderableType:
        phase, since = self._phase
        cells = {"update": "-", "steps_per_s": "-", "eta": "-", "solved": "-", **self._cells,
                 "phase": _phase_text(phase, since)}
        return fitted_table(PROGRESS_COLUMNS, [cells], width)

    def _draw(self) -> None:
        if not self.interactive:
            return
        if self._live is None:
            self._live = LiveArea(self.stream, lambda: Fitted(self._row), auto_refresh=True)
            self._live.start()
        else:
            self._live.refresh()

    def close(self, phase: str | None = None) -> None:
        """Stop the live row; its last drawing stays on the screen, showing `phase` ("done", "stopped") if given."""
        if phase is not None:
            self._phase = (phase, time.monotonic())
        if self._live is not None:
            self._live.refresh()
            self._live.stop()
            self._live = None


class Heartbeat:
    """What a command does while it shows nothing else, for phases that take more than a few seconds.

    On a terminal: a spinner with the phase and its seconds so far, below the log lines. Off a terminal: the first
    phase (`phase`, when given) as a log line at once, and a log line whenever the current phase has been quiet
    for `every_s` seconds ("compiling the evaluation (2 levels x 2 attempts): 10 s so far"). Later phases are set
    with `phase()`; the code that starts them logs them itself, as it does without a heartbeat, so the heartbeat
    only says what runs now and for how long. `touch()` says that something else was just shown (a benchmark's
    own progress line), which keeps the heartbeat quiet for `every_s` more. Used as a context manager."""

    def __init__(self, phase: str | None = None, stream: TextIO | None = None, every_s: float = HEARTBEAT_EVERY_S,
                 logger: logging.Logger | None = None) -> None:
        self.stream = stream or sys.stderr
        self.interactive = interactive(self.stream)
        self.every_s = every_s
        self.log = logger or log
        self._first = phase
        self._phase: tuple[str, float] | None = (phase, time.monotonic()) if phase else None
        self._quiet_since = time.monotonic()
        self._spinner = Spinner("dots", style="cyan")
        self._live: LiveArea | None = None
        self._stop = threading.Event()
        self._beat: threading.Thread | None = None

    def __enter__(self) -> Heartbeat:
        if self.interactive:
            if self._phase is not None:
                self._show()
        else:
            if self._first:
                self.log.info("%s ...", self._first)
            self._beat = threading.Thread(target=self._beat_off_terminal, name="heartbeat", daemon=True)
            self._beat.start()
        return self

    def phase(self, text: str) -> None:
        """What runs now (a new phase: its seconds count from now)."""
        self._phase = (text, time.monotonic())
        self._quiet_since = time.monotonic()
        if self.interactive:
            self._show()

    def touch(self) -> None:
        """Something else was just shown: the next heartbeat line is due `every_s` from now."""
        self._quiet_since = time.monotonic()

    def _show(self) -> None:
        if self._live is None:
            # Erased when it ends: the log line of what comes next says that it is done.
            self._live = LiveArea(self.stream, self._drawing, auto_refresh=True, refresh_per_second=4,
                                  transient=True)
            self._live.start()

    def _drawing(self) -> RenderableType:
        phase = self._phase
        text = "" if phase is None else _phase_text(phase[0], phase[1], quiet=())
        self._spinner.update(text=Text(text, no_wrap=True, overflow="ellipsis"))
        return self._spinner

    def _beat_off_terminal(self) -> None:
        while not self._stop.wait(min(1.0, self.every_s)):
            now = time.monotonic()
            phase = self._phase
            if phase is not None and now - self._quiet_since >= self.every_s:
                self._quiet_since = now
                self.log.info("%s: %.0f s so far", phase[0], now - phase[1])

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        if self._beat is not None:
            self._beat.join()
        if self._live is not None:
            self._live.stop()
            self._live = None

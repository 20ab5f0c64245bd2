"""What a person watching a training run sees, and what a script reading it afterwards parses.

`MetricsFile` appends one JSON object per line, each written whole or not at all (`engine.io_errors.append_whole`),
so a crash loses at most the line being written and a write that fails on a full disk (`DiskFullError`) leaves the
file as it was, ready for the same row to be written again; after a resume it first sets aside the rows of the
updates the run redoes (`rewind_metrics`). `ProgressLine`
redraws one status line on a terminal (steps/s, return, solve rate, ETA) and falls back to a log line every few
seconds when the output is not a terminal (CI logs, `nohup`).
"""

from __future__ import annotations

import json
import logging
import math
import os
import sys
import time
from pathlib import Path
from typing import Any, TextIO

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


class ProgressLine:
    """A one-line progress display for a run of `total` environment steps."""

    def __init__(self, total: int, stream: TextIO | None = None, log_every_s: float = 10.0):
        self.total = total
        self.stream = stream or sys.stderr
        self.interactive = self.stream.isatty()
        self.log_every_s = log_every_s
        self._last_log = -math.inf

    def update(self, done: int, steps_per_second: float, metrics: dict[str, Any]) -> None:
        fraction = min(done / max(self.total, 1), 1.0)
        eta = max(self.total - done, 0) / steps_per_second if steps_per_second > 0 else math.inf
        # An actor may produce more than the run's budget (batches the learner dropped): never past 100%.
        parts = [f"{min(done, self.total):,}/{self.total:,} steps", f"{steps_per_second:,.0f} steps/s",
                 f"ETA {_duration(eta)}"]
        for key, label, fmt in (
            ("episode_return", "return", "{:.3f}"),
            ("solve_rate", "solved", "{:.0%}"),
            ("episodes", "episodes", "{:,}"),
        ):
            value = metrics.get(key)
            if value is not None and not (isinstance(value, float) and math.isnan(value)):
                parts.append(f"{label} {fmt.format(value)}")
        text = " | ".join(parts)
        if self.interactive:
            width = 20
            filled = int(width * fraction)
            bar = "#" * filled + "-" * (width - filled)
            self.stream.write(f"\r[{bar}] {text}\x1b[K")
            self.stream.flush()
        elif time.monotonic() - self._last_log >= self.log_every_s or done >= self.total:
            self._last_log = time.monotonic()
            log.info("progress %s", text)

    def close(self) -> None:
        if self.interactive:
            self.stream.write("\n")
            self.stream.flush()

"""The Run page's data: which training runs the studio can show, and their learning curves from `metrics.jsonl`.

A run is a folder holding `metrics.jsonl` (what `impulse train` and `impulse launch` write, one JSON object per
update) or, for a shipped agent, `curve.jsonl` (the same rows, kept with `pretrained/<name>`). The studio lists
the runs it already knows: the checkpoints the Play page offers (`--run RUN_DIR` first, then `./pretrained/*`;
for a checkpoint's folder, the run directory above it) and every folder directly under the runs folders it is
given (`./runs` by default, where `run_dir = "runs/{name}"` puts new runs). Only listed runs are read: a request
names a run by its id in the listing, never by a path of its own.

Rows are read incrementally (`MetricsReader`): each request reads only what was appended since the last one, so a
live run's page can poll every few seconds; a file that shrank (a resumed run sets aside the rows it redoes) is
read again from its start. A reply carries at most `MAX_ROWS` rows and the scalar columns only, without the
per-level evaluation columns (`eval/level/...`, one per level of the evaluation sets), so it stays small.
"""

from __future__ import annotations

import json
import math
import threading
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from impulse.studio.library import UnknownLevel

METRICS_FILES = ("metrics.jsonl", "curve.jsonl")
"""The files a run's curves are read from, in this order of preference."""
MAX_ROWS = 2000
"""The most rows one reply carries; the page asks again for the rest ("more": true)."""
MAX_COLUMNS = 200
SKIPPED_PREFIXES = ("eval/level/",)
"""Columns left out of the replies: one per evaluated level, hundreds for the Kinetix sets."""
PARENT_LEVELS = 3
"""How far above a checkpoint's folder the run directory (the folder with the metrics file) is looked for."""


class UnknownRun(UnknownLevel):
    """A run id the studio does not list (404, as an unknown level)."""


def metrics_file(folder: Path) -> Path | None:
    """The metrics file of the run in `folder`, or None when it has none."""
    for name in METRICS_FILES:
        path = folder / name
        if path.is_file():
            return path
    return None


def _run_of(checkpoint: Path) -> Path | None:
    """The run directory of a checkpoint path as the Play page offers it: the path itself, or one of the few
    folders above it (a checkpoint's own folder is `RUN_DIR/checkpoints/<step>`)."""
    for folder in (checkpoint, *list(checkpoint.parents)[:PARENT_LEVELS]):
        if folder.is_dir() and metrics_file(folder) is not None:
            return folder
    return None


@dataclass
class _Cursor:
    """How far one metrics file has been read: its identity, the byte offset of the first unread line, and the
    rows read so far (scalar columns only)."""

    inode: int = -1
    offset: int = 0
    rows: list[dict[str, float]] = field(default_factory=list)
    columns: dict[str, None] = field(default_factory=dict)


def _scalars(record: Any, index: int) -> dict[str, float] | None:
    """The numeric columns of one metrics row (booleans as 0/1, non-finite numbers dropped), with `update` set (the
    row's position when the row has none); None for a line that is not a JSON object."""
    if not isinstance(record, dict):
        return None
    row: dict[str, float] = {}
    for name, value in record.items():
        if not isinstance(name, str) or name.startswith(SKIPPED_PREFIXES):
            continue
        if isinstance(value, bool):
            value = float(value)
        if isinstance(value, (int, float)) and math.isfinite(value):
            row[name] = value
    if not isinstance(row.get("update"), (int, float)):
        row["update"] = index + 1
    return row


class MetricsReader:
    """Reads metrics files incrementally, one cursor per file, safe to call from several worker threads."""

    def __init__(self) -> None:
        self._cursors: dict[Path, _Cursor] = {}
        self._lock = threading.Lock()

    def rows(self, path: Path) -> tuple[list[dict[str, float]], list[str]]:
        """Every row of `path` so far and the columns seen, reading only what was appended since the last call (the
        whole file again when it was replaced or shrank)."""
        with self._lock:
            cursor = self._cursors.setdefault(path, _Cursor())
            stat = path.stat()
            if stat.st_ino != cursor.inode or stat.st_size < cursor.offset:
                cursor.inode, cursor.offset, cursor.rows, cursor.columns = stat.st_ino, 0, [], {}
            if stat.st_size > cursor.offset:
                with path.open("rb") as file:
                    file.seek(cursor.offset)
                    chunk = file.read(stat.st_size - cursor.offset)
                complete = chunk[:chunk.rfind(b"\n") + 1]  # a line still being written waits for the next call
                cursor.offset += len(complete)
                for line in complete.splitlines():
                    try:
                        row = _scalars(json.loads(line), len(cursor.rows))
                    except ValueError:
                        continue  # a line cut short by a crash
                    if row is None:
                        continue
                    cursor.rows.append(row)
                    for name in row:
                        if len(cursor.columns) < MAX_COLUMNS:
                            cursor.columns.setdefault(name)
            return cursor.rows, list(cursor.columns)


class Runs:
    """The runs a studio shows: those of `checkpoints` (the Play page's list) and every run folder directly under
    `folders`. Listed afresh at each call, so a run started after the studio appears."""

    def __init__(self, checkpoints: Sequence[str] = (), folders: Sequence[Path] = ()):
        self.checkpoints = tuple(checkpoints)
        self.folders = tuple(Path(folder) for folder in folders)
        self.reader = MetricsReader()

    def listing(self) -> list[dict[str, Any]]:
        """`[{"id", "title", "file"}]`: the offered checkpoints' runs first (in the Play page's order), then the
        runs folders' runs by name; each run once."""
        found: dict[str, dict[str, Any]] = {}

        def add(folder: Path, title: str) -> None:
            path = metrics_file(folder)
            key = str(folder.resolve())
            if path is not None and key not in {entry["key"] for entry in found.values()}:
                found[str(folder)] = {"id": str(folder), "title": title, "file": path.name, "key": key}

        for checkpoint in self.checkpoints:
            run = _run_of(Path(checkpoint).expanduser())
            if run is not None:
                add(run, str(run))
        for folder in self.folders:
            if folder.is_dir():
                for run in sorted(child for child in folder.iterdir() if child.is_dir()):
                    add(run, str(run))
        return [{k: v for k, v in entry.items() if k != "key"} for entry in found.values()]

    def metrics(self, run_id: str, after: float = -math.inf, limit: int = MAX_ROWS) -> dict[str, Any]:
        """The run's rows whose update is after `after`, at most `limit` (capped at MAX_ROWS), in columns:
        `{"run", "file", "columns", "rows": [[value or None per column]], "total", "last_update", "more"}`;
        `UnknownRun` for a run the studio does not list."""
        if run_id not in {entry["id"] for entry in self.listing()}:
            raise UnknownRun(f"no run {run_id!r} among the runs this studio shows")
        path = metrics_file(Path(run_id))
        if path is None:
            raise UnknownRun(f"run {run_id!r} has no metrics file any more")
        try:
            rows, columns = self.reader.rows(path)
        except OSError as err:
            raise UnknownRun(f"cannot read {path}: {err.strerror or err}") from None
        limit = max(1, min(limit, MAX_ROWS))
        start = next((i for i, row in enumerate(rows) if row["update"] > after), len(rows))
        chosen = rows[start:start + limit]
        last = chosen[-1]["update"] if chosen else (after if math.isfinite(after) else None)
        return {"run": run_id, "file": path.name, "columns": columns,
                "rows": [[row.get(name) for name in columns] for row in chosen],
                "total": len(rows), "last_update": last, "more": start + limit < len(rows)}


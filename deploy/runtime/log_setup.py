"""Logging for every `impulse` process: readable text on a terminal, or one JSON object per line for machines.

Logs go to stderr, because stdout carries data (benchmark JSON lines, `--print-config` TOML) that must stay
parseable. Structured values are passed as `extra={...}` and appear as `key=value` pairs in text and as fields
in JSON, so the same call site serves a person watching a run and a log collector reading many of them.
(Named `log_setup` so that it never shadows the standard library's `logging`.)

A log on a full disk (a launched process's log file under the run directory): a line that cannot be written is
dropped quietly (`LogHandler`), instead of the logging module's "--- Logging error ---" traceback, which went into
the same full file, cut short, and became the launcher's error line; once lines can be written again, the first
says how many were lost and why (`engine.io_errors`' message: the path and the space left). An uncaught
`DiskFullError` ends the process with its one line rather than a traceback (`configure_logging` installs the
hook).
"""

from __future__ import annotations

import json
import logging
import os
import sys
import time
from types import TracebackType
from typing import Any, Literal, TextIO

from impulse.engine.io_errors import DiskFullError, disk_full_error

LogFormat = Literal["text", "json"]
LEVELS = ("debug", "info", "warning", "error", "critical")

# Attributes every LogRecord has; anything else on a record came from `extra=` and is shown as a field.
_STANDARD_ATTRS = frozenset(vars(logging.LogRecord("", 0, "", 0, "", None, None))) | {"message", "asctime"}


def record_extras(record: logging.LogRecord) -> dict[str, Any]:
    """The `extra=` fields of a record, in the order they were given."""
    return {k: v for k, v in vars(record).items() if k not in _STANDARD_ATTRS and not k.startswith("_")}


class TextFormatter(logging.Formatter):
    """`HH:MM:SS.mmm LEVEL logger: message key=value ...`: short lines that a terminal and grep both read well."""

    def format(self, record: logging.LogRecord) -> str:
        clock = time.strftime("%H:%M:%S", time.localtime(record.created))
        line = f"{clock}.{int(record.msecs):03d} {record.levelname:<7} {record.name}: {record.getMessage()}"
        extras = record_extras(record)
        if extras:
            line += " " + " ".join(f"{k}={_text_value(v)}" for k, v in extras.items())
        if record.exc_info:
            line += "\n" + self.formatException(record.exc_info)
        return line


class JsonFormatter(logging.Formatter):
    """One JSON object per line: ts (ISO 8601, UTC), level, logger, msg, then the extra fields."""

    def format(self, record: logging.LogRecord) -> str:
        stamp = time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(record.created))
        entry: dict[str, Any] = {
            "ts": f"{stamp}.{int(record.msecs):03d}Z",
            "level": record.levelname,
            "logger": record.name,
            "msg": record.getMessage(),
        }
        for key, value in record_extras(record).items():
            entry.setdefault(key, value)
        if record.exc_info:
            entry["exc"] = self.formatException(record.exc_info)
        return json.dumps(entry, default=str, ensure_ascii=False)


def stream_path(stream: TextIO) -> str:
    """The file a stream writes to, for a message (`/proc/self/fd` on Linux, else the stream's name)."""
    try:
        return os.readlink(f"/proc/self/fd/{stream.fileno()}")
    except (OSError, ValueError, AttributeError):
        return str(getattr(stream, "name", "<log stream>"))


class LogHandler(logging.StreamHandler):
    """The one handler of every process: a StreamHandler that, when its stream's disk is full (see the module
    docstring), counts the lines it drops (`lost`) and writes, before the next line that fits, one line saying
    how many and why. Any other failure to write is reported as the logging module reports it."""

    def __init__(self, stream: TextIO | None = None) -> None:
        super().__init__(stream)
        self.lost = 0
        self.why: DiskFullError | None = None

    def emit(self, record: logging.LogRecord) -> None:
        if self.lost:
            note = logging.LogRecord("impulse.log", logging.WARNING, __file__, 0, "%d log line(s) were lost: %s",
                                     (self.lost, self.why), None)
            lost = self.lost
            try:
                self.stream.write(self.format(note) + self.terminator)
                self.flush()
            except Exception:
                self.handleError(note)
                if self.lost > lost:  # still full: counted once more, for this record, which goes the same way
                    return
            else:
                self.lost, self.why = 0, None
        super().emit(record)

    def handleError(self, record: logging.LogRecord) -> None:
        full = disk_full_error(stream_path(self.stream), sys.exc_info()[1])
        if full is None:
            super().handleError(record)
            return
        self.lost += 1
        self.why = full


def _disk_full_hook(kind: type[BaseException], error: BaseException, trace: TracebackType | None) -> None:
    """`sys.excepthook`: an uncaught `DiskFullError` ends the process with its one line (a traceback would be
    cut short by the same full disk); anything else as Python reports it."""
    if isinstance(error, DiskFullError):
        try:
            sys.stderr.write(f"impulse: {error}\n")
            sys.stderr.flush()
        except OSError:
            pass
        return
    sys.__excepthook__(kind, error, trace)


def configure_logging(fmt: LogFormat = "text", level: str = "info", stream: TextIO | None = None) -> None:
    """Route all logging through one handler on the root logger with the chosen format and level.

    Replaces handlers installed before (so calling it twice, as tests do, never doubles lines), lowers the
    chatter of libraries that log at INFO on import or per call, and installs the hook that ends a process on a
    full disk with one line (the module docstring).
    """
    if level.lower() not in LEVELS:
        raise ValueError(f"log level must be one of {', '.join(LEVELS)}, got {level!r}")
    handler = LogHandler(stream if stream is not None else sys.stderr)
    handler.setFormatter(JsonFormatter() if fmt == "json" else TextFormatter())
    if sys.excepthook is sys.__excepthook__:
        sys.excepthook = _disk_full_hook
    root = logging.getLogger()
    for old in list(root.handlers):
        root.removeHandler(old)
    root.addHandler(handler)
    root.setLevel(level.upper())
    for noisy in ("jax._src", "absl", "orbax"):
        logging.getLogger(noisy).setLevel(max(logging.WARNING, root.level))


def _text_value(value: Any) -> str:
    text = str(value)
    return repr(text) if (not text or any(c.isspace() for c in text)) else text

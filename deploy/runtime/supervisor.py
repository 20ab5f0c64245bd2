"""Child processes of `impulse launch`: start them, notice when they exit, restart them with a back-off, give up
on one that keeps failing the same way, and stop them in order.

Each child writes its output to its own log file (appended across restarts). A child that dies is restarted after
a delay that doubles with each quick death (RESTART_BACKOFF_S) and resets once it has stayed up for
STABLE_AFTER_S, so a process that crashes at start-up does not spin, and one that crashes rarely comes back fast.

When a child exits with an error, its error line is read from what that incarnation appended to its log: the last
exception line of a Python traceback, else the last non-empty line (a leading clock stamp dropped), never a line
of a traceback's frames (`error_line`); a traceback cut short (by a full disk, most often: the log is on it too) is
said to be, and where the log's file system is full the line says that instead. A child that
fails GIVE_UP_AFTER times in a row the same way (the same exit code and error line, each time within
STABLE_AFTER_S of its start) is not restarted: the same start-up will fail again, and a crash loop only hides the
error. Failures are non-zero exit statuses and crash signals (SIGSEGV, SIGABRT, ...); SIGKILL, SIGTERM, SIGINT
and SIGHUP come from outside (a user, a test, the OOM killer) and never count towards giving up. A child that
exits with EXIT_CANNOT_RUN has said its configuration cannot run on this machine (an update or a rollout that does
not fit in memory): it is given up on at once, however long it took to find out.

A child dies with the launcher, even when the launcher is killed with SIGKILL: it asks the kernel for SIGTERM
when its parent dies (PR_SET_PDEATHSIG). It asks itself, first thing, before it executes the command (`Child.start`
runs the command through GUARD, a few lines of Python): the parent's pid is in the child's environment
(PARENT_PID_ENV), and if the parent is already gone by then, the child stops at once. No `preexec_fn` is used:
CPython runs its at-fork hooks for one, in the launcher, and JAX's warns that a fork of a multithreaded process
may deadlock.
"""

from __future__ import annotations

import json
import logging
import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from impulse.deploy.runtime.exit_codes import EXIT_CANNOT_RUN
from impulse.engine.io_errors import disk_full_message, disk_usage, writing

log = logging.getLogger("impulse.launch")

RESTART_BACKOFF_S = (1.0, 2.0, 4.0, 8.0, 16.0, 30.0)
STABLE_AFTER_S = 60.0
GIVE_UP_AFTER = 3
"""Identical quick failures in a row after which a child is not restarted."""
EXTERNAL_SIGNALS = frozenset({signal.SIGKILL, signal.SIGTERM, signal.SIGINT, signal.SIGHUP})
"""Signals that end a child from outside: they say nothing about how its start-up goes, so they never count."""
LOG_TAIL_BYTES = 64 * 1024
"""How much of what an incarnation appended to its log is searched for its error line (the end of it)."""
PR_SET_PDEATHSIG = 1
PARENT_PID_ENV = "IMPULSE_PARENT_PID"
"""In a child's environment: the pid of the supervisor that started it (read and removed by GUARD)."""
GUARD = f"""\
import ctypes, os, signal, sys
parent = os.environ.pop({PARENT_PID_ENV!r}, "")
if parent.isdigit():
    try:
        ctypes.CDLL(None, use_errno=True).prctl({PR_SET_PDEATHSIG}, signal.SIGTERM)
    except (OSError, AttributeError):
        pass
    if os.getppid() != int(parent):
        signal.raise_signal(signal.SIGTERM)
os.execvp(sys.argv[1], sys.argv[1:])
"""
"""What a child runs first, `python -c GUARD ARGV...` (`guarded`): ask for SIGTERM when the parent dies; stop at
once if the parent named in PARENT_PID_ENV is already gone (it died between the fork and the request: no signal
would ever come); take the variable out of the environment (the child's own children must not read their
grandparent's pid); then replace itself with ARGV (the same pid; the request survives the exec). It imports
nothing of ours, so that it costs no more than an interpreter's start."""
TRACEBACK = "Traceback (most recent call last):"
GROUP_TRACEBACK = "Exception Group Traceback (most recent call last):"
FATAL = "Fatal Python error:"
CUT_SHORT = "a traceback cut short (its exception line is missing)"
"""The error line of an output that ends inside a traceback and says nothing else."""
MAX_ERROR_LINE = 300
"""Characters an error line is cut to."""
LOW_SPACE_BYTES = 1 << 20
"""Free space under which a child's log is taken to be on a full disk (for its error line)."""
_EXCEPTION_LINE = re.compile(r"^(?:[A-Za-z_]\w*\.)*[A-Za-z_]\w*(?::(?:\s.*)?)?$")
"""`ValueError: ...`, `jax.errors.JaxRuntimeError: ...`, `KeyboardInterrupt`: how Python ends a traceback."""
_TRACEBACK_PARTS = (TRACEBACK, "During handling of the above exception, another exception occurred:",
                    "The above exception was the direct cause of the following exception:", "--- Logging error ---",
                    "Call stack:", "Exception ignored in", "Exception in thread", 'File "', "[Previous line repeated")
_CLOCK_STAMP = re.compile(
    r"^(?:\d{2}:\d{2}:\d{2}(?:\.\d+)?"  # ours: HH:MM:SS.mmm
    r"|\d{4}-\d{2}-\d{2}[T ]\d{2}:\d{2}:\d{2}(?:[.,]\d+)?Z?"  # ISO 8601 (zenoh's and others')
    r"|[IWEF]\d{4} \d{2}:\d{2}:\d{2}\.\d+\s+\d+)\s+"  # absl/glog: I1125 14:17:03.123456 12345
)


def guarded(argv: list[str], env: dict[str, str]) -> tuple[list[str], dict[str, str]]:
    """The command line and environment that start `argv` through GUARD, so that it dies with this process:
    what `Child.start` runs (and what any other starter of a child, such as `impulse view`'s, can run instead of
    a `preexec_fn`)."""
    return [sys.executable, "-c", GUARD, *argv], {**env, PARENT_PID_ENV: str(os.getpid())}


@dataclass
class Child:
    """One supervised process. `argv` is called with whether this start is a restart.

    After an exit: `last_exit` is its code, `error_line` the error it ended with (None for a clean exit or a kill
    from outside), `streak` the identical quick failures in a row so far, and `gave_up` whether the supervisor
    stopped restarting it."""

    name: str
    argv: Callable[[bool], list[str]]
    log_path: Path
    process: subprocess.Popen | None = None
    restarts: int = 0
    quick_deaths: int = 0
    started_at: float = 0.0
    restart_at: float | None = None
    last_exit: int | None = None
    history: list[int] = field(default_factory=list)
    log_start: int = 0
    """Size of the log file when this incarnation started: what it wrote is what follows."""
    error_line: str | None = None
    streak: int = 0
    last_failure: tuple[int, str | None] | None = None
    gave_up: bool = False
    started_wall: float = 0.0
    """`time.time()` at this incarnation's start, to compare with times that messages carry."""
    shown_status: tuple[float, Any] | None = field(default=None, repr=False, compare=False)
    """The status display's memory (`status_display.current_status`): the status it last showed for this child
    and the start (`started_at`) of the incarnation it showed it for."""

    @property
    def pid(self) -> int | None:
        return self.process.pid if self.process is not None and self.process.poll() is None else None

    def start(self, env: dict[str, str]) -> None:
        """Start an incarnation: its output appended to the log, in a session of its own, dying with this process
        (the module docstring)."""
        restart = self.process is not None
        with writing(self.log_path):
            self.log_path.parent.mkdir(parents=True, exist_ok=True)
            out = self.log_path.open("ab")
        with out:
            self.log_start = os.fstat(out.fileno()).st_size
            # A session of its own: a Ctrl-C at the terminal reaches the launcher only, which stops the children
            # in order.
            argv, child_env = guarded(self.argv(restart), env)
            self.process = subprocess.Popen(argv, stdout=out, stderr=subprocess.STDOUT, env=child_env,
                                            start_new_session=True)
        self.started_at = time.monotonic()
        self.started_wall = time.time()
        self.restart_at = None
        self.error_line = None
        if restart:
            self.restarts += 1
        log.info("%s started (pid %d)%s", self.name, self.process.pid, " again" if restart else "")

    def read_error_line(self) -> str | None:
        """The error line of what this incarnation appended to its log (None if it wrote nothing)."""
        try:
            with self.log_path.open("rb") as log_file:
                size = log_file.seek(0, os.SEEK_END)
                log_file.seek(max(self.log_start, size - LOG_TAIL_BYTES))
                appended = log_file.read()
        except OSError:
            return None
        line = error_line(appended.decode("utf-8", errors="replace"))
        if line in (None, CUT_SHORT):  # nothing to say, or cut short: a full disk, if its log's is full
            usage = disk_usage(self.log_path)
            if usage is not None and usage.free < LOW_SPACE_BYTES:
                return disk_full_message(self.log_path)
        return line


def is_failure(code: int) -> bool:
    """Whether an exit code says the child failed by itself: a non-zero status or a crash signal (not one of
    EXTERNAL_SIGNALS, which come from outside)."""
    if code >= 0:
        return code != 0
    return -code not in {int(sig) for sig in EXTERNAL_SIGNALS}


def error_line(text: str) -> str | None:
    """The line that says why a process ended, from the end of its output, at most MAX_ERROR_LINE characters:
    - the exception line of the last Python traceback (the first line after "Traceback (most recent call
      last):" that is not part of a frame and reads as an exception: `Name: message`; log lines another thread
      wrote in between are passed over; for an exception group, its own line);
    - if that traceback was cut short (no exception line: the output ended inside it, as it does when the disk is
      full), the exception line of the traceback before it (a chained one), else the last line outside any frame,
      else CUT_SHORT (also for an output that holds nothing but pieces of a traceback);
    - else the last "Fatal Python error:" line (a crash), else the last non-empty line.
    Never a line of a traceback's frames (`File "..."`, source, carets). A leading clock stamp is dropped (it
    would make every failure look different) and a JSON log line is shown as its level, logger and message."""
    lines = [line.rstrip() for line in text.splitlines()]
    starts = [i for i, line in enumerate(lines) if line.startswith(TRACEBACK) or line.lstrip(" |+-")
              .startswith(GROUP_TRACEBACK)]
    found = None
    for number, start in enumerate(reversed(starts)):
        end = starts[len(starts) - number] if number else len(lines)
        found = _exception_line(lines[start + 1:end], group=not lines[start].startswith(TRACEBACK))
        if found is not None:
            break
    if found is None:
        fatal = [line for line in lines if line.startswith(FATAL)]
        found = fatal[-1] if fatal else _last_plain_line(lines)
    if found is None and (starts or any(line.strip() for line in lines)):  # nothing but pieces of a traceback
        found = CUT_SHORT
    return None if found is None else _cut(found, MAX_ERROR_LINE)


def _exception_line(block: list[str], group: bool) -> str | None:
    """The exception line of one traceback's lines (after its "Traceback" line), or None if it has none."""
    for line in block:
        if group:  # `  | ExceptionGroup: ...`, at the depth of the frames' `  |   File ...`
            match = re.match(r"^\s*\| (\S.*)$", line)
            line = match.group(1) if match else ""
        if not line or line[0].isspace() or _is_traceback_part(line):
            continue
        if _EXCEPTION_LINE.match(line):
            return line
    return None


def _is_traceback_part(line: str) -> bool:
    """Whether `line` (stripped or not) is obviously a piece of a traceback rather than something said."""
    stripped = line.strip()
    return (stripped.startswith(_TRACEBACK_PARTS) or stripped.lstrip(" |+-").startswith(GROUP_TRACEBACK)
            or set(stripped) <= set("^~ ") or set(stripped) <= set("+-| "))


def _last_plain_line(lines: list[str]) -> str | None:
    """The last non-empty line that is not part of a traceback (its header, its frames and their source lines,
    which are indented, or the lines that chain two tracebacks): one that starts at the margin if there is one,
    else any (stripped), as `_plain` shows it."""
    candidates, inside = [], False
    for line in lines:
        if line.startswith(TRACEBACK) or line.lstrip(" |+-").startswith(GROUP_TRACEBACK):
            inside = True
        elif line and not line[0].isspace():
            inside = False
        if line.strip() and not inside and not _is_traceback_part(line):
            candidates.append(line)
    at_margin = [line for line in candidates if not line[0].isspace()]
    chosen = at_margin or candidates
    return _plain(chosen[-1].strip()) if chosen else None


def _cut(line: str, limit: int) -> str:
    return line if len(line) <= limit else line[:limit - 3] + "..."


def _plain(line: str) -> str:
    """A log line without its time: `LEVEL logger: message` for our JSON lines, else the line less a leading
    clock stamp."""
    if line.startswith("{"):
        try:
            entry = json.loads(line)
        except ValueError:
            entry = None
        if isinstance(entry, dict) and "msg" in entry:
            return f"{entry.get('level', '')} {entry.get('logger', '')}: {entry['msg']}".strip()
    return _CLOCK_STAMP.sub("", line, count=1)


def describe_exit(code: int) -> str:
    """"exit status N" or "killed by SIGNAME"."""
    if code < 0:
        try:
            return f"killed by {signal.Signals(-code).name}"
        except ValueError:
            return f"killed by signal {-code}"
    return f"exit status {code}"


def describe_failure(child: Child) -> str:
    """How a child last ended, with its error line: "exit status 1: ValueError: ..."."""
    how = "not started" if child.last_exit is None else describe_exit(child.last_exit)
    return f"{how}: {child.error_line}" if child.error_line else how


class Supervisor:
    """Starts, watches, restarts and stops a set of children.

    `give_up_after`, `backoff_s` and `stable_after_s` default to GIVE_UP_AFTER, RESTART_BACKOFF_S and
    STABLE_AFTER_S; tests pass small ones."""

    def __init__(self, children: list[Child], env: dict[str, str] | None = None, *,
                 give_up_after: int = GIVE_UP_AFTER, backoff_s: Sequence[float] = RESTART_BACKOFF_S,
                 stable_after_s: float = STABLE_AFTER_S):
        if give_up_after < 1 or not backoff_s:
            raise ValueError("give_up_after must be at least 1 and backoff_s must not be empty")
        self.children = {child.name: child for child in children}
        self.env = dict(os.environ if env is None else env)
        self.give_up_after = give_up_after
        self.backoff_s = tuple(backoff_s)
        self.stable_after_s = stable_after_s

    def start(self, name: str) -> None:
        self.children[name].start(self.env)

    def exited(self) -> list[tuple[Child, int]]:
        """Children that have exited since the last call, with their exit codes (negative: a signal). Each one's
        `error_line`, `streak` and `gave_up` are brought up to date first: restart only those that did not give
        up."""
        ended = []
        for child in self.children.values():
            if child.process is None or child.restart_at is not None:
                continue
            code = child.process.poll()
            if code is not None and child.last_exit is None:
                child.last_exit = code
                child.history.append(code)
                self._note_exit(child, code)
                ended.append((child, code))
        return ended

    def _note_exit(self, child: Child, code: int) -> None:
        """Count identical quick failures in a row; anything else (a clean exit, a kill from outside, a failure
        after a stable run) breaks the row."""
        failed = is_failure(code)
        child.error_line = child.read_error_line() if failed else None
        quick = time.monotonic() - child.started_at < self.stable_after_s
        if failed and quick:
            failure = (code, child.error_line)
            child.streak = child.streak + 1 if failure == child.last_failure else 1
            child.last_failure = failure
        else:
            child.streak = 0
            child.last_failure = None
        child.gave_up = child.streak >= self.give_up_after or code == EXIT_CANNOT_RUN

    def restart_later(self, child: Child) -> float:
        """Schedule a restart after the back-off; returns the delay."""
        if time.monotonic() - child.started_at >= self.stable_after_s:
            child.quick_deaths = 0
        delay = self.backoff_s[min(child.quick_deaths, len(self.backoff_s) - 1)]
        child.quick_deaths += 1
        child.restart_at = time.monotonic() + delay
        return delay

    def restart_due(self) -> list[Child]:
        """Start the children whose back-off has passed; returns them."""
        started = []
        for child in self.children.values():
            if child.restart_at is not None and time.monotonic() >= child.restart_at:
                child.last_exit = None
                child.start(self.env)
                started.append(child)
        return started

    def stop(self, names: list[str], timeout_s: float) -> None:
        """SIGTERM the named children (their run loops finish the cycle and checkpoint), wait up to `timeout_s`,
        then SIGKILL whatever is left."""
        running = [self.children[n] for n in names if self.children[n].pid is not None]
        for child in self.children.values():
            if child.name in names:
                child.restart_at = None
        for child in running:
            child.process.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + timeout_s
        for child in running:
            try:
                child.process.wait(timeout=max(deadline - time.monotonic(), 0.1))
            except subprocess.TimeoutExpired:
                log.warning("%s did not stop within %.0f s: killing it", child.name, timeout_s)
                child.process.kill()
                child.process.wait()
            child.last_exit = child.process.returncode

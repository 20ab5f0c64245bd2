"""Child processes of `impulse launch`: start them, notice when they exit, restart them with a back-off, give up
on one that keeps failing the same way, and stop them in order.

Each child writes its output to its own log file (appended across restarts). A child that dies is restarted after
a delay that doubles with each quick death (RESTART_BACKOFF_S) and resets once it has stayed up for
STABLE_AFTER_S, so a process that crashes at start-up does not spin, and one that crashes rarely comes back fast.

When a child exits with an error, its error line is read from what that incarnation appended to its log: the last
exception line of a Python traceback, else the last non-empty line (a leading clock stamp dropped). A child that
fails GIVE_UP_AFTER times in a row the same way (the same exit code and error line, each time within
STABLE_AFTER_S of its start) is not restarted: the same start-up will fail again, and a crash loop only hides the
error. Failures are non-zero exit statuses and crash signals (SIGSEGV, SIGABRT, ...); SIGKILL, SIGTERM, SIGINT
and SIGHUP come from outside (a user, a test, the OOM killer) and never count towards giving up. A child that
exits with EXIT_CANNOT_RUN has said its configuration cannot run on this machine (an update or a rollout that does
not fit in memory): it is given up on at once, however long it took to find out.
"""

from __future__ import annotations

import ctypes
import json
import logging
import os
import re
import signal
import subprocess
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

log = logging.getLogger("impulse.launch")

RESTART_BACKOFF_S = (1.0, 2.0, 4.0, 8.0, 16.0, 30.0)
STABLE_AFTER_S = 60.0
GIVE_UP_AFTER = 3
"""Identical quick failures in a row after which a child is not restarted."""
EXIT_CANNOT_RUN = 78
"""Exit status of a process whose configuration cannot run here (sysexits' EX_CONFIG): restarting it would fail
the same way, after the same long compile, so it is never restarted."""
EXTERNAL_SIGNALS = frozenset({signal.SIGKILL, signal.SIGTERM, signal.SIGINT, signal.SIGHUP})
"""Signals that end a child from outside: they say nothing about how its start-up goes, so they never count."""
LOG_TAIL_BYTES = 64 * 1024
"""How much of what an incarnation appended to its log is searched for its error line (the end of it)."""
PR_SET_PDEATHSIG = 1
TRACEBACK = "Traceback (most recent call last):"
FATAL = "Fatal Python error:"
_CLOCK_STAMP = re.compile(
    r"^(?:\d{2}:\d{2}:\d{2}(?:\.\d+)?"  # ours: HH:MM:SS.mmm
    r"|\d{4}-\d{2}-\d{2}[T ]\d{2}:\d{2}:\d{2}(?:[.,]\d+)?Z?"  # ISO 8601 (zenoh's and others')
    r"|[IWEF]\d{4} \d{2}:\d{2}:\d{2}\.\d+\s+\d+)\s+"  # absl/glog: I1125 14:17:03.123456 12345
)


def die_with_parent() -> None:
    """In a child before exec (Linux): receive SIGTERM when the parent dies, even by SIGKILL, so no service (nor a
    viewer `impulse view` started) outlives the process that started it. Elsewhere a no-op."""
    try:
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGTERM)
    except (OSError, AttributeError):
        pass


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

    @property
    def pid(self) -> int | None:
        return self.process.pid if self.process is not None and self.process.poll() is None else None

    def start(self, env: dict[str, str]) -> None:
        restart = self.process is not None
        self.log_path.parent.mkdir(parents=True, exist_ok=True)
        with self.log_path.open("ab") as out:
            self.log_start = os.fstat(out.fileno()).st_size
            # A session of its own: a Ctrl-C at the terminal reaches the launcher only, which stops the children
            # in order.
            self.process = subprocess.Popen(self.argv(restart), stdout=out, stderr=subprocess.STDOUT, env=env,
                                            start_new_session=True, preexec_fn=die_with_parent)
        self.started_at = time.monotonic()
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
        return error_line(appended.decode("utf-8", errors="replace"))


def is_failure(code: int) -> bool:
    """Whether an exit code says the child failed by itself: a non-zero status or a crash signal (not one of
    EXTERNAL_SIGNALS, which come from outside)."""
    if code >= 0:
        return code != 0
    return -code not in {int(sig) for sig in EXTERNAL_SIGNALS}


def error_line(text: str) -> str | None:
    """The line that says why a process ended, from the end of its output: the exception line of the last Python
    traceback (the first unindented line after "Traceback (most recent call last):"), else the last "Fatal Python
    error:" line (a crash), else the last non-empty line. A leading clock stamp is dropped (it would make every
    failure look different) and a JSON log line is shown as its level, logger and message."""
    lines = [line.rstrip() for line in text.splitlines()]
    tracebacks = [i for i, line in enumerate(lines) if line.startswith(TRACEBACK)]
    if tracebacks:
        for line in lines[tracebacks[-1] + 1:]:
            if line and not line[0].isspace():
                return line
    fatal = [line for line in lines if line.startswith(FATAL)]
    if fatal:
        return fatal[-1]
    for line in reversed(lines):
        if line.strip():
            return _plain(line.strip())
    return None


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

"""Child processes of `impulse launch`: start them, notice when they exit, restart them with a back-off, and stop
them in order.

Each child writes its output to its own log file (appended across restarts). A child that dies is restarted after
a delay that doubles with each quick death (RESTART_BACKOFF_S) and resets once it has stayed up for
STABLE_AFTER_S, so a process that crashes at start-up does not spin, and one that crashes rarely comes back fast.
"""

from __future__ import annotations

import ctypes
import logging
import os
import signal
import subprocess
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

log = logging.getLogger("impulse.launch")

RESTART_BACKOFF_S = (1.0, 2.0, 4.0, 8.0, 16.0, 30.0)
STABLE_AFTER_S = 60.0
PR_SET_PDEATHSIG = 1


def die_with_parent() -> None:
    """In a child before exec (Linux): receive SIGTERM when the parent dies, even by SIGKILL, so no service (nor a
    viewer `impulse view` started) outlives the process that started it. Elsewhere a no-op."""
    try:
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGTERM)
    except (OSError, AttributeError):
        pass


@dataclass
class Child:
    """One supervised process. `argv` is called with whether this start is a restart."""

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

    @property
    def pid(self) -> int | None:
        return self.process.pid if self.process is not None and self.process.poll() is None else None

    def start(self, env: dict[str, str]) -> None:
        restart = self.process is not None
        self.log_path.parent.mkdir(parents=True, exist_ok=True)
        with self.log_path.open("ab") as out:
            # A session of its own: a Ctrl-C at the terminal reaches the launcher only, which stops the children
            # in order.
            self.process = subprocess.Popen(self.argv(restart), stdout=out, stderr=subprocess.STDOUT, env=env,
                                            start_new_session=True, preexec_fn=die_with_parent)
        self.started_at = time.monotonic()
        self.restart_at = None
        if restart:
            self.restarts += 1
        log.info("%s started (pid %d)%s", self.name, self.process.pid, " again" if restart else "")


def describe_exit(code: int) -> str:
    if code < 0:
        try:
            return f"killed by {signal.Signals(-code).name}"
        except ValueError:
            return f"killed by signal {-code}"
    return f"exit status {code}"


class Supervisor:
    """Starts, watches, restarts and stops a set of children."""

    def __init__(self, children: list[Child], env: dict[str, str] | None = None):
        self.children = {child.name: child for child in children}
        self.env = dict(os.environ if env is None else env)

    def start(self, name: str) -> None:
        self.children[name].start(self.env)

    def exited(self) -> list[tuple[Child, int]]:
        """Children that have exited since the last call, with their exit codes (negative: a signal)."""
        ended = []
        for child in self.children.values():
            if child.process is None or child.restart_at is not None:
                continue
            code = child.process.poll()
            if code is not None and child.last_exit is None:
                child.last_exit = code
                child.history.append(code)
                ended.append((child, code))
        return ended

    def restart_later(self, child: Child) -> float:
        """Schedule a restart after the back-off; returns the delay."""
        if time.monotonic() - child.started_at >= STABLE_AFTER_S:
            child.quick_deaths = 0
        delay = RESTART_BACKOFF_S[min(child.quick_deaths, len(RESTART_BACKOFF_S) - 1)]
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

"""A command run under a pseudo-terminal of a given size, as a person in tmux runs it: what it writes is fed to a
pyte screen of that size, and the screen is kept as it looked every fraction of a second (`TerminalRun.snapshots`),
so a test can ask what was on the screen while the command ran and what is left on it at the end."""

from __future__ import annotations

import fcntl
import os
import pty
import select
import signal
import struct
import subprocess
import termios
import time
from dataclasses import dataclass, field

import pyte

from tests.support.paths import REPO


@dataclass
class TerminalRun:
    """What a command left on a terminal: its exit status, the screen at the end, and the screens on the way."""

    returncode: int
    screen: list[str]
    snapshots: list[list[str]] = field(default_factory=list)

    def shown(self, text: str) -> bool:
        """Whether `text` was on the screen at some point (on one line)."""
        return any(text in line for snapshot in [*self.snapshots, self.screen] for line in snapshot)

    def dump(self) -> str:
        """The last screen, framed, for an assertion's message."""
        return "\n".join(f"|{line.rstrip()}" for line in self.screen)


def run_in_terminal(argv: list[str], columns: int, rows: int = 40, timeout_s: float = 300.0,
                    every_s: float = 0.25, env: dict[str, str] | None = None) -> TerminalRun:
    """Run `argv` with a pseudo-terminal of `columns` x `rows` as its stdin, stdout and stderr (the window size set
    with TIOCSWINSZ, and COLUMNS/LINES as a shell exports them), until it exits; on `timeout_s`, kill it and fail
    showing the screen."""
    master, slave = pty.openpty()
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", rows, columns, 0, 0))
    full_env = {**os.environ, "COLUMNS": str(columns), "LINES": str(rows), "TERM": "xterm-256color",
                "IMPULSE_CACHE_DIR": str(REPO / ".cache"), "PYTHONUNBUFFERED": "1", **(env or {})}
    full_env.pop("FORCE_COLOR", None)
    full_env.pop("TTY_COMPATIBLE", None)
    process = subprocess.Popen(argv, stdin=slave, stdout=slave, stderr=slave, cwd=REPO, env=full_env,
                               start_new_session=True, close_fds=True)
    os.close(slave)
    screen = pyte.Screen(columns, rows)
    stream = pyte.ByteStream(screen)
    snapshots: list[list[str]] = []
    last_snapshot = 0.0
    deadline = time.monotonic() + timeout_s
    try:
        while True:
            if time.monotonic() > deadline:
                os.killpg(process.pid, signal.SIGKILL)
                process.wait()
                raise AssertionError(f"{argv} did not end in {timeout_s:.0f} s:\n" +
                                     "\n".join(f"|{line.rstrip()}" for line in screen.display))
            ready, _, _ = select.select([master], [], [], 0.05)
            if ready:
                try:
                    data = os.read(master, 65536)
                except OSError:  # the terminal closed: everything holding it has exited
                    data = b""
                if not data:
                    break
                stream.feed(data)
                continue
            if process.poll() is not None:
                break
            # Quiet for a moment: the screen is as the command left it, not halfway through a redraw.
            if time.monotonic() - last_snapshot >= every_s:
                snapshots.append(list(screen.display))
                last_snapshot = time.monotonic()
    finally:
        os.close(master)
    process.wait()
    return TerminalRun(process.returncode, list(screen.display), snapshots)

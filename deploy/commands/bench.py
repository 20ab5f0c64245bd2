"""`impulse bench NAME [args...]`: find and run a benchmark module of the `benchmarks` package.

A benchmark is any public module of the package (its file name does not start with `_`) with a
`main(argv) -> int | None`; the arguments after NAME go to it untouched, so each benchmark owns its options.
Modules are listed without importing them, so `impulse bench --help` stays instant even though benchmarks
import JAX.

While a benchmark runs, a heartbeat on stderr says what it does (`deploy.runtime.progress.Heartbeat`): its newest
progress line (what it last wrote to stderr) with the seconds since, as a spinner on a terminal and, when stderr is
not one, as a log line whenever it has been quiet for 5 s. Its JSON lines on stdout are left as they are.
"""

from __future__ import annotations

import contextlib
import difflib
import importlib
import io
import logging
import pkgutil
import sys
from collections.abc import Callable, Iterator, Sequence

from impulse.deploy.runtime.progress import Heartbeat

DEFAULT_PACKAGE = "impulse.benchmarks"
log = logging.getLogger("impulse.bench")


class UnknownBenchmark(LookupError):
    """NAME is not a benchmark module; the message lists the ones there are."""


def available(package: str = DEFAULT_PACKAGE) -> list[str]:
    """Names of the benchmark modules, sorted."""
    pkg = importlib.import_module(package)
    return sorted(m.name for m in pkgutil.iter_modules(pkg.__path__) if not m.name.startswith("_"))


def run(name: str, argv: Sequence[str], package: str = DEFAULT_PACKAGE) -> int:
    """Import `package.name` and call its `main(argv)`; returns its exit status (None counts as 0)."""
    names = available(package)
    if name not in names:
        message = f"unknown benchmark '{name}'; available: {', '.join(names) or '(none)'}"
        close = difflib.get_close_matches(name, names, n=1)
        if close:
            message += f" (did you mean '{close[0]}'?)"
        raise UnknownBenchmark(message)
    module = importlib.import_module(f"{package}.{name}")
    main = getattr(module, "main", None)
    if not callable(main):
        raise UnknownBenchmark(f"{package}.{name} has no main(argv) function, so it is not a runnable benchmark")
    with Heartbeat(f"benchmark {name}", logger=log) as beat, _following_stderr(
            lambda line: beat.phase(f"benchmark {name}: {line}")):
        status = main(list(argv))
    return int(status or 0)


class _LineWatcher(io.TextIOBase):
    """A text stream that writes through to `stream` and tells `on_line` of every non-blank line written."""

    def __init__(self, stream: io.TextIOBase, on_line: Callable[[str], None]) -> None:
        self._stream = stream
        self._on_line = on_line
        self._partial = ""

    def write(self, text: str) -> int:
        written = self._stream.write(text)
        *lines, self._partial = (self._partial + text).split("\n")
        for line in lines:
            if line.strip():
                self._on_line(line.strip())
        return len(text) if written is None else written

    def flush(self) -> None:
        self._stream.flush()

    def isatty(self) -> bool:
        return self._stream.isatty()

    def fileno(self) -> int:
        return self._stream.fileno()


@contextlib.contextmanager
def _following_stderr(on_line: Callable[[str], None]) -> Iterator[None]:
    """While inside: what is written to `sys.stderr` (a benchmark's progress lines) also goes to `on_line`."""
    previous = sys.stderr
    sys.stderr = _LineWatcher(previous, on_line)  # type: ignore[assignment]
    try:
        yield
    finally:
        sys.stderr = previous

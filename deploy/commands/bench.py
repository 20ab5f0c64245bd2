"""`impulse bench NAME [args...]`: find and run a benchmark module of the `benchmarks` package.

A benchmark is any public module of the package (its file name does not start with `_`) with a
`main(argv) -> int | None`; the arguments after NAME go to it untouched, so each benchmark owns its options.
Modules are listed without importing them, so `impulse bench --help` stays instant even though benchmarks
import JAX.
"""

from __future__ import annotations

import difflib
import importlib
import pkgutil
from collections.abc import Sequence

DEFAULT_PACKAGE = "impulse.benchmarks"


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
    status = main(list(argv))
    return int(status or 0)

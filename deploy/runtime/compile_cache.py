"""JAX's persistent compilation cache for every Impulse process, so a second start skips recompiling; and, on
request, a record of what each process compiled and for how long (`IMPULSE_COMPILE_LOG`)."""

from __future__ import annotations

import atexit
import fcntl
import json
import os
import sys
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

import jax
from jax import monitoring

COMPILE_LOG_ENV = "IMPULSE_COMPILE_LOG"
"""A file path: each process that enables the cache appends one JSON line to it when it exits, with the seconds
it spent tracing, lowering and compiling (or reading back from the cache), per jitted function name. For finding
where a test suite's or a process start's time goes; unset, nothing is recorded."""
COMPILE_EVENTS = {
    "/jax/core/compile/jaxpr_trace_duration": "trace",
    "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower",
    "/jax/core/compile/backend_compile_duration": "compile",
}
"""JAX's duration events a compile log adds up, by the name the log gives them. "compile" includes a cache hit's
read-back: a program compiled for real takes far longer than one read back."""


def enable_compile_cache() -> Path:
    """Keep compiled programs across runs (the training step takes tens of seconds to compile on CPU): in
    $IMPULSE_CACHE_DIR, else the checkout's ignored .cache/jax (shared with the tests), else ~/.cache/impulse.
    With $IMPULSE_COMPILE_LOG set, also record this process's compiles there (`COMPILE_LOG_ENV`)."""

    checkout = Path(__file__).resolve().parents[2]
    if os.environ.get("IMPULSE_CACHE_DIR"):
        root = Path(os.environ["IMPULSE_CACHE_DIR"])
    elif (checkout / "pyproject.toml").is_file():
        root = checkout / ".cache"
    else:
        root = Path.home() / ".cache" / "impulse"
    directory = root / "jax"
    jax.config.update("jax_compilation_cache_dir", str(directory))
    # Every program, however quick to compile: a process's start runs hundreds of small ones (building levels,
    # initialising a network, op by op) whose compiles, summed, take seconds, and reading them back takes a
    # fraction of that (benchmarks/RESULTS.md, "Process start").
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    if os.environ.get(COMPILE_LOG_ENV):
        record_compiles(Path(os.environ[COMPILE_LOG_ENV]))
    return directory


_recording: list[Path] = []


def record_compiles(path: Path) -> None:
    """Add up this process's trace, lower and compile durations per function name, and append them to `path` as
    one JSON line at exit ({"argv", "pid", "wall_s", "totals": {stage: s}, "functions": {name: {stage: [count,
    s]}}}). Once per process: later calls do nothing."""

    if _recording:
        return
    _recording.append(path)
    started = time.monotonic()
    functions: dict[str, dict[str, list[float]]] = defaultdict(lambda: defaultdict(lambda: [0, 0.0]))

    def heard(event: str, duration_s: float, **labels: Any) -> None:
        stage = COMPILE_EVENTS.get(event)
        if stage is not None:
            name = str(labels.get("fun_name", "?"))
            if name.startswith("jit(") and name.endswith(")"):  # lowering and compiling name it jit(f), tracing f
                name = name[4:-1]
            entry = functions[name][stage]
            entry[0] += 1
            entry[1] += duration_s

    def write() -> None:
        totals = defaultdict(float)
        for stages in functions.values():
            for stage, (_, seconds) in stages.items():
                totals[stage] += seconds
        line = json.dumps({"argv": sys.argv[:4], "pid": os.getpid(), "wall_s": round(time.monotonic() - started, 3),
                           "totals": {stage: round(s, 3) for stage, s in totals.items()},
                           "functions": {name: {stage: [count, round(s, 4)] for stage, (count, s) in stages.items()}
                                         for name, stages in functions.items()}})
        with open(path, "a") as out:
            fcntl.flock(out, fcntl.LOCK_EX)  # processes of one suite share the file
            out.write(line + "\n")

    monitoring.register_event_duration_secs_listener(heard)
    atexit.register(write)

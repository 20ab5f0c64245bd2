"""Compiling a program once per machine: processes that compile the same program at the same time take turns.

`impulse launch` starts its actors together, and on a cold compilation cache each would compile the same rollout
side by side (on a 2-core CPU, minutes of compile done twice, each slower for the other). Here the first to start
compiling holds a lock named after the program (the hash of its lowered text) in the compilation cache's folder;
the others wait on it and then find the program in JAX's persistent cache, which they read back in a fraction of the
time. The program a process runs is always the one it lowered itself: the lock only orders the compiles, so a
program that is not in the cache (another program with the same hash, a cache that did not keep it) is compiled
as usual, after the wait. Without a compilation cache configured there is nothing to share and nothing is locked.
"""

from __future__ import annotations

import fcntl
import hashlib
import logging
import time
from pathlib import Path

import jax

log = logging.getLogger(__name__)

LOCKS_FOLDER = "compile-locks"
"""Beside the cached programs, in the compilation cache's folder: one empty lock file per program compiled."""


def lock_path(lowered: jax.stages.Lowered) -> Path | None:
    """The lock file of `lowered`'s program (named by the hash of its lowered text) in the compilation cache's
    folder, which is created; None without a compilation cache."""
    directory = jax.config.jax_compilation_cache_dir
    if not directory:
        return None
    locks = Path(directory) / LOCKS_FOLDER
    locks.mkdir(parents=True, exist_ok=True)
    return locks / f"{hashlib.sha256(lowered.as_text().encode()).hexdigest()[:32]}.lock"


def compile_once(lowered: jax.stages.Lowered, what: str) -> jax.stages.Compiled:
    """`lowered.compile()`, taking turns with any other process of this machine compiling the same program (module
    docstring); `what` names the program in the line that says this process waits."""
    path = lock_path(lowered)
    if path is None:
        return lowered.compile()
    with open(path, "a") as lock:
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            started = time.monotonic()
            log.info("another process is compiling the same program as %s: waiting to read it from the cache", what)
            fcntl.flock(lock, fcntl.LOCK_EX)
            log.info("waited %.1f s for %s's program", time.monotonic() - started, what)
        try:
            return lowered.compile()
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)

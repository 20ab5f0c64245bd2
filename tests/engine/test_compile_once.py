"""`engine.compile_once`: a process compiling a program another process is compiling waits for it, then compiles
(reading the program back from the cache) and runs it."""

from __future__ import annotations

import fcntl
import os
import subprocess
import sys
from pathlib import Path

from tests.support.paths import REPO

CHILD = """
import logging, sys
logging.basicConfig(level=logging.INFO, stream=sys.stdout, format="%(message)s")
from impulse.deploy.runtime.compile_cache import enable_compile_cache
enable_compile_cache()
import jax, jax.numpy as jnp
from impulse.engine.compile_once import compile_once, lock_path
lowered = jax.jit(lambda x: jnp.cumsum(jnp.sin(x) * 3.0)).lower(jnp.ones(7))
print("lock", lock_path(lowered), flush=True)
sys.stdin.readline()
compiled = compile_once(lowered, "the test's program")
print("result", float(compiled(jnp.ones(7))[-1]), flush=True)
"""


def line_with(stream, text: str) -> str:
    """The first line of `stream` holding `text` (JAX's own log lines come before it); fails at the stream's end."""
    for line in stream:
        if text in line:
            return line
    raise AssertionError(f"the child ended without saying {text!r}")


def test_a_second_compile_of_the_same_program_waits_for_the_first(tmp_path: Path) -> None:
    env = {**os.environ, "IMPULSE_CACHE_DIR": str(tmp_path / "cache")}
    child = subprocess.Popen([sys.executable, "-c", CHILD], cwd=REPO, env=env, text=True, stdin=subprocess.PIPE,
                             stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    try:
        assert child.stdout is not None and child.stdin is not None
        path = Path(line_with(child.stdout, "lock ").split()[1])
        assert path.parent == tmp_path / "cache" / "jax" / "compile-locks"
        with open(path, "a") as held:  # this process compiles the same program now
            fcntl.flock(held, fcntl.LOCK_EX)
            child.stdin.write("go\n")
            child.stdin.flush()
            line_with(child.stdout, "another process is compiling the same program as the test's program")
            assert child.poll() is None, "the child went on while the program's lock was held"
            fcntl.flock(held, fcntl.LOCK_UN)
        rest = child.stdout.read()
        assert child.wait(timeout=120) == 0, rest
        assert "waited" in rest and "result 17.67" in rest, rest  # the program ran: 7 x 3 sin(1)
    finally:
        if child.poll() is None:
            child.kill()

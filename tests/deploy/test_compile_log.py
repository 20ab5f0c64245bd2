"""The compile log (`deploy.runtime.compile_cache`, $IMPULSE_COMPILE_LOG): a process that enables the cache
appends one line at exit naming what it traced, lowered and compiled, and for how long."""

from __future__ import annotations

import json
import os
import subprocess
import sys

SCRIPT = """
from impulse.deploy.runtime.compile_cache import enable_compile_cache
enable_compile_cache()
import jax, jax.numpy as jnp
def doubled_sine(x):
    return jnp.sin(x) * 2
jax.jit(doubled_sine)(jnp.ones(3))
"""


def test_each_process_appends_its_compiles_by_function(tmp_path):
    log = tmp_path / "compiles.jsonl"
    env = {**os.environ, "IMPULSE_COMPILE_LOG": str(log), "IMPULSE_CACHE_DIR": str(tmp_path / "cache")}
    for _ in range(2):  # the second process reads the program back from the cache
        subprocess.run([sys.executable, "-c", SCRIPT], check=True, env=env, timeout=120)
    first, second = (json.loads(line) for line in log.read_text().splitlines())
    for line in (first, second):
        stages = line["functions"]["doubled_sine"]
        assert stages["trace"][0] == stages["lower"][0] == stages["compile"][0] == 1, stages
        assert line["totals"]["compile"] >= stages["compile"][1] > 0
    assert first["pid"] != second["pid"]

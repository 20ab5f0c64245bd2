"""Shared timing harness for our engine's benchmarks: one jitted scan of a vmapped function, warmed up, median
of repeats. The reference runner (run in Jax2D's own virtualenv) follows the same protocol."""

from __future__ import annotations

import json
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
import numpy as np

REPO = Path(__file__).resolve().parents[1]
# Kinetix's level files: the shared folder beside the checkout, or where $IMPULSE_KINETIX_LEVELS says (as for
# `impulse eval --levels kinetix:...`; on a lent GPU machine the shared folder does not travel, see docs/gpu.md).
LEVELS_DIR = Path(os.environ.get("IMPULSE_KINETIX_LEVELS") or REPO.parent / "shared" / "kinetix-levels")
DEFAULT_LEVELS = {"s": "s/h4_thrust_aim.json", "m": "m/h0_unicycle.json", "l": "l/h4_cartpole.json"}


def emit(record: dict[str, Any]) -> None:
    """Print one JSON line (the benchmarks' only stdout) and flush so piped readers see it at once."""
    print(json.dumps(record), flush=True)


def progress(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def environment() -> dict[str, str]:
    device = jax.devices()[0]
    return {"jax_version": jax.__version__, "backend": jax.default_backend(), "device": device.device_kind}


def time_jitted(fn: Callable[[], Any], repeats: int = 3) -> tuple[float, float]:
    """(compile seconds, median run seconds). Two warm-up calls: the first compiles; the second catches any
    recompilation from weak types changing after one call."""
    start = time.perf_counter()
    jax.block_until_ready(fn())
    jax.block_until_ready(fn())
    compile_s = time.perf_counter() - start
    runs = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn())
        runs.append(time.perf_counter() - start)
    return compile_s, float(np.median(runs))


def require_levels() -> Path:
    if not LEVELS_DIR.is_dir():
        raise SystemExit(f"Kinetix levels not found at {LEVELS_DIR} (the shared/ folder beside the checkout)")
    return LEVELS_DIR

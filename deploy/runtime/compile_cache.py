"""JAX's persistent compilation cache for every Impulse process, so a second start skips recompiling."""

from __future__ import annotations

from pathlib import Path


def enable_compile_cache() -> Path:
    """Keep compiled programs across runs (the training step takes tens of seconds to compile on CPU): in
    $IMPULSE_CACHE_DIR, else the checkout's ignored .cache/jax (shared with the tests), else ~/.cache/impulse."""
    import os

    import jax

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
    return directory

"""Settings for the whole test run.

JAX's persistent compilation cache lives under `<repo>/.cache/jax` (ignored by git), so a second `make test` on
the same machine, or CI after a developer's run, skips recompiling the engine's jitted functions; only
compilations slower than half a second are stored, which keeps the cache small.
"""

from __future__ import annotations

from pathlib import Path

import jax

REPO_ROOT = Path(__file__).resolve().parents[1]

jax.config.update("jax_compilation_cache_dir", str(REPO_ROOT / ".cache" / "jax"))
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)

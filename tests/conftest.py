"""Settings for the whole test run.

Each test folder keeps its shared helper modules beside its tests (`tests/engine/physics_sim.py`,
`tests/env/env_scenes.py`, ...); every folder is put on `sys.path` here, so the tests import them by name under
any pytest import mode. Helper module names are unique across folders for that reason.

JAX's persistent compilation cache lives under `<repo>/.cache/jax` (ignored by git), so a second `make test` on
the same machine, or CI after a developer's run, skips recompiling the engine's jitted functions; only
compilations slower than half a second are stored, which keeps the cache small.

`make test` runs the suite as two streams side by side (pytest-xdist, `-n 2 --dist loadgroup`): tests marked
`heavy` (they start processes of their own: launches, Zenoh sessions, viewers, training subprocesses; or train
for a while) run one after another on one worker, every other test runs in order on the other. Neither stream
compiles a program twice, and the CPU the heavy tests leave idle while their processes wait goes to the rest.
The marks balance the two streams (each about half of the suite's time on a 2-core machine).
"""

from __future__ import annotations

import sys
from pathlib import Path

import jax
import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
for _folder in [REPO_ROOT, *sorted(p for p in Path(__file__).resolve().parent.iterdir() if p.is_dir())]:
    if not _folder.name.startswith((".", "_")) and str(_folder) not in sys.path:
        sys.path.insert(0, str(_folder))

jax.config.update("jax_compilation_cache_dir", str(REPO_ROOT / ".cache" / "jax"))
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line("markers", "heavy: starts processes of its own or trains for a while (own stream)")


def pytest_itemcollected(item: pytest.Item) -> None:
    """Each test joins its stream as it is collected, before xdist reads the groups."""
    stream = "heavy" if item.get_closest_marker("heavy") else "light"
    item.add_marker(pytest.mark.xdist_group(stream))


@pytest.hookimpl(trylast=True)
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Under `--dist loadgroup` every test must carry its stream in its node id by now; if xdist could not tag them
    (it cannot under pytest 9), the streams would mix and the heavy tests run side by side, so stop instead."""
    if config.getoption("loadgroup", default=False) and any("@" not in item.nodeid for item in items):
        raise pytest.UsageError("pytest-xdist did not group the tests into their streams (pytest "
                                f"{pytest.__version__}); install the versions pyproject.toml's dev extra names")

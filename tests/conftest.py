"""Settings for the whole test run.

The folders mirror the rooms (`tests/engine/physics`, `tests/engine/env`, `tests/bus`, ...). Helpers shared by
tests live in one package, `tests.support` (scenes, level samples, launched processes, paths), imported by its
full name; pytest's `pythonpath` puts the checkout on `sys.path`, nothing else is added to it.

JAX's persistent compilation cache is the one every Impulse process uses (`deploy.runtime.compile_cache`, under
`<repo>/.cache/jax`, ignored by git), so the test processes and the processes they launch share what each compiled,
and a second `make test` on the same machine skips recompiling. Every program is stored, the small ones too: the
launched processes each run hundreds of them as they start.

`make test` runs the suite as three streams side by side (pytest-xdist, `-n 3 --dist loadgroup`): tests marked
`heavy` (they start processes of their own: launches, routers, viewers, training subprocesses; or train for a while)
run one after another on one worker; every other test runs in order on one of two more workers, the engine's and the
curriculum's tests on one, the rest on the other. A test that only opens Zenoh sessions on loopback in its own
process (the curriculum service's tests) is light: the heavy stream is the suite's longest, and those tests run as
well beside it (`LIGHT_STREAM_FILES` evens out the light streams). On a 2-core machine the heavy tests' processes
spend much of their time waiting (for updates, kills, timeouts), so two light streams keep both cores busy where one
would leave one idle. A stream never compiles a program twice, and streams share what they compile through the
compilation cache above. The split balances the two light streams (each about half of their CPU time).
"""

from __future__ import annotations

import pytest

from impulse.deploy.runtime.compile_cache import enable_compile_cache

enable_compile_cache()


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line("markers", "heavy: starts processes of its own or trains for a while (own stream)")


ENGINE_STREAM = ("tests/engine/", "tests/curriculum/")
"""Test folders whose light tests form the second light stream."""
LIGHT_STREAM_FILES = ("tests/curriculum/test_batch_sfl_service.py",)
"""Files of those folders that run in the first light stream instead, to keep the two light streams even: the
curriculum service's tests left the heavy stream (about 220 s in all), half to each (benchmarks/RESULTS.md, "Where
the clean-clone suite's time goes")."""


def pytest_itemcollected(item: pytest.Item) -> None:
    """Each test joins its stream as it is collected, before xdist reads the groups."""
    if item.get_closest_marker("heavy"):
        stream = "heavy"
    elif item.nodeid.startswith(ENGINE_STREAM) and not item.nodeid.startswith(LIGHT_STREAM_FILES):
        stream = "light-engine"
    else:
        stream = "light"
    item.add_marker(pytest.mark.xdist_group(stream))


@pytest.hookimpl(trylast=True)
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Under `--dist loadgroup` every test must carry its stream in its node id by now; if xdist could not tag them
    (it cannot under pytest 9), the streams would mix and the heavy tests run side by side, so stop instead."""
    if config.getoption("loadgroup", default=False) and any("@" not in item.nodeid for item in items):
        raise pytest.UsageError("pytest-xdist did not group the tests into their streams (pytest "
                                f"{pytest.__version__}); install the versions pyproject.toml's dev extra names")

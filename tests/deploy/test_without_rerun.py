"""A run with monitoring off needs no rerun-sdk: the services' modules import it only once a monitor is opened
(deploy/runtime/monitoring.py), which is what lets a machine without it (a lent GPU machine, docs/gpu.md) run them.
And importing the services' modules starts no JAX backend, which the settings each applies after its imports need."""

from __future__ import annotations

import re
import subprocess
import sys

import pytest

from tests.support.launch_procs import REPO

pytestmark = pytest.mark.heavy

ENTRY_MODULES = tuple(f"impulse.{name}" for name in (
    "deploy.cli", "deploy.commands.services", "deploy.commands.curriculum", "deploy.commands.curriculum_service",
    "deploy.commands.evaluator", "deploy.commands.recorder", "deploy.commands.train", "deploy.commands.launch",
    "deploy.runtime.monitoring", "actors.process", "learner.service", "curriculum.service", "benchmarks.distributed"))
RERUN_MODULES = sorted(f"impulse.monitor.{path.stem}" for path in (REPO / "monitor").glob("*.py")
                       if re.search(r"^(import|from) rerun\b", path.read_text(), re.MULTILINE))
"""The monitor modules that import rerun-sdk as they load (drawing and streaming)."""


def test_service_modules_import_without_rerun() -> None:
    blocked = "import sys; sys.modules['rerun'] = None\n" + "".join(f"import {m}\n" for m in ENTRY_MODULES)
    # No drawing or streaming code may load (the scalar sinks, PNG and video writers need no rerun).
    assert "impulse.monitor.stream" in RERUN_MODULES
    blocked += f"assert not set(sys.modules) & set({RERUN_MODULES!r}), 'a Rerun module was imported'\n"
    # Nor may importing them start JAX's backend: a service sets the GPUs it sees, its memory share and its
    # multi-host group after its imports and before JAX first touches a device.
    blocked += ("from jax._src import xla_bridge\n"
                "assert not xla_bridge.backends_are_initialized(), 'importing started a JAX backend'\n")
    result = subprocess.run([sys.executable, "-c", blocked], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr[-2000:]
    # The same check fails where rerun is needed: opening a monitor.
    opened = blocked + "import impulse.monitor.stream\n"
    result = subprocess.run([sys.executable, "-c", opened], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert result.returncode != 0 and "rerun" in result.stderr

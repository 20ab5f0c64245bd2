"""A run with monitoring off needs no rerun-sdk: the services' modules import it only once a monitor is opened
(deploy/runtime/monitoring.py), which is what lets a machine without it (a lent GPU machine, docs/gpu.md) run them."""

from __future__ import annotations

import subprocess
import sys

import pytest

from tests.support.launch_procs import REPO

pytestmark = pytest.mark.heavy

ENTRY_MODULES = tuple(f"impulse.{name}" for name in (
    "deploy.cli", "deploy.commands.services", "deploy.commands.curriculum", "deploy.commands.launch",
    "deploy.runtime.monitoring", "actors.process", "learner.service", "curriculum.service", "benchmarks.distributed"))


def test_service_modules_import_without_rerun() -> None:
    blocked = "import sys; sys.modules['rerun'] = None\n" + "".join(f"import {m}\n" for m in ENTRY_MODULES)
    # Only the [monitor] config section may load: a dataclass, no drawing or streaming code.
    blocked += ("assert not [m for m in sys.modules if m.startswith('impulse.monitor.') "
                "and m != 'impulse.monitor.config'], 'a monitor module was imported'\n")
    result = subprocess.run([sys.executable, "-c", blocked], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr[-2000:]
    # The same check fails where rerun is needed: opening a monitor.
    opened = blocked + "import impulse.monitor.stream\n"
    result = subprocess.run([sys.executable, "-c", opened], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert result.returncode != 0 and "rerun" in result.stderr

"""The learner's PPO update sharded over 2 and 4 simulated CPU devices gives the parameters of the single-device
update on the same batch. XLA fixes the device count when it starts, so the comparison runs in a process of its own
(`tests/support/sharded_update_check.py`)."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from tests.support.paths import REPO

pytestmark = pytest.mark.heavy

PARAM_TOLERANCE = 1e-6
"""Float32 summation order only: measured differences are about 3e-8, against parameter changes of about 1e-3."""


@pytest.fixture(scope="module")
def comparisons() -> dict[int, dict]:
    env = {**os.environ, "XLA_FLAGS": "--xla_force_host_platform_device_count=4", "JAX_PLATFORMS": "cpu",
           "PYTHONPATH": str(REPO)}
    done = subprocess.run([sys.executable, "-m", "tests.support.sharded_update_check", "2", "4"], env=env, cwd=REPO,
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    rows = [json.loads(line) for line in done.stdout.splitlines() if line.startswith("{")]
    return {row["devices"]: row for row in rows}


@pytest.mark.parametrize("devices", [2, 4])
def test_sharded_update_matches_single_device(comparisons: dict[int, dict], devices: int) -> None:
    row = comparisons[devices]
    print(json.dumps(row))
    assert row["visible_devices"] == 4
    assert row["envs_per_device"] == [16 // devices]  # each device holds its share of the environments
    assert row["all_reduce"]  # the gradient is summed across devices, not computed on one
    assert row["params_moved_by_update"] > 100 * PARAM_TOLERANCE  # the comparison is not between unchanged params
    assert row["param_max_abs_error"] < PARAM_TOLERANCE
    assert row["metric_max_abs_error"] < 1e-5
    assert row["version"] == 4

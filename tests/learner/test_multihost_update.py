"""The learner's PPO update over two learner processes on loopback (`learner.hosts = 2`, `jax.distributed` with
gloo collectives on CPU), each holding half of the batch's environments, gives the parameters of the
single-process update on the whole batch. Each process runs `tests/support/multihost_update_check.py`."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from tests.support.launch_procs import free_port
from tests.support.paths import REPO

pytestmark = pytest.mark.heavy

PARAM_TOLERANCE = 1e-6
"""Float32 summation order only, as for several devices in one process (test_sharded_update.py)."""


@pytest.fixture(scope="module")
def rows() -> list[dict]:
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "PYTHONPATH": str(REPO)}
    env.pop("XLA_FLAGS", None)
    coordinator = f"127.0.0.1:{free_port()}"
    processes = [subprocess.Popen([sys.executable, "-m", "tests.support.multihost_update_check", str(index), "2",
                                   coordinator], env=env, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                  text=True) for index in (0, 1)]
    outputs = []
    for process in processes:
        try:
            out, err = process.communicate(timeout=300)
        except subprocess.TimeoutExpired:
            for other in processes:
                other.kill()
            raise
        assert process.returncode == 0, err[-3000:]
        outputs.append(out)
    return [json.loads(line) for out in outputs for line in out.splitlines() if line.startswith("{")]


def test_two_learner_processes_update_as_one(rows: list[dict]) -> None:
    print("\n".join(json.dumps(row) for row in rows))
    assert [row["index"] for row in rows] == [0, 1]
    for row in rows:
        assert row["processes"] == 2 and row["mesh_devices"] == 2
        assert row["local_envs"] == [8]  # each process holds its own half of the 16 environments
        assert row["all_reduce"]  # the gradient is summed across the processes
        assert row["params_moved_by_update"] > 100 * PARAM_TOLERANCE
        assert row["param_max_abs_error"] < PARAM_TOLERANCE  # ... to the single-process update's parameters
        assert row["metric_max_abs_error"] < 1e-5
        assert row["version"] == 4


def test_the_group_combines_what_each_process_saw(rows: list[dict]) -> None:
    for row in rows:
        assert row["episodes"] == 1 + 2  # episode counts added up over the processes
        assert row["policy_lag"] == 1  # the oldest behaviour version of the two (3 and 2) against version 3
        assert row["agreed_have_batch"] == [True, False]  # every process sees every process's flag, in order
        assert row["broadcast_seed"] == 100  # the leader's value reaches everyone

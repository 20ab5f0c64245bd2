"""A learner on two processes (`learner.hosts = 2`) in a real run: started by hand as the docs say (the leader is the
bus hub, `--host-index 0` and `1`), with two actors, real zenoh on loopback and `jax.distributed` over gloo.
Each learner process trains on its own actor's batches, the two agree on every update, the leader alone writes
metrics and checkpoints, and a Ctrl-C to the other process stops both in order, the leader checkpointing the
update the group reached. (The update itself is compared with one process's in test_multihost_update.py.)"""

from __future__ import annotations

import os
import signal
import subprocess
import sys

import pytest

from tests.support.launch_procs import QUICK_LAUNCH, REPO, TINY_BATCH, free_port, last_update, metrics, tail, wait_for

pytestmark = pytest.mark.heavy

STEPS_PER_BATCH = 8 * 8  # TINY_BATCH: one actor's batch


def test_two_learner_processes_share_the_actors_and_stop_together(tmp_path):
    run_dir = tmp_path / "hosts"
    common = ["--config", str(QUICK_LAUNCH), f"run_dir={run_dir}", "name=hosts",
              f"bus.hub=tcp/127.0.0.1:{free_port()}", "learner.hosts=2",
              f"learner.coordinator=127.0.0.1:{free_port()}", "total_env_steps=100000000",
              "checkpoint.every_updates=1000", *TINY_BATCH]
    env = {**os.environ, "IMPULSE_CACHE_DIR": str(REPO / ".cache"), "PYTHONUNBUFFERED": "1"}
    env.pop("XLA_FLAGS", None)
    processes: dict[str, subprocess.Popen] = {}
    logs = {}

    def start(name: str, *words: str) -> None:
        logs[name] = tmp_path / f"{name}.log"
        with logs[name].open("wb") as out:
            processes[name] = subprocess.Popen([sys.executable, "-m", "impulse.deploy.cli", *words, *common],
                                               cwd=REPO, env=env, stdout=out, stderr=subprocess.STDOUT)

    try:
        start("leader", "learner", "--hub", "--host-index", "0")
        start("other", "learner", "--host-index", "1")
        start("actor-0", "actor", "--index", "0")
        start("actor-1", "actor", "--index", "1")
        wait_for(lambda: last_update(run_dir) >= 3, 300, "the group's first updates", processes["leader"],
                 logs["leader"])
        processes["other"].send_signal(signal.SIGINT)  # the process that is not the leader stops the group
        for name in ("other", "leader"):
            assert processes[name].wait(timeout=120) == 0, tail(logs[name])
    finally:
        for process in processes.values():
            if process.poll() is None:
                process.kill()
                process.wait(timeout=30)

    leader_log, other_log = logs["leader"].read_text(), logs["other"].read_text()
    assert "learner process 1 of 2 joined: 2 devices in the group, 1 here" in other_log
    rows = metrics(run_dir)
    updates = [row["update"] for row in rows]
    assert updates == list(range(1, len(rows) + 1)), "the leader writes each update once; the other writes none"
    # An update trains on one batch of each process: both actors' steps, counted once.
    assert [row["env_steps"] for row in rows] == [2 * STEPS_PER_BATCH * update for update in updates]
    assert {row["actor"] for row in rows} == {0.0}, "the leader trains on actor-0's batches, the other on actor-1's"
    stopped_at = updates[-1]
    assert f"learner process 1 of 2 stopped at update {stopped_at} of" in other_log
    assert f"learner stopped at update {stopped_at} of" in leader_log, "the leader stopped with the group"
    assert sorted(int(p.name) for p in (run_dir / "checkpoints").iterdir()) == [stopped_at], (
        "the leader checkpointed the update the group reached, and nothing else did")

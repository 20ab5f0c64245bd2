"""A deliberately slow learner: actors (configured to drop their oldest batch) keep rolling out without flooding
anything; drops are counted and every process's resident memory stays flat. Then Ctrl-C stops the run in order
and the learner's final checkpoint holds its last update."""

from __future__ import annotations

import os
import signal
import time

from launch_procs import (
    StatusWatcher,
    free_port,
    last_update,
    rss_mib,
    service_pids,
    start_launch,
    tail,
    wait_for,
)

from deploy.config import resolve_config
from learner.checkpoint import Checkpointer
from learner.config import TrainConfig

WATCH_S = 24.0
SAMPLE_S = 2.0
TREND_LIMIT_MIB = 48.0
"""The learner's resident memory swings by about 80 MiB within each update (one batch in flight, update
temporaries), so flatness is judged on peaks: the later half's peak may not exceed the earlier half's by more."""


def test_slow_learner_back_pressure_keeps_memory_flat_and_ctrl_c_checkpoints(tmp_path):
    run_dir = tmp_path / "slow"
    port = free_port()
    launch, log = start_launch(run_dir, port, "learner.slow_down_s=1.5", "actors.when_no_credit=drop_oldest",
                               "actors.credits=1", "total_env_steps=40960000", "checkpoint.every_updates=1000")
    watcher = StatusWatcher(run_dir.name, port)
    try:
        wait_for(lambda: last_update(run_dir) >= 3, 400, "the first updates", launch, log)
        pids = {"learner": service_pids(run_dir, "learner")[0],
                **{f"actor-{i}": service_pids(run_dir, "actor", i)[0] for i in (0, 1)}}
        drops_before = sum(watcher.poll().get(f"actor-{i}", {}).get("dropped_no_credit", 0) for i in (0, 1))
        samples: dict[str, list[float]] = {name: [] for name in pids}
        for _ in range(int(WATCH_S / SAMPLE_S)):
            for name, pid in pids.items():
                samples[name].append(rss_mib(pid))
            time.sleep(SAMPLE_S)
        statuses = watcher.poll()
        half = len(samples["learner"]) // 2
        before = {name: max(values[:half]) for name, values in samples.items()}
        after = {name: max(values[half:]) for name, values in samples.items()}
        for name in pids:
            assert after[name] - before[name] < TREND_LIMIT_MIB, (name, samples[name])
        drops = sum(statuses[f"actor-{i}"]["dropped_no_credit"] for i in (0, 1))
        assert drops - drops_before >= 3, f"actors should have replaced held-back batches: {statuses}"
        assert all(statuses[f"actor-{i}"]["in_flight"] <= 1 for i in (0, 1)), statuses
        assert statuses["learner"]["queue"] <= 2, statuses["learner"]
        print(f"peak RSS MiB, first half {before}, second half {after}; batches dropped by actors {drops}")

        # Ctrl-C: actors stop first, then the learner checkpoints its last update and exits.
        launch.send_signal(signal.SIGINT)
        assert launch.wait(timeout=240) == 0, tail(log)
    finally:
        watcher.close()
        if launch.poll() is None:
            launch.kill()
        for role in ("learner", "actor"):
            for pid in service_pids(run_dir, role):
                os.kill(pid, signal.SIGKILL)
    config = resolve_config(TrainConfig, run_dir / "config.toml")
    with Checkpointer(run_dir / "checkpoints", config.checkpoint) as checkpoints:
        assert checkpoints.latest_step() == last_update(run_dir), "the final checkpoint holds the last update"
    assert not service_pids(run_dir, "learner") and not service_pids(run_dir, "actor")
    assert "stopping the learner" in log.read_text()

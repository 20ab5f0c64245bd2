"""A distributed run with an exploding learning rate (a real `impulse launch`: a learner and one actor over zenoh
on loopback) skips every update, counts them in metrics.jsonl, publishes and checkpoints only finite parameters,
and stops after `ppo.max_non_finite_updates` in a row with one line naming the cause, instead of stalling with
actors that refuse the weights and a learner that drops every batch as stale. The fused
run's side is tests/learner/test_non_finite.py."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from impulse.deploy.config import resolve_config
from impulse.deploy.run_config import RunConfig
from impulse.engine.env.spec import env_from_config
from impulse.learner.agent import make_agent
from impulse.learner.checkpoint import TRAIN, Checkpointer
from impulse.learner.non_finite import SKIPPED_COLUMN
from impulse.learner.update import TrainState, make_optimizer
from tests.support.launch_procs import TINY_BATCH, free_port, metrics, start_launch, stop_launch, tail

pytestmark = pytest.mark.heavy


def test_an_exploding_learning_rate_stops_a_launch_with_one_clear_line(tmp_path) -> None:
    run_dir = tmp_path / "exploding"
    launch, log_path = start_launch(run_dir, free_port(), "actors.num_actors=1", "checkpoint.every_updates=2",
                                    "eval.attempts=0", "ppo.learning_rate=1e38", "ppo.max_grad_norm=1e38",
                                    *TINY_BATCH)
    try:
        code = launch.wait(timeout=400)
    finally:
        stop_launch(launch, run_dir)
    output = tail(log_path, 400)
    assert code == 1, output
    stopped = [line for line in output.splitlines() if line.startswith("impulse launch: stopped the run")]
    assert len(stopped) == 1, output
    assert "learner cannot run with this configuration" in stopped[0]
    assert "were not finite" in stopped[0] and "ppo.learning_rate=1e+38" in stopped[0], stopped[0]
    assert 'File "' not in stopped[0] and "Traceback" not in stopped[0]

    rows = metrics(run_dir)  # kept: the run trained (if only to skip), so its directory is not taken back
    assert [row[SKIPPED_COLUMN] for row in rows] == [1.0, 2.0, 3.0, 4.0, 5.0], rows
    config = resolve_config(RunConfig, run_dir / "config.toml")
    spec, _ = env_from_config(config.env)
    agent = make_agent(config.network, spec)
    params = agent.init(jax.random.PRNGKey(config.seed))
    template = TrainState(params, make_optimizer(config.ppo, config.num_updates).init(params), np.int32(0))
    with Checkpointer(run_dir / "checkpoints", config.checkpoint) as checkpoints:
        steps = checkpoints.all_steps()
        assert steps == [2, 4], steps  # the cadence's: the learner stops by an error, with no last save
        for step in steps:
            restored = checkpoints.restore({TRAIN: template}, step, set_aside=False)
            leaves = jax.tree.leaves(restored.items[TRAIN].params)
            assert all(np.isfinite(leaf).all() for leaf in leaves)
            # The starting policy: every update was undone.
            assert all(np.array_equal(a, b) for a, b in zip(leaves, jax.tree.leaves(params), strict=True))

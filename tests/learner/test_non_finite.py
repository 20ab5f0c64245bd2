"""An update that is not finite is skipped, counted and, after `ppo.max_non_finite_updates` in a row, stops the
run with one error naming the cause; a non-finite parameter tree is never checkpointed or exported.
The fused run here is a real `impulse train` (in this process) with an exploding learning rate;
the distributed run is tests/deploy/test_launch_non_finite.py."""

from __future__ import annotations

import json
import logging

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from impulse.deploy.cli import main
from impulse.deploy.config import resolve_config
from impulse.deploy.run_config import RunConfig
from impulse.engine.pytree import count_non_finite
from impulse.learner.checkpoint import TRAIN, Checkpointer
from impulse.learner.config import PPOConfig
from impulse.learner.non_finite import (
    SKIPPED_COLUMN,
    NonFiniteGuard,
    NonFiniteParameters,
    NonFiniteUpdates,
    refuse_non_finite,
)
from impulse.learner.run import RunError, build, export_policy
from impulse.learner.update import keep_if_finite
from tests.support.paths import REPO

QUICK = REPO / "configs" / "quick-cpu.toml"
EXPLODING = ["ppo.learning_rate=1e38", "ppo.max_grad_norm=1e38"]
TINY = ["ppo.num_envs=8", "ppo.num_steps=8", "ppo.num_minibatches=1", "ppo.update_epochs=1",
        "total_env_steps=1280", "checkpoint.every_updates=2", "eval.attempts=0"]


def test_a_non_finite_update_is_undone_as_a_whole():
    old = ({"w": jnp.ones(3)}, {"mu": jnp.zeros(3)})
    poisoned = ({"w": jnp.array([1.0, jnp.nan, 2.0])}, {"mu": jnp.ones(3)})
    params, opt_state, skipped = keep_if_finite(poisoned, old, jnp.asarray(True))
    assert float(skipped) == 1.0 and (params["w"] == 1).all() and (opt_state["mu"] == 0).all()
    fine = ({"w": jnp.full(3, 2.0)}, {"mu": jnp.ones(3)})
    params, opt_state, skipped = keep_if_finite(fine, old, jnp.asarray(True))
    assert float(skipped) == 0.0 and (params["w"] == 2).all() and (opt_state["mu"] == 1).all()
    params, _, skipped = keep_if_finite(fine, old, jnp.asarray(False))  # e.g. a NaN loss, finite parameters
    assert float(skipped) == 1.0 and (params["w"] == 1).all()


def test_the_guard_counts_resets_and_stops_after_the_limit(caplog):
    guard = NonFiniteGuard(PPOConfig(learning_rate=1e38, max_non_finite_updates=3))
    guard.note(1, {"non_finite": 1.0})
    guard.check()
    guard.note(2, {"non_finite": 0.0, "total_loss": 0.3})
    assert (guard.skipped, guard.in_a_row) == (1, 0)
    guard.note(3, {"non_finite": 1.0})
    guard.note(4, {"non_finite": 1.0})
    guard.note(5, {"non_finite": 1.0})
    with pytest.raises(NonFiniteUpdates) as stopped:
        guard.check()
    message = str(stopped.value)
    assert "updates 3 to 5" in message and "update 2" in message and "ppo.learning_rate=1e+38" in message
    assert guard.columns() == {SKIPPED_COLUMN: 4.0}
    with caplog.at_level(logging.WARNING, "impulse.learner"):
        for update in range(10, 20):
            guard.note(update, {"non_finite": 0.0, "total_loss": 1e14})
    diverging = [r for r in caplog.records if "diverging" in r.getMessage()]
    assert len(diverging) == 1 and "1e+14" in diverging[0].getMessage()


def test_refuse_non_finite_names_what_and_how_many():
    refuse_non_finite({"a": np.ones(4, np.float32), "n": np.arange(3)}, "checkpoint 1")
    with pytest.raises(NonFiniteParameters, match=r"refusing checkpoint 7: 2 of 5 parameters"):
        refuse_non_finite({"a": np.array([1, np.inf, np.nan], np.float32), "b": np.ones(2)}, "checkpoint 7")


def test_an_exploding_learning_rate_stops_impulse_train_with_no_non_finite_checkpoint(tmp_path, capsys):
    run_dir = tmp_path / "run"
    code = main(["train", "--config", str(QUICK), f"run_dir={run_dir}", *TINY, *EXPLODING])
    err = capsys.readouterr().err
    assert code == 1, err
    lines = [line for line in err.splitlines() if line.startswith("impulse train:")]
    assert len(lines) == 1 and "Traceback" not in err, err
    assert "were skipped because their loss, gradients or parameters were not finite" in lines[0], lines[0]
    assert "ppo.learning_rate=1e+38" in lines[0] and "ppo.max_grad_norm=1e+38" in lines[0]
    rows = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    assert [row[SKIPPED_COLUMN] for row in rows] == [1.0, 2.0, 3.0, 4.0, 5.0], rows  # every update skipped
    assert all(row["non_finite"] == 1.0 for row in rows)

    # Every checkpoint the run wrote (updates 2 and 4) holds its starting parameters, all finite.
    config = resolve_config(RunConfig, run_dir / "config.toml")
    trainer, _, _, levels = build(config)
    start = jax.jit(trainer.init)(jax.random.PRNGKey(config.seed), levels).train
    with Checkpointer(run_dir / "checkpoints", config.checkpoint) as checkpoints:
        assert checkpoints.all_steps() == [2, 4]
        for step in checkpoints.all_steps():
            restored = checkpoints.restore({TRAIN: start}, step, set_aside=False)
            params = restored.items[TRAIN].params
            assert count_non_finite(params)[0] == 0
            assert all(np.array_equal(a, b) for a, b in zip(jax.tree.leaves(params), jax.tree.leaves(start.params),
                                                             strict=True))
            assert restored.counters[SKIPPED_COLUMN] == step

    # An export refuses a checkpoint whose parameters are not finite (one written before this guard existed).
    poisoned = start._replace(params=jax.tree.map(lambda x: x * jnp.nan, start.params))
    old_dir = tmp_path / "old"
    with Checkpointer(old_dir / "checkpoints", config.checkpoint) as checkpoints:
        checkpoints.save(3, {TRAIN: poisoned}, {"update": 3, "env_steps": 192}, "")
    with pytest.raises(RunError, match="refusing to export checkpoint 3: .* parameters are not finite"):
        export_policy(config, old_dir, tmp_path / "exported", "")

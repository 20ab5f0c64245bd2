"""A trained policy shipped and fine-tuned: `impulse export` writes a run's policy alone into a small directory
(config.toml, agent.json, a checkpoint with only the `train` item), `impulse eval` scores it, and `impulse train
--init-from` starts a new run from exactly its parameters, with the source's network whatever the command line
says (real `impulse` processes, real orbax checkpoints). The source run's metrics also reach TensorBoard (read
back with TensorBoard's reader), equal to its metrics.jsonl, and `impulse tensorboard` writes the same event files
from that metrics.jsonl."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import jax
import numpy as np
import pytest
from impulse.deploy.cli import main
from impulse.deploy.config import resolve_config
from impulse.deploy.run_config import RunConfig
from impulse.learner.checkpoint import TRAIN, Checkpointer
from impulse.learner.run import build

from tests.support.paths import REPO
from tests.support.scalars import expected_points, metrics_rows, tensorboard_points

pytestmark = pytest.mark.heavy

QUICK = REPO / "configs" / "quick-cpu.toml"
# The README's quick learner at a quarter of its batch (32 envs x 32 steps), 2 updates, no final evaluation.
SETTINGS = ["--config", str(QUICK), f"total_env_steps={2 * 32 * 32}", "ppo.num_envs=32", "ppo.num_steps=32",
            "ppo.num_minibatches=2", "checkpoint.every_updates=2", "eval.attempts=0"]


def impulse(*args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "IMPULSE_CACHE_DIR": str(REPO / ".cache")}
    return subprocess.run([sys.executable, "-m", "impulse.deploy.cli", *args], cwd=REPO, env=env, text=True,
                          stdout=subprocess.PIPE, stderr=subprocess.STDOUT, timeout=600)


def policy_params(run_dir: Path):
    config = resolve_config(RunConfig, run_dir / "config.toml")
    trainer, _, _, levels = build(config)
    template = jax.eval_shape(trainer.init, jax.random.PRNGKey(config.seed), levels).train
    with Checkpointer(run_dir / "checkpoints", config.checkpoint) as checkpoints:
        restored = checkpoints.restore({TRAIN: template})
    return restored.items[TRAIN].params, restored.counters


def same_tree(a, b) -> bool:
    return all(np.array_equal(x, y) for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True))


def test_export_eval_and_fine_tune(tmp_path):
    source = tmp_path / "source"
    trained = impulse("train", f"run_dir={source}", *SETTINGS)
    assert trained.returncode == 0, trained.stdout

    # Its metrics, as TensorBoard holds them: the metrics.jsonl rows, one point per column and update.
    rows = metrics_rows(source / "metrics.jsonl")
    assert [row["env_steps"] for row in rows] == [32 * 32, 2 * 32 * 32]
    expected = expected_points(rows)
    assert {"update", "episodes", "policy_loss", "entropy"} <= set(expected)
    live, wall = tensorboard_points(source / "tensorboard")
    assert live == expected
    assert wall == {row["env_steps"]: pytest.approx(row["time_s"]) for row in rows}
    copy = tmp_path / "copy"
    copy.mkdir()
    (copy / "metrics.jsonl").write_text((source / "metrics.jsonl").read_text())
    assert main(["tensorboard", str(copy)]) == 0
    assert tensorboard_points(copy / "tensorboard") == (live, wall)

    shipped = tmp_path / "shipped"
    exported = impulse("export", "--checkpoint", str(source), "--out", str(shipped), "--note", "commit=abc123")
    assert exported.returncode == 0, exported.stdout
    agent = json.loads((shipped / "agent.json").read_text())
    assert agent["env_steps"] == 2 * 32 * 32 and agent["commit"] == "abc123", agent
    [step_dir] = (shipped / "checkpoints").iterdir()
    assert {p.name for p in step_dir.iterdir() if p.is_dir()} >= {"train"}
    assert not {"envs", "curriculum"} & {p.name for p in step_dir.iterdir()}, "only the policy is shipped"
    source_params, _ = policy_params(source)
    shipped_params, counters = policy_params(shipped)
    assert same_tree(source_params, shipped_params) and counters["update"] == 2

    scored = impulse("eval", "--checkpoint", str(shipped), "--levels", "handmade:s_easy_car_right",
                     "--attempts", "2")
    assert scored.returncode == 0 and "s_easy_car_right" in scored.stdout, scored.stdout

    # A fine-tuning run: the source's network (the command line's width is overridden) and its exact parameters.
    # One update at a negligible learning rate leaves them where the run started: the shipped policy's (a run
    # started from a fresh network would sit at its initial parameters, 2 updates away).
    tuned = tmp_path / "tuned"
    fine = impulse("train", "--init-from", str(shipped), f"run_dir={tuned}", *SETTINGS, "network.width=32",
                   "ppo.learning_rate=1e-30", "--updates", "1")
    assert fine.returncode == 0, fine.stdout
    assert "fine-tuning the policy of" in fine.stdout, fine.stdout
    assert resolve_config(RunConfig, tuned / "config.toml").network.width == 64
    tuned_params, tuned_counters = policy_params(tuned)
    assert tuned_counters["init_from_env_steps"] == 2 * 32 * 32 and tuned_counters["update"] == 1, tuned_counters
    assert all(np.allclose(x, y, rtol=0, atol=1e-12) for x, y in zip(jax.tree.leaves(tuned_params),
                                                                     jax.tree.leaves(shipped_params), strict=True))

    refused = impulse("train", "--init-from", str(tmp_path / "nowhere"), f"run_dir={tmp_path / 'x'}", *SETTINGS)
    assert refused.returncode == 2 and "--init-from" in refused.stdout and "config.toml" in refused.stdout, (
        refused.stdout)

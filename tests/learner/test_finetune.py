"""A trained policy shipped and fine-tuned: `impulse export` writes a run's policy alone into a small directory
(config.toml, agent.json, a checkpoint with only the `train` item), `impulse eval` scores it, and `impulse train
--init-from` and `impulse launch --init-from` start new runs from its parameters, with the source's network
whatever the command line says (real `impulse train`, `impulse launch` and `impulse eval` processes, the other
commands called in this process; real orbax checkpoints).
The source run's metrics also reach TensorBoard (read back with TensorBoard's reader), equal to its metrics.jsonl,
and `impulse tensorboard` writes the same event files from that metrics.jsonl.

Both training runs use configs/quick-cpu.toml's own batch and learning rate, so they run the training step that
tests/learner/test_learns.py compiles (one program through the compilation cache, not three)."""

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
from tests.support.launch_procs import TINY_BATCH, free_port
from tests.support.paths import REPO
from tests.support.scalars import expected_points, metrics_rows, tensorboard_points

pytestmark = pytest.mark.heavy

QUICK = REPO / "configs" / "quick-cpu.toml"
STEPS = 64 * 64
"""Env steps per update of the README's quick learner (64 envs x 64 steps)."""
# The README's quick learner, 2 updates, no final evaluation.
SETTINGS = ["--config", str(QUICK), f"total_env_steps={2 * STEPS}", "checkpoint.every_updates=2", "eval.attempts=0"]
TUNE_SEED = 1
"""The fine-tuning run's seed: another than the source's, so that a run that ignored --init-from would start from
a network of its own, far from the source's (the seed reaches the program as data: the same compiled step)."""


def impulse(*args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "IMPULSE_CACHE_DIR": str(REPO / ".cache")}
    return subprocess.run([sys.executable, "-m", "impulse.deploy.cli", *args], cwd=REPO, env=env, text=True,
                          stdout=subprocess.PIPE, stderr=subprocess.STDOUT, timeout=600)


class Built:
    """A run's config, trainer and training levels, as `impulse train` builds them from its config.toml."""

    def __init__(self, run_dir: Path):
        self.config = resolve_config(RunConfig, run_dir / "config.toml")
        self.trainer, _, _, self.levels = build(self.config)

    def train_template(self):
        return jax.eval_shape(self.trainer.init, jax.random.PRNGKey(self.config.seed), self.levels).train


def policy_params(run_dir: Path, template):
    """The policy of the run's newest checkpoint, and its counters (`template`: a train state of its network)."""
    config = resolve_config(RunConfig, run_dir / "config.toml")
    with Checkpointer(run_dir / "checkpoints", config.checkpoint) as checkpoints:
        restored = checkpoints.restore({TRAIN: template})
    return restored.items[TRAIN].params, restored.counters


def same_tree(a, b) -> bool:
    return all(np.array_equal(x, y) for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True))


def max_distance(a, b) -> float:
    return max(float(np.max(np.abs(np.asarray(x) - np.asarray(y))))
               for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True))


def test_export_eval_and_fine_tune(tmp_path, capsys):
    source = tmp_path / "source"
    trained = impulse("train", f"run_dir={source}", *SETTINGS)
    assert trained.returncode == 0, trained.stdout

    # Its metrics, as TensorBoard holds them: the metrics.jsonl rows, one point per column and update.
    rows = metrics_rows(source / "metrics.jsonl")
    assert [row["env_steps"] for row in rows] == [STEPS, 2 * STEPS]
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
    capsys.readouterr()
    assert main(["export", "--checkpoint", str(source), "--out", str(shipped), "--note", "commit=abc123"]) == 0, (
        capsys.readouterr())
    agent = json.loads((shipped / "agent.json").read_text())
    assert agent["env_steps"] == 2 * STEPS and agent["commit"] == "abc123", agent
    [step_dir] = (shipped / "checkpoints").iterdir()
    assert {p.name for p in step_dir.iterdir() if p.is_dir()} >= {"train"}
    assert not {"envs", "curriculum"} & {p.name for p in step_dir.iterdir()}, "only the policy is shipped"
    built = Built(source)
    template = built.train_template()  # the network of the source, the shipped policy and the fine-tuning run
    source_params, _ = policy_params(source, template)
    shipped_params, counters = policy_params(shipped, template)
    assert same_tree(source_params, shipped_params) and counters["update"] == 2

    scored = impulse("eval", "--checkpoint", str(shipped), "--levels", "handmade:s_easy_car_right",
                     "--attempts", "2")
    assert scored.returncode == 0 and "s_easy_car_right" in scored.stdout, scored.stdout

    # A fine-tuning run: the source's network (the command line's width is overridden) and its parameters, under
    # another seed. One update (16 Adam steps of about the learning rate, 3e-4, each) moves no parameter by 0.01:
    # it sits by the shipped policy, while a fresh network of its seed would sit about 1 away (checked below).
    tuned = tmp_path / "tuned"
    fine = impulse("train", "--init-from", str(shipped), f"run_dir={tuned}", *SETTINGS, "network.width=32",
                   f"seed={TUNE_SEED}", "--updates", "1")
    assert fine.returncode == 0, fine.stdout
    assert "fine-tuning the policy of" in fine.stdout, fine.stdout
    assert resolve_config(RunConfig, tuned / "config.toml").network.width == 64
    tuned_params, tuned_counters = policy_params(tuned, template)
    assert tuned_counters["init_from_env_steps"] == 2 * STEPS and tuned_counters["update"] == 1, tuned_counters
    assert 0 < max_distance(tuned_params, shipped_params) < 0.01, "one update from the shipped policy"
    fresh = jax.jit(built.trainer.init)(jax.random.PRNGKey(TUNE_SEED), built.levels).train.params
    assert max_distance(fresh, shipped_params) > 0.5, "a fresh network of the fine-tuning seed is far from it"

    # The same in distributed mode: `impulse launch --init-from` (learner and one actor as processes on loopback),
    # one update of the distributed tests' tiny batch (their programs, through the compilation cache).
    launched = tmp_path / "launched"
    fine = impulse("launch", "--init-from", str(shipped), f"run_dir={launched}", "--config", str(QUICK),
                   f"name={launched.name}", f"bus.hub=tcp/127.0.0.1:{free_port()}", *TINY_BATCH,
                   f"total_env_steps={8 * 8}", "checkpoint.every_updates=1", "eval.attempts=0", "network.width=32",
                   f"seed={TUNE_SEED}", "actors.num_actors=1", "--status-every", "5")
    assert fine.returncode == 0, fine.stdout
    assert f"run {launched.name} in {launched}: learner, 1 actor; logs in" in fine.stdout, fine.stdout
    assert "Logging error" not in fine.stdout, fine.stdout
    assert "fine-tuning the policy of" in (launched / "logs" / "learner.log").read_text()
    assert resolve_config(RunConfig, launched / "config.toml").network.width == 64
    launched_params, launched_counters = policy_params(launched, template)
    assert launched_counters["init_from_env_steps"] == 2 * STEPS and launched_counters["update"] == 1, (
        launched_counters)
    assert 0 < max_distance(launched_params, shipped_params) < 0.01, "one update from the shipped policy"

    capsys.readouterr()
    assert main(["train", "--init-from", str(tmp_path / "nowhere"), f"run_dir={tmp_path / 'x'}", *SETTINGS]) == 2
    refused = capsys.readouterr().err
    assert "--init-from" in refused and "config.toml" in refused, refused
    assert main(["launch", "--init-from", str(shipped), "--resume", str(launched)]) == 2
    refused = capsys.readouterr().err
    assert "--init-from starts a new run and --resume continues one" in refused, refused
    empty = tmp_path / "empty"  # a config.toml but no checkpoint: refused before anything starts
    empty.mkdir()
    (empty / "config.toml").write_text((shipped / "config.toml").read_text())
    assert main(["launch", "--init-from", str(empty), f"run_dir={tmp_path / 'y'}", "--config", str(QUICK),
                 f"bus.hub=tcp/127.0.0.1:{free_port()}"]) == 1
    refused = capsys.readouterr().err
    assert "--init-from: no checkpoint in" in refused, refused
    assert not (tmp_path / "y").exists()

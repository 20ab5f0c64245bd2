"""The README's main job learns: `configs/quick-cpu.toml` (a small entity network on our easy one-wheel car)
reaches a 90% solve rate on CPU, starting from a policy that rarely solves the level; its periodic evaluation
(`eval.every_updates`) writes the same `eval/...` columns the evaluator process gives a distributed run."""

from __future__ import annotations

import json

import jax
import pytest

from impulse.deploy.commands.train import train_run
from impulse.deploy.config import config_to_toml, resolve_config
from impulse.deploy.run_config import RunConfig
from impulse.learner.evaluate import evaluate
from impulse.learner.run import build
from impulse.monitor.runs import EVAL_COLUMNS, SHARED_COLUMNS
from tests.support.paths import REPO

pytestmark = pytest.mark.heavy


QUICK = REPO / "configs" / "quick-cpu.toml"


def test_quick_cpu_config_learns_the_easy_car(tmp_path):
    config = resolve_config(RunConfig, QUICK, ["eval.every_updates=10"])
    trainer, agent, names, levels = build(config)
    untrained = jax.jit(trainer.init)(jax.random.PRNGKey(config.seed), levels)
    before = evaluate(agent, untrained.train.params, trainer.env_params, levels, jax.random.PRNGKey(5), attempts=20)
    assert before.solve_rate.max() < 0.5, f"the untrained policy already solves it: {before.solve_rate}"

    summary = train_run(config, tmp_path, config_to_toml(config))
    assert summary.env_steps == config.total_env_steps
    assert summary.eval_scores is not None
    solved = summary.eval_scores[names[0]]["solve_rate"]
    assert solved >= 0.9, f"solve rate after training {solved:.0%}: {summary.eval_scores}"
    assert json.loads((tmp_path / "eval.json").read_text())[names[0]]["solve_rate"] == solved
    rows = [json.loads(line) for line in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    assert len(rows) == summary.updates
    # The columns both modes write (tests/deploy/test_launch_faults.py checks a distributed run's rows).
    assert {row["update"]: sorted(set(SHARED_COLUMNS) - row.keys()) for row in rows
            if not set(SHARED_COLUMNS) <= row.keys()} == {}
    evaluated = [row for row in rows if "eval/mean" in row]
    assert all(set(EVAL_COLUMNS) <= row.keys() for row in evaluated), evaluated
    assert [row["update"] for row in evaluated] == list(range(10, summary.updates + 1, 10))
    assert all(row["eval/policy_version"] == row["update"] for row in evaluated)
    assert evaluated[-1][f"eval/level/{names[0]}"] >= 0.5, evaluated[-1]  # the trained policy, as eval.json says


def test_evaluation_is_reproducible_with_a_fixed_seed():
    config = resolve_config(RunConfig, QUICK)
    trainer, agent, _, levels = build(config)
    carry = jax.jit(trainer.init)(jax.random.PRNGKey(1), levels)
    # As many attempts as the evaluations above: the same program, through the compilation cache.
    runs = [evaluate(agent, carry.train.params, trainer.env_params, levels, jax.random.PRNGKey(7),
                     attempts=config.eval.attempts) for _ in range(2)]
    for a, b in zip(runs[0], runs[1], strict=True):
        assert (a == b).all()

"""A fused training run from a `TrainConfig`: levels, trainer, progress, metrics, checkpoints, resume, final
evaluation. `impulse train` is a thin wrapper around `train_run`.

Run directory layout: `config.toml` (the resolved config, written by the command), `metrics.jsonl` (one line per
update), `checkpoints/<update>/` (orbax), `eval.json` (the final evaluation).
A run killed at any point resumes from its newest complete checkpoint with `--resume`; the iterations after it
are recomputed exactly, so the resumed run ends with the same parameters as one that was never interrupted.
"""

from __future__ import annotations

import json
import logging
import math
import signal
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import jax
import numpy as np

from engine.env.spec import env_from_config
from engine.levels.level import Level
from engine.levels.sets import HANDMADE, RANDOM, load_level_set
from learner.agent import Agent, make_agent
from learner.checkpoint import Checkpointer, CheckpointError
from learner.config import TrainConfig
from learner.evaluate import LevelScores, evaluate
from learner.fused import FusedCarry, FusedTrainer
from learner.networks import describe_parameters
from learner.progress import MetricsFile, ProgressLine

log = logging.getLogger(__name__)


class RunError(RuntimeError):
    """A run cannot start or resume (existing run directory, mismatched checkpoint, no levels)."""


@dataclass
class RunSummary:
    updates: int
    env_steps: int
    compile_s: float
    steps_per_s: float
    final_metrics: dict[str, float]
    eval_scores: dict[str, dict[str, float]] | None


def _random_level_sampler(config: TrainConfig, sizes):
    from engine.levels.generator import sample_random_level  # only random runs pay for the generator's import

    num = config.ppo.num_envs

    def sample(key):
        return jax.vmap(sample_random_level, in_axes=(0, None))(jax.random.split(key, num), sizes)

    return sample


def _levels(config: TrainConfig, sizes) -> tuple[list[str], Level | None]:
    if config.env.levels == RANDOM:
        return [], None
    try:
        return load_level_set(config.env.levels, sizes)
    except ValueError as err:
        raise RunError(str(err)) from err


def _eval_levels(config: TrainConfig, sizes, train_names: list[str], train_levels: Level | None):
    source = config.eval.levels or (HANDMADE if train_levels is None else "")
    if not source:
        return train_names, train_levels
    try:
        return load_level_set(source, sizes)
    except ValueError as err:
        log.warning("no evaluation: %s", err)
        return [], None


def _scores_table(names: list[str], scores: LevelScores) -> dict[str, dict[str, float]]:
    return {
        name: {
            "solve_rate": float(scores.solve_rate[i]),
            "mean_return": float(scores.mean_return[i]),
            "mean_length": float(scores.mean_length[i]),
        }
        for i, name in enumerate(names)
    }


def format_scores(table: dict[str, dict[str, float]]) -> str:
    """A terminal table of per-level evaluation scores."""
    width = max([len(n) for n in table] + [5])
    lines = [f"{'level':<{width}}  solved  return  length"]
    for name, s in table.items():
        lines.append(f"{name:<{width}}  {s['solve_rate']:>6.0%}  {s['mean_return']:>6.3f}  {s['mean_length']:>6.1f}")
    if table:
        mean = np.mean([s["solve_rate"] for s in table.values()])
        lines.append(f"{'mean':<{width}}  {mean:>6.0%}")
    return "\n".join(lines)


class _StopFlag:
    """SIGINT/SIGTERM ask the loop to checkpoint and stop at the end of the current update."""

    def __init__(self) -> None:
        self.stop = False
        self._previous: dict[int, Any] = {}

    def __enter__(self) -> _StopFlag:
        for sig in (signal.SIGINT, signal.SIGTERM):
            self._previous[sig] = signal.signal(sig, self._handle)
        return self

    def _handle(self, signum, frame) -> None:
        if self.stop:  # second signal: give up at once
            raise KeyboardInterrupt
        log.warning("stopping after this update (checkpointing first); send again to abort")
        self.stop = True

    def __exit__(self, *exc) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)


def build(config: TrainConfig) -> tuple[FusedTrainer, Agent, list[str], Level | None]:
    spec, env_params = env_from_config(config.env)
    agent = make_agent(config.network, spec)
    names, levels = _levels(config, spec.sizes)
    steps_per_update = config.ppo.num_envs * config.ppo.num_steps
    num_updates = max(1, math.ceil(config.total_env_steps / steps_per_update))
    sampler = _random_level_sampler(config, spec.sizes) if levels is None else None
    trainer = FusedTrainer(agent, env_params, config.ppo, num_updates, sample_levels=sampler)
    return trainer, agent, names, levels


def train_run(
    config: TrainConfig,
    run_dir: Path,
    config_toml: str,
    resume: bool = False,
    stop_after_updates: int | None = None,
) -> RunSummary:
    """Train until `config.total_env_steps` (or `stop_after_updates` more updates, for tests and benchmarks)."""
    trainer, agent, names, levels = build(config)
    steps_per_update = config.ppo.num_envs * config.ppo.num_steps
    checkpoints = Checkpointer(run_dir / config.checkpoint.directory, config.checkpoint)
    if not resume and checkpoints.latest_step() is not None:
        checkpoints.close()
        raise RunError(f"{run_dir} already holds checkpoints: resume it with --resume, or choose another name")

    init, iterate = trainer.jitted()
    key = jax.random.PRNGKey(config.seed)
    carry: FusedCarry = init(key, levels)
    log.info(
        "network %s, %s parameters:\n%s",
        config.network.kind,
        f"{sum(x.size for x in jax.tree.leaves(carry.train.params)):,}",
        describe_parameters(carry.train.params),
    )
    update = 0
    if resume:
        step = checkpoints.latest_step()
        if step is None:
            raise RunError(f"nothing to resume: no complete checkpoint in {checkpoints.directory}")
        try:
            carry, counters, _ = checkpoints.restore(carry, step)
        except CheckpointError as err:
            raise RunError(str(err)) from err
        update = int(counters["update"])
        log.info("resumed from checkpoint %d (update %d, %s env steps)", step, update, f"{counters['env_steps']:,}")

    start = time.perf_counter()
    compiled = iterate.lower(carry, levels).compile()
    compile_s = time.perf_counter() - start
    log.info("compiled the training step in %.1f s (%s envs x %s steps)", compile_s, config.ppo.num_envs,
             config.ppo.num_steps)

    metrics_file = MetricsFile(run_dir / "metrics.jsonl")
    target = trainer.num_updates
    if stop_after_updates is not None:
        target = min(target, update + stop_after_updates)
    progress = ProgressLine(trainer.num_updates * steps_per_update)
    window: list[dict[str, float]] = []
    last: dict[str, float] = {}
    config_text = config_toml
    run_start = time.perf_counter()
    steps_done_here = 0
    try:
        with _StopFlag() as stop:
            while update < target and not stop.stop:
                t0 = time.perf_counter()
                carry, metrics = compiled(carry, levels)
                metrics = {k: float(v) for k, v in jax.device_get(metrics).items()}
                update += 1
                steps_done_here += steps_per_update
                elapsed = time.perf_counter() - t0
                record = {
                    "update": update,
                    "env_steps": update * steps_per_update,
                    "steps_per_s": steps_per_update / elapsed,
                    "time_s": round(time.time(), 3),
                    **metrics,
                }
                metrics_file.write(record)
                window = (window + [record])[-max(1, config.checkpoint.every_updates) :]
                last = record
                progress.update(update * steps_per_update, steps_done_here / (time.perf_counter() - run_start),
                                _window_summary(window))
                if update % config.checkpoint.every_updates == 0 or update == target or stop.stop:
                    _save(checkpoints, update, steps_per_update, carry, config_text, window)
            if stop.stop and update % config.checkpoint.every_updates:
                _save(checkpoints, update, steps_per_update, carry, config_text, window)
    finally:
        progress.close()
        metrics_file.close()
        checkpoints.close()

    train_time = time.perf_counter() - run_start
    scores_table = None
    if update >= trainer.num_updates and config.eval.attempts > 0:
        eval_names, eval_levels = _eval_levels(config, agent.spec.sizes, names, levels)
        if eval_levels is not None and eval_names:
            scores = evaluate(agent, carry.train.params, trainer.env_params, eval_levels,
                              jax.random.PRNGKey(config.seed + 1), attempts=config.eval.attempts)
            scores_table = _scores_table(eval_names, scores)
            (run_dir / "eval.json").write_text(json.dumps(scores_table, indent=2))
            log.info("evaluation over %d attempts per level:\n%s", config.eval.attempts, format_scores(scores_table))
    return RunSummary(
        updates=update,
        env_steps=update * steps_per_update,
        compile_s=compile_s,
        steps_per_s=steps_done_here / train_time if train_time > 0 else 0.0,
        final_metrics=last,
        eval_scores=scores_table,
    )


def _window_summary(window: list[dict[str, float]]) -> dict[str, float]:
    """Solve rate and return over the episodes that ended in the recent updates (not a mean of means)."""
    episodes = sum(r["episodes"] for r in window)
    if episodes == 0:
        return {"episodes": 0}
    return {
        "episodes": int(episodes),
        "solve_rate": sum(r["solved"] for r in window) / episodes,
        "episode_return": sum(r["return_sum"] for r in window) / episodes,
    }


def _save(checkpoints: Checkpointer, update: int, steps_per_update: int, carry: FusedCarry, config_text: str,
          window: list[dict[str, float]]) -> None:
    summary = _window_summary(window)
    counters = {"update": update, "env_steps": update * steps_per_update, **summary}
    checkpoints.save(update, carry, counters, config_text, solve_rate=summary.get("solve_rate"))


def evaluate_run(
    config: TrainConfig,
    run_dir: Path,
    step: int | None = None,
    levels: str | None = None,
    attempts: int | None = None,
    seed: int = 0,
    greedy: bool = False,
) -> dict[str, dict[str, float]]:
    """Scores per level of a run's checkpoint (newest unless `step`), on `levels` (default: as after training)."""
    trainer, agent, names, train_levels = build(config)
    sizes = agent.spec.sizes
    if levels:
        try:
            eval_names, eval_levels = load_level_set(levels, sizes)
        except ValueError as err:
            raise RunError(str(err)) from err
    else:
        eval_names, eval_levels = _eval_levels(config, sizes, names, train_levels)
        if eval_levels is None:
            raise RunError("no evaluation levels: pass --levels")
    template = jax.jit(trainer.init)(jax.random.PRNGKey(config.seed), train_levels)
    with Checkpointer(run_dir / config.checkpoint.directory, config.checkpoint) as checkpoints:
        try:
            carry, _, _ = checkpoints.restore(template, step)
        except CheckpointError as err:
            raise RunError(str(err)) from err
    scores = evaluate(agent, carry.train.params, trainer.env_params, eval_levels, jax.random.PRNGKey(seed),
                      attempts=attempts or config.eval.attempts, greedy=greedy)
    return _scores_table(eval_names, scores)

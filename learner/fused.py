"""Fused training: level sampling, rollout and PPO update composed into one jitted iteration on one device.

The iteration is the same rollout (`actors.rollout.rollout`) and update (`learner.update.ppo_update`) that the
distributed services use, so fused mode is both the fastest single-device trainer and the baseline the
distributed mode is measured against.

Everything an iteration depends on lives in `FusedCarry` (parameters, optimiser state, every environment's state
and observation, the random key), and the iteration is a pure function of it. Checkpointing the carry therefore
makes a resumed run continue bit for bit.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from impulse.actors.rollout import RolloutCarry, rollout, start_rollout
from impulse.actors.trajectory import episode_metrics, make_batch
from impulse.curriculum.methods import Curriculum
from impulse.curriculum.state import ORIGIN_MUTATED, ORIGIN_NEW, ORIGIN_REPLAY, CurriculumState
from impulse.engine.env.spec import EnvParams, EnvSpec
from impulse.engine.levels.level import Level
from impulse.learner.agent import Agent
from impulse.learner.config import PPOConfig
from impulse.learner.curriculum_inputs import batch_level_results
from impulse.learner.evaluate import solve_rates
from impulse.learner.update import TrainState, make_optimizer, ppo_update

Array = jax.Array


class FusedCarry(NamedTuple):
    train: TrainState
    envs: RolloutCarry
    key: Array
    curriculum: CurriculumState | None = None


@dataclass(frozen=True)
class FusedTrainer:
    """The static parts of a fused run; `init` and `iterate` are its two pure (jitted) functions."""

    agent: Agent
    env_params: EnvParams
    ppo: PPOConfig
    num_updates: int
    curriculum: Curriculum | None = None
    """For random levels: the curriculum that picks every iteration's level batch (its state rides in the
    carry). None: the fixed batch passed to `iterate`."""

    @property
    def spec(self) -> EnvSpec:
        return self.agent.spec

    @functools.cached_property
    def optimizer(self):
        return make_optimizer(self.ppo, self.num_updates)

    def init_train(self, key: Array) -> TrainState:
        """Fresh parameters from `key` with a fresh optimizer state, at policy version 0: the `train` part of
        `init`, and, through `jax.eval_shape`, the shapes a checkpoint's policy is restored into (without tracing
        environments or a curriculum)."""
        params = self.agent.init(key)
        return TrainState(params, self.optimizer.init(params), jnp.zeros((), jnp.int32))

    def init(self, key: Array, levels: Level | None) -> FusedCarry:
        """Fresh parameters and `ppo.num_envs` environments started on the level batch (staggered): the fixed
        one, or the curriculum's first."""
        init_key, level_key, env_key, key = jax.random.split(key, 4)
        train = self.init_train(init_key)
        curriculum, flags = None, None
        if self.curriculum is not None:
            curriculum_key, sample_key = jax.random.split(level_key)
            curriculum, batch = self.curriculum.sample(self.curriculum.init(curriculum_key), sample_key)
            levels, flags = batch.levels, batch.train
        envs = start_rollout(self.spec, self.env_params, levels, self.ppo.num_envs, env_key, flags)
        return FusedCarry(train, envs, key, curriculum)

    def iterate(self, carry: FusedCarry, levels: Level | None) -> tuple[FusedCarry, dict[str, Array]]:
        """Pick the levels (curriculum), one rollout of `ppo.num_steps` steps in every environment, one PPO update,
        then the curriculum learns from the levels' results."""
        key, level_key, update_key = jax.random.split(carry.key, 3)
        curriculum, flags, origin_metrics = carry.curriculum, None, {}
        if self.curriculum is not None and self.curriculum.batch_scored:
            # Due before the first update too (Kinetix fills its buffer before training starts).
            version = carry.train.policy_version
            due = version % self.curriculum.config.sfl_refresh_updates == 0
            refill_key = jax.random.fold_in(level_key, 1)  # the other curricula's random streams stay as they were
            curriculum = jax.lax.cond(
                due, lambda c: self.refill_curriculum(c, carry.train.params, refill_key, version), lambda c: c,
                curriculum)
        if self.curriculum is not None:
            curriculum, chosen = self.curriculum.sample(curriculum, level_key)
            levels, flags = chosen.levels, chosen.train
            origin_metrics = {f"levels_{name}": (chosen.origin == origin).mean() for name, origin in
                              (("new", ORIGIN_NEW), ("replay", ORIGIN_REPLAY), ("mutated", ORIGIN_MUTATED))}
        acting = carry.train.params
        envs, trajectory, train_mask, stats, _ = rollout(
            self.agent.act, acting, self.spec, self.env_params, carry.envs, levels, self.ppo.num_steps, flags,
            restart=self.ppo.restart_envs,
        )
        # The parameters that acted are the ones trained, so the batch's version equals the learner's: lag 0.
        batch = make_batch(trajectory, envs.obs, carry.train.policy_version, train_mask=train_mask, episodes=stats)
        train, losses = ppo_update(
            carry.train,
            batch,
            update_key,
            apply_fn=self.agent.apply,
            distribution=self.agent.distribution,
            optimizer=self.optimizer,
            config=self.ppo,
        )
        if self.curriculum is not None:
            rows = self.ppo.num_envs + self.curriculum.batch_size
            results = batch_level_results(self.agent, self.ppo, acting, batch, rows)
            curriculum = self.curriculum.update(curriculum, results)
        metrics = {
            **losses,
            **episode_metrics(stats),
            "reward_per_step": trajectory.reward.mean(),
            **origin_metrics,
        }
        return FusedCarry(train, envs, key, curriculum), metrics

    def refill_curriculum(self, curriculum: CurriculumState, params: Any, key: Array,
                          policy_version: Array) -> CurriculumState:
        """Batch-scored SFL: `sfl_candidates` fresh levels, each played `sfl_attempts` times by `params`, and the
        buffer refilled with the most learnable of them (`Curriculum.refill`). Its episodes are not training
        steps and are not counted in the run's env steps, as in Kinetix."""
        config = self.curriculum.config
        level_key, play_key = jax.random.split(key)
        candidates = self.curriculum.new_levels(level_key, config.sfl_candidates)
        rates = solve_rates(self.agent, params, self.env_params, candidates, play_key, config.sfl_attempts)
        return self.curriculum.refill(curriculum, candidates, rates, policy_version)

    def jitted(self) -> tuple[Callable[..., FusedCarry], Callable[..., tuple[FusedCarry, dict[str, Any]]]]:
        """(init, iterate) compiled; `iterate` donates its carry so the environments are updated in place."""
        return jax.jit(self.init), jax.jit(self.iterate, donate_argnums=0)
